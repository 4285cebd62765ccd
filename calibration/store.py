"""The calibration store: one zarr v3 directory holding everything a calibration measured.

Layout::

    calib.zarr/               attrs: format "lfpiv-calibration", format_version, rig (as
                              loaded), created, software_version
      <camera>/white          uint16 (rows, columns): the averaged white image
      <camera>/dark           uint16 (rows, columns): the averaged dark image (lens capped, no
                              light), when one was taken or given
      <camera>/mla/centres_px float64 (n, 2): detected micro-image centres (column, row);
                              attrs: pitch_px, rotation_deg, offset_px, grid, rms_px, ...
      <camera>/mla/indices    int64 (n, 2): lattice indices of each centre
      <camera>/mla/residuals_px  float64 (n, 2): measured minus fitted centre
      <camera>/mla/inliers    bool (n,): the centres the lattice was fitted to
      <camera>/planes/frames  uint16 (planes, rows, columns): the dot target at each plane
      <camera>/planes/stage_mm   float64 (planes,): stage readback, NaN while not yet taken
      <camera>/planes/target_mm  float64 (planes,): where the stage was sent
      <camera>/model          attrs only: the fitted camera model (when fitted): camera (a
                              rig-file [[camera]] table), rms_px, plane_rms_px, plane_dots, ...;
                              a pinhole camera's also its Soloff polynomial (soloff, soloff_rms_px,
                              soloff_plane_rms_px)
      <camera>/selfcal        pinhole cameras, after a volume self-calibration: attrs camera (the
                              corrected model), soloff (corrected), the run, frames, rms_px and
                              max_px per pass; disparity_px float32 (passes, nz, ny, nx, 2) the
                              disparity maps, matches int64 (passes, nz, ny, nx)

Root attrs ``target`` hold the dot board (:class:`lfcore.target.DotBoard`) of the planes.

Every array carries ``units``, ``axes`` and ``description`` attributes, like the run store
(:mod:`lfcore.runstore`), so a user with plain zarr can read a calibration without lfpiv. A plane
is done when its ``stage_mm`` is finite: an interrupted volumetric run resumes from the others.

Every other write is atomic: the white and dark images and the grid of a camera (or its fitted
model) are written into ``<camera>/update.staged/``, whose ``commit`` attribute, written last, is
the point of no return; the new items are then renamed into place (the old ones through
``<camera>/update.old/``, deleted after). An interrupt before the commit leaves the old content
(the staged group is deleted when the store is next opened), one after it the new (the renames
are finished when the store is next opened). A store that ``calibrate mla`` creates carries the
root attribute ``unfinished`` until its first calibration is written; readers refuse it.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import shutil
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from calibration.mla_grid import MlaGrid
from lfcore.rig import Rig, camera_from_dict, is_pinhole, rotation_angle_deg
from lfcore.runstore import FRAME_CODEC
from lfcore.target import DotBoard
from lfcore.zarrstore import RigStore, described_array

__all__ = ["FORMAT", "FORMAT_VERSION", "CalibrationStore", "CalibrationStoreError", "UnfinishedCalibrationError"]

FORMAT = "lfpiv-calibration"
FORMAT_VERSION = 1
_CODEC = FRAME_CODEC  # white and plane images are raw camera frames too


class CalibrationStoreError(ValueError):
    """A calibration store that cannot be created or read; one line saying what to do."""


class UnfinishedCalibrationError(CalibrationStoreError):
    """A calibration store whose first calibration was interrupted before it was written."""


class CalibrationStore(RigStore):
    """Read and write access to one calibration store.

    Use :meth:`open_or_create` (the calibrate commands add to one store step by step),
    :meth:`create` or :meth:`open`.
    """

    FORMAT = FORMAT
    FORMAT_VERSION = FORMAT_VERSION
    KIND = "lfpiv calibration store"
    HINT = "give the path of a calibration store (made by 'lfpiv calibrate mla' or 'lfpiv calibrate volume')"
    Error = CalibrationStoreError

    # --- creation and opening -----------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, rig: Rig, *, software_version: str = "", overwrite: bool = False,
               unfinished: str | None = None) -> CalibrationStore:
        """Create an empty store for ``rig``.

        ``unfinished`` (the command that creates it) marks the store as not yet calibrated until
        :meth:`finish`: readers refuse it, so an interrupted first calibration is never taken for one.

        Raises
        ------
        CalibrationStoreError
            If ``path`` exists and ``overwrite`` is false.
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise CalibrationStoreError(f"{path} already exists; choose another path or pass --overwrite")
        root = zarr.open_group(str(path), mode="w", zarr_format=3)
        root.attrs.update({
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "rig": rig.to_dict(),
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "software_version": software_version,
            **({"unfinished": unfinished} if unfinished else {}),
        })
        for cam in rig.camera:
            root.create_group(cam.name).attrs.update({"sensor_px": list(cam.sensor_px)})
        return cls(root, path)

    @classmethod
    def open(cls, path: str | Path, mode: str = "r", *, resume: bool = False) -> CalibrationStore:
        """Open an existing store (``mode`` ``"r"`` or ``"r+"``); ``resume``: an unfinished one too.

        An update interrupted after its commit is completed, one interrupted before it is
        discarded (see the module's notes).

        Raises
        ------
        CalibrationStoreError
            If ``path`` does not exist, is not a calibration store, or is unfinished.
        """
        path = Path(path)
        root = cls._open_root(path, mode)
        store = cls(root, path)
        store._recover()
        unfinished = root.attrs.get("unfinished")
        if unfinished and not resume:
            raise UnfinishedCalibrationError(f"{path} is an unfinished calibration ('lfpiv {unfinished}' was "
                                             f"interrupted before it wrote one); run it again with --out {path}, or "
                                             f"delete {path}")
        return store

    @classmethod
    def open_or_create(cls, path: str | Path, rig: Rig, *, software_version: str = "",
                       unfinished: str | None = None) -> CalibrationStore:
        """Open the store at ``path`` for writing if it exists (it must be for the same cameras),
        else create it (marked ``unfinished`` when given, see :meth:`create`); an unfinished store
        is opened to be finished."""
        path = Path(path)
        if not path.exists():
            return cls.create(path, rig, software_version=software_version, unfinished=unfinished)
        store = cls.open(path, mode="r+", resume=True)
        theirs = {c["name"]: tuple(c["sensor_px"]) for c in store.group.attrs["rig"]["camera"]}
        ours = {c.name: tuple(c.sensor_px) for c in rig.camera}
        if theirs != ours:
            raise CalibrationStoreError(f"{path} holds a calibration of other cameras ({sorted(theirs)}); "
                                        "give a new --out path")
        changed = _first_change(store.rig, rig)
        if changed:
            # its white images, grids and planes were taken, and dots named, with the nominal
            # optics in the store: mixing in planes of other optics would spoil the fit
            raise CalibrationStoreError(f"{path} was made with another rig ({changed}); give a new --out path, or "
                                        "the rig file it was made with")
        return store

    # --- metadata -----------------------------------------------------------------------
    def _camera(self, camera: str) -> zarr.Group:
        if camera not in self.cameras:
            raise CalibrationStoreError(f"{self.path} has no camera '{camera}' (it has {self.cameras})")
        return self.group[camera]

    # --- atomic updates -----------------------------------------------------------------
    def _update(self, camera: str, build: Callable[[zarr.Group], list[str]], *, remove: tuple[str, ...] = ()) -> None:
        """Replace items of ``camera`` atomically: ``build`` writes the new ones into a staged group
        and returns their names; they, and ``remove``, replace the old ones only once all are written.
        SIGINT, SIGTERM and SIGHUP wait until it is done (then act as they would have)."""
        g = self._camera(camera)
        here = Path(self.path) / camera
        with _signals_held():
            _settle(here)
            staged = g.create_group(_STAGED, overwrite=True)
            names = build(staged)
            # the commit point: one file written atomically (zarr writes beside and renames)
            staged.attrs["commit"] = {"replace": list(names), "remove": [n for n in remove if n not in names]}
            _settle(here)

    def _recover(self) -> None:
        """Finish or discard the updates an interrupt left (best effort on a read-only store)."""
        for name in self.cameras:
            with contextlib.suppress(OSError):
                _settle(Path(self.path) / name)

    def finish(self) -> None:
        """Clear the ``unfinished`` mark of a store's first calibration (it holds one now)."""
        if "unfinished" in self.group.attrs:
            del self.group.attrs["unfinished"]

    # --- white image and microlens grid ---------------------------------------------------
    @staticmethod
    def _image(g: zarr.Group, name: str, image: np.ndarray, what: str, frames_averaged: int) -> str:
        img = np.clip(np.rint(np.asarray(image, dtype=np.float64)), 0, 65535).astype(np.uint16)
        a = described_array(g, name, "counts", ["row", "column"], what, shape=img.shape, chunks=img.shape,
                            dtype=np.uint16, compressors=_CODEC, overwrite=True)
        a[...] = img
        a.attrs["frames_averaged"] = int(frames_averaged)
        return name

    def write_white(self, camera: str, image: np.ndarray, *, frames_averaged: int = 1) -> None:
        """Store the (rows, columns) white image of ``camera``, rounded to uint16 (atomically)."""
        self._update(camera, lambda st: [self._image(st, "white", image, "white (uniformly lit) image, mean of "
                                                     "frames", frames_averaged)])

    def white(self, camera: str) -> np.ndarray | None:
        """The white image of ``camera`` (rows, columns) uint16, or None if not taken."""
        g = self._camera(camera)
        return g["white"][...] if "white" in g else None

    def write_dark(self, camera: str, image: np.ndarray, *, frames_averaged: int = 1) -> None:
        """Store the (rows, columns) dark image of ``camera``, rounded to uint16 (atomically)."""
        self._update(camera, lambda st: [self._image(st, "dark", image, "dark image (no light: lens capped, laser "
                                                     "off), mean of frames", frames_averaged)])

    def dark(self, camera: str) -> np.ndarray | None:
        """The dark image of ``camera`` (rows, columns) uint16, or None if not taken."""
        g = self._camera(camera)
        return g["dark"][...] if "dark" in g else None

    def write_mla(self, camera: str, *, white: np.ndarray, grid: MlaGrid, mla: dict[str, Any] | None = None,
                  white_frames: int = 1, dark: np.ndarray | None = None, dark_frames: int = 1) -> bool:
        """Store ``camera``'s white image, its dark image (where given) and its microlens grid in one
        atomic update: an interrupt leaves all three as they were or all new.

        A fitted model of ``camera`` is removed: its dots were found through the earlier grid.

        Returns
        -------
        bool
            Whether a fitted model was removed.
        """
        stale = "model" in self._camera(camera)

        def build(st: zarr.Group) -> list[str]:
            names = [self._image(st, "white", white, "white (uniformly lit) image, mean of frames", white_frames)]
            if dark is not None:
                names.append(self._image(st, "dark", dark, "dark image (no light: lens capped, laser off), mean of "
                                         "frames", dark_frames))
            self._grid_group(st.create_group("mla"), grid, mla)
            return [*names, "mla"]

        self._update(camera, build, remove=("model",))
        return stale

    def write_grid(self, camera: str, grid: MlaGrid, *, mla: dict[str, Any] | None = None) -> bool:
        """Store the detected microlens grid of ``camera`` (replacing any earlier one, atomically).

        ``mla`` is :meth:`MlaGrid.to_mla` of the nominal camera, kept as attributes. A fitted
        model of ``camera`` is removed: its dots were found through the earlier grid.

        Returns
        -------
        bool
            Whether a fitted model was removed.
        """
        stale = "model" in self._camera(camera)
        self._update(camera, lambda st: (self._grid_group(st.create_group("mla"), grid, mla), ["mla"])[1],
                     remove=("model",))
        return stale

    @staticmethod
    def _grid_group(m: zarr.Group, grid: MlaGrid, mla: dict[str, Any] | None) -> None:
        n = grid.n_lenslets
        arrays = (
            ("centres_px", grid.centres_px, np.float64, "px", ["lenslet", "column_row"],
             "measured micro-image centres (column, row) in continuous pixel coordinates: pixel [row, column] "
             "covers column..column+1, row..row+1, so its centre is (column + 0.5, row + 0.5)"),
            ("indices", grid.indices, np.int64, "1", ["lenslet", "n1_n2"], "lattice indices along basis_px"),
            ("residuals_px", grid.residuals_px, np.float64, "px", ["lenslet", "column_row"],
             "measured minus fitted centre"),
            ("inliers", grid.inliers, bool, "1", ["lenslet"], "centres the lattice was fitted to"),
        )
        for name, data, dtype, units, axes, what in arrays:
            shape = (n, 2) if data.ndim == 2 else (n,)
            described_array(m, name, units, axes, what, shape=shape, chunks=shape, dtype=dtype,
                            overwrite=True)[...] = np.asarray(data, dtype=dtype)
        m.attrs.update({
            "grid": grid.grid, "pitch_px": grid.pitch_px, "rotation_deg": grid.rotation_deg,
            "offset_px": list(grid.offset_px), "rms_px": grid.rms_px, "origin_px": list(grid.origin_px),
            "basis_px": np.asarray(grid.basis_px).tolist(), "image_shape": list(grid.image_shape),
            "n_lenslets": n, "n_inliers": int(np.sum(grid.inliers)),
            "description": "micro-image lattice from the white image; rotation_deg in the sensor-plane frame "
                           "(sign of Camera.mla_rotation_deg); offset_px: lattice node nearest the sensor centre "
                           "minus the centre (column, row)",
            "mla": dict(mla or {}),
        })

    def grid(self, camera: str) -> MlaGrid | None:
        """The stored microlens grid of ``camera``, or None."""
        g = self._camera(camera)
        if "mla" not in g or "centres_px" not in g["mla"]:
            return None
        m = g["mla"]
        at = m.attrs
        return MlaGrid(grid=at["grid"], pitch_px=float(at["pitch_px"]), rotation_deg=float(at["rotation_deg"]),
                       offset_px=tuple(at["offset_px"]), image_shape=tuple(at["image_shape"]),
                       centres_px=m["centres_px"][...], indices=m["indices"][...],
                       residuals_px=m["residuals_px"][...], inliers=m["inliers"][...], rms_px=float(at["rms_px"]),
                       origin_px=tuple(at["origin_px"]), basis_px=np.asarray(at["basis_px"], dtype=np.float64))

    # --- volumetric calibration planes --------------------------------------------------
    def init_planes(self, targets_mm: np.ndarray, *, step_mm: float) -> None:
        """Create the plane arrays of every camera for stage targets ``targets_mm`` (planes,).

        If they exist with the same targets nothing changes (a resumed run); other targets are
        an error, so that planes of two different runs are never mixed.
        """
        targets = np.asarray(targets_mm, dtype=np.float64)
        for name in self.cameras:
            g = self._camera(name)
            if "planes" in g:
                old = g["planes/target_mm"][...]
                if old.shape != targets.shape or not np.allclose(old, targets, atol=1e-6):
                    raise CalibrationStoreError(
                        f"{self.path} holds planes at other stage positions ({len(old)} planes from "
                        f"{old[0]:g} mm); give the same --planes and --step-mm to resume, or a new --out path")
                continue
            cols, rows = g.attrs["sensor_px"]
            p = g.create_group("planes")
            p.attrs.update({"step_mm": float(step_mm),
                            "description": "the dot target at each stage position; a plane is done when its "
                                           "stage_mm is finite"})
            n = len(targets)
            described_array(p, "frames", "counts", ["plane", "row", "column"], "raw light-field image of the dot "
                            "target", shape=(n, rows, cols), chunks=(1, rows, cols), dtype=np.uint16, fill_value=0,
                            compressors=_CODEC)
            described_array(p, "stage_mm", "mm", ["plane"], "stage position read back after the move; NaN: not "
                            "taken yet", shape=(n,), chunks=(n,), dtype=np.float64, fill_value=np.nan)
            described_array(p, "target_mm", "mm", ["plane"], "stage position requested", shape=(n,), chunks=(n,),
                            dtype=np.float64)[...] = targets

    def write_plane(self, camera: str, plane: int, image: np.ndarray, stage_mm: float) -> None:
        """Store one plane's image; the readback is written last, so a plane is never marked done
        without its image."""
        p = self._camera(camera)["planes"]
        p["frames"][plane] = np.asarray(image, dtype=np.uint16)
        s = p["stage_mm"]
        s[plane] = float(stage_mm)

    def plane_targets(self) -> np.ndarray | None:
        """(planes,) requested stage positions, mm, or None if no volumetric run was started."""
        g = self._camera(self.cameras[0])
        return g["planes/target_mm"][...] if "planes" in g else None

    def stage_mm(self, camera: str) -> np.ndarray:
        """(planes,) stage readback of each plane of ``camera``, NaN where not taken."""
        return self._camera(camera)["planes/stage_mm"][...]

    def planes_done(self) -> np.ndarray:
        """(planes,) bool: planes taken by every camera."""
        done = [np.isfinite(self.stage_mm(c)) for c in self.cameras]
        return np.logical_and.reduce(done)

    def plane_frames(self, camera: str) -> zarr.Array:
        """(planes, rows, columns) uint16 images of ``camera``."""
        return self._camera(camera)["planes/frames"]

    # --- target and fitted models ---------------------------------------------------------
    def write_target(self, board: DotBoard) -> None:
        """Store the dot board (spacing, tilt, marker, where the stage puts it) as root attrs."""
        self.group.attrs["target"] = board.to_dict()

    def target(self) -> DotBoard | None:
        """The stored dot board, or None."""
        t = self.group.attrs.get("target")
        return DotBoard.from_dict(t) if t else None

    def write_model(self, camera: str, model: dict[str, Any], stats: dict[str, Any]) -> bool:
        """Store ``camera``'s fitted model (a rig-file camera table) and its fit statistics.

        A self-calibration of ``camera`` is removed: it corrected the earlier model.

        Returns
        -------
        bool
            Whether a self-calibration was removed.
        """
        stale = "selfcal" in self._camera(camera)

        def build(st: zarr.Group) -> list[str]:
            st.create_group("model").attrs.update({
                "camera": model, **stats, "description": "fitted camera model (rig-file [[camera]] table) and its "
                                                         "reprojection RMS (px) over all planes and per plane (NaN: "
                                                         "no dots)"})
            return ["model"]

        self._update(camera, build, remove=("selfcal",))
        return stale

    def model(self, camera: str) -> dict[str, Any] | None:
        """The fitted model attrs of ``camera`` (``camera``: the rig-file table, rms_px, ...), or None."""
        g = self._camera(camera)
        return dict(g["model"].attrs) if "model" in g else None

    def write_selfcal(self, camera: str, model: dict[str, Any], stats: dict[str, Any], maps_px: np.ndarray,
                      matches: np.ndarray) -> None:
        """Store a pinhole camera's self-calibrated model and the disparity maps that corrected it.

        Parameters
        ----------
        camera
            The camera's name.
        model
            The corrected model (a rig-file camera table).
        stats
            JSON-compatible attributes: the run, frames, rms_px and max_px per pass, ...
        maps_px
            (passes, nz, ny, nx, 2) this camera's disparity map of each pass, pixels.
        matches
            (passes, nz, ny, nx) matched particles per sub-volume.
        """
        g = self._camera(camera)
        if "model" not in g:
            raise CalibrationStoreError(f"camera '{camera}' has no fitted model in {self.path} to self-calibrate; "
                                        "run 'lfpiv calibrate fit' first")
        self._update(camera, lambda st: (self._selfcal_group(st.create_group("selfcal"), model, stats, maps_px,
                                                             matches), ["selfcal"])[1])

    @staticmethod
    def _selfcal_group(sc: zarr.Group, model: dict[str, Any], stats: dict[str, Any], maps_px: np.ndarray,
                       matches: np.ndarray) -> None:
        sc.attrs.update({"camera": model, **stats,
                         "description": "volume self-calibration (Wieneke 2008): the model corrected by the "
                                        "disparity maps of a recording's particles; pass 0 before, the last after"})
        m = np.asarray(maps_px, dtype=np.float32)
        described_array(sc, "disparity_px", "px", ["pass", "z", "y", "x", "column_row"], "disparity of each "
                        "sub-volume (particle minus the model's image of the triangulated point); NaN: too few "
                        "matches", shape=m.shape, chunks=m.shape, dtype=np.float32, fill_value=np.nan)[...] = m
        n = np.asarray(matches, dtype=np.int64)
        described_array(sc, "matches", "1", ["pass", "z", "y", "x"], "matched particles (true and ghost) per "
                        "sub-volume", shape=n.shape, chunks=n.shape, dtype=np.int64)[...] = n

    def selfcal(self, camera: str) -> dict[str, Any] | None:
        """The self-calibration attrs of ``camera`` (``camera``: the corrected model, rms_px, ...),
        or None."""
        g = self._camera(camera)
        return dict(g["selfcal"].attrs) if "selfcal" in g else None

    def fitted_rig(self) -> Rig:
        """The store's rig with every fitted camera replaced by its model.

        Raises
        ------
        CalibrationStoreError
            No camera has a fitted model.
        """
        rig = self.rig
        cams = []
        for cam in rig.camera:
            m = self.model(cam.name)
            cams.append(camera_from_dict(m["camera"]) if m else cam)
        if all(self.model(c.name) is None for c in rig.camera):
            raise CalibrationStoreError(f"{self.path} holds no fitted camera model; run 'lfpiv calibrate fit'")
        return rig.model_copy(update={"camera": tuple(cams)})

    # --- summary --------------------------------------------------------------------------
    def summary(self) -> list[str]:
        """What the store holds, one line per item, for ``lfpiv calibrate report``."""
        at = self.group.attrs
        lines = [f"{self.path}: lfpiv calibration (format {at['format_version']}), created {at['created']}, "
                 f"{len(self.cameras)} camera(s)"]
        for name in self.cameras:
            g = self._camera(name)
            white = self.white(name)
            if is_pinhole(self.rig.camera_named(name)):
                lines.append(f"  {name}: pinhole camera (no microlenses, no white image)")
            elif white is None:
                lines.append(f"  {name}: no white image (run 'lfpiv calibrate mla')")
            else:
                lines.append(f"  {name}: white image {white.shape[1]} x {white.shape[0]} px, "
                             f"mean of {g['white'].attrs.get('frames_averaged', 1)} frame(s), "
                             f"levels {np.percentile(white, 1):.0f}..{np.percentile(white, 99.5):.0f} counts")
                dark = self.dark(name)
                lines.append(f"  {name}: " + (f"dark image, mean of {g['dark'].attrs.get('frames_averaged', 1)} "
                                              f"frame(s), levels {np.percentile(dark, 1):.0f}.."
                                              f"{np.percentile(dark, 99.5):.0f} counts" if dark is not None else
                                              "no dark image (the flat field takes the white image's own floor)"))
            grid = self.grid(name)
            if grid is not None:
                mla = dict(g["mla"].attrs.get("mla", {}))
                lines.append(f"  {name}: MLA {grid.grid}, pitch {grid.pitch_px:.4f} px, rotation "
                             f"{grid.rotation_deg:+.4f} deg, offset ({grid.offset_px[0]:+.3f}, "
                             f"{grid.offset_px[1]:+.3f}) px, RMS {grid.rms_px:.4f} px over "
                             f"{int(grid.inliers.sum())} of {grid.n_lenslets} lenslets")
                if mla:
                    ox, oy = mla["mla_offset_um"]
                    lines.append(f"  {name}: lenslets (optical axis at the sensor centre): pitch "
                                 f"{mla['mla_pitch_um']:.3f} um, offset ({ox:+.2f}, {oy:+.2f}) um")
            if "planes" in g:
                done = np.isfinite(self.stage_mm(name))
                targets = g["planes/target_mm"][...]
                lines.append(f"  {name}: planes {int(done.sum())} of {len(done)} taken, stage "
                             f"{targets[0]:g}..{targets[-1]:g} mm in steps of {g['planes'].attrs['step_mm']:g} mm")
            if "model" in g:
                m = dict(g["model"].attrs)
                c = m["camera"]
                # Near ry = +-90 deg, rx and rz of R = Rz Ry Rx act about nearly one axis, so a tiny
                # turn moves both a lot (gimbal lock): the angle from the rig file's pose says more.
                turn = rotation_angle_deg(self.rig.camera_named(name).rotation_deg, c["rotation_deg"])
                pose = (f"magnification {c['magnification']:.5f}, rotation {[round(v, 4) for v in c['rotation_deg']]} "
                        f"deg ({turn:.4f} deg from the rig file's), focus {[round(v, 4) for v in c['focus_mm']]} mm")
                dots = f"over {sum(m['plane_dots'])} dots on {sum(1 for n in m['plane_dots'] if n)} planes"
                if c.get("kind") == "pinhole":
                    pp = c["principal_point_px"]
                    lines.append(f"  {name}: fitted pinhole model: {pose}, principal point ({pp[0]:+.3f}, "
                                 f"{pp[1]:+.3f}) px from the sensor centre, k1 {c['k1']:+.3g} k2 {c['k2']:+.3g} "
                                 f"p1 {c['p1']:+.3g} p2 {c['p2']:+.3g}")
                    lines.append(f"  {name}: reprojection RMS {m['rms_px']:.4f} px (pinhole), "
                                 f"{m['soloff_rms_px']:.4f} px (Soloff polynomial, cubic in x and y, quadratic in z) "
                                 f"{dots}")
                else:
                    lines.append(f"  {name}: fitted model: {pose}, MLA offset "
                                 f"({c['mla_offset_um'][0]:+.3f}, {c['mla_offset_um'][1]:+.3f}) um, rotation "
                                 f"{c['mla_rotation_deg']:+.4f} deg")
                    lines.append(f"  {name}: reprojection RMS {m['rms_px']:.4f} px {dots} (white-image lattice "
                                 f"{m['lattice_rms_px']:.4f} px)")
                sc = self.selfcal(name)
                if sc is not None:
                    rms, mine = sc["rms_px"], sc.get("camera_rms_px", sc["rms_px"])
                    lines.append(f"  {name}: self-calibrated on {sc['run']} ({sc['frames']} frames): its disparity "
                                 f"RMS {mine[0]:.3f} -> {mine[-1]:.3f} px (all cameras {rms[0]:.3f} -> {rms[-1]:.3f} "
                                 f"px) over {len(rms) - 1} correction(s)")
            else:
                lines.append(f"  {name}: no fitted camera model yet")
        return lines


def _first_change(stored: Rig, rig: Rig) -> str | None:
    """The first camera key (serial aside) or stage microstep that differs, as "key a, now b"."""
    for old in stored.camera:
        new = rig.camera_named(old.name)
        a, b = old.model_dump(exclude={"serial"}), new.model_dump(exclude={"serial"})
        if a["kind"] != b["kind"]:
            return f"camera '{old.name}' kind {a['kind']} in the store, {b['kind']} now"
        for key in a:
            if a[key] != b[key]:
                return f"camera '{old.name}' {key} {a[key]} in the store, {b[key]} now"
    if stored.stage.microstep_um != rig.stage.microstep_um:
        return f"stage microstep_um {stored.stage.microstep_um} in the store, {rig.stage.microstep_um} now"
    return None


#: Where an update of a camera's items is staged, and where the items it replaces wait to be deleted.
_STAGED = "update.staged"
_OLD = "update.old"


def _settle(camera_dir: Path) -> None:
    """Complete a committed update of one camera's folder, or discard an uncommitted one."""
    staged, old = camera_dir / _STAGED, camera_dir / _OLD
    if not staged.exists():
        shutil.rmtree(old, ignore_errors=True)
        return
    try:
        commit = json.loads((staged / "zarr.json").read_text()).get("attributes", {}).get("commit")
    except (OSError, ValueError):
        commit = None
    if not commit:  # interrupted before its commit: the old items are whole
        shutil.rmtree(staged, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
        return
    old.mkdir(exist_ok=True)
    replace, remove = list(commit.get("replace", [])), list(commit.get("remove", []))
    for name in replace + remove:
        cur = camera_dir / name
        if cur.exists() and (name in remove or (staged / name).exists()):  # not yet swapped
            shutil.rmtree(old / name, ignore_errors=True)
            os.replace(cur, old / name)
    for name in replace:
        if (staged / name).exists():
            os.replace(staged / name, camera_dir / name)
    shutil.rmtree(staged, ignore_errors=True)
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP wait until the block ends, then are handled as they would have
    been (in the main thread; elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = [s for s in (signal.SIGINT, getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)) if s]
    got: list[int] = []
    before = {s: signal.getsignal(s) for s in sigs}
    for s in sigs:
        if before[s] not in (signal.SIG_IGN, None):
            signal.signal(s, lambda signum, frame: got.append(signum))
    try:
        yield
    finally:
        for s in sigs:
            if before[s] is not None:
                signal.signal(s, before[s])
        for s in dict.fromkeys(got):
            signal.raise_signal(s)
