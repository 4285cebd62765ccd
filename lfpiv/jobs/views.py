"""Perspective views and refocused planes of a raw light-field frame (``lfpiv views``).

The frame is a run's (pair, frame A or B, camera) or a raw image file of a camera of a
calibration store's rig. The micro-image lattice is the one fitted to the white image
(``lfpiv calibrate mla``) where a calibration store gives it, else the rig file's nominal MLA
(with a note); the optics that turn depths into parallax are the store's fitted camera model
where it has one, else the rig file's. The computation is :mod:`lfcore.views`.

Where the calibration store holds the camera's white image, the views are divided by the same
views of the white image for display (each micro-image's vignetting levelled). This is a
display normalisation only; the per-pixel dark and white correction of the raw frame (the flat
field of issue 49, part 1) is applied before the views are sampled once it exists
(:func:`_corrected`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lfcore.camera_checks import background_noise
from lfcore.files import replacing
from lfcore.rig import Camera, Rig, camera_from_dict, is_pinhole
from lfcore.views import Lattice, Views, nominal_lattice, refocus_stack, sample_views, view_mosaic
from lfpiv.errors import UsageError

__all__ = ["ViewsResult", "frame_of_image", "frame_of_run", "lattice_of", "make_views", "views", "write_views"]

PathLike = str | os.PathLike[str]


@dataclass
class ViewsResult:
    """The views and refocused planes of one frame.

    Attributes
    ----------
    camera
        The camera's name.
    views
        The perspective views (:class:`lfcore.views.Views`).
    depths_mm
        (n,) the refocused planes' z in the rig's frame, mm.
    planes
        (n, rows, columns) float32 refocused images (on the lattice, ``upsample`` samples a step).
    lattice_source
        Where the lattice came from (the calibration store, or the rig file's nominal MLA).
    notes
        What the user should know (nominal lattice, display normalisation), one line each.
    files
        The files written (:func:`write_views`).
    """

    camera: str
    views: Views
    depths_mm: np.ndarray
    planes: np.ndarray
    lattice_source: str
    notes: list[str] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)

    @property
    def mosaic(self) -> np.ndarray:
        """Every view tiled by its offset (:func:`lfcore.views.view_mosaic`)."""
        return view_mosaic(self.views)

    @property
    def centre_view(self) -> np.ndarray:
        """The central view as a picture."""
        return self.views.picture(self.views.centre)

    def plane_images(self) -> list[np.ndarray]:
        """The refocused planes as pictures (hexagonal rows straightened)."""
        up = max(self.planes.shape[1] // max(self.views.inside.shape[0], 1), 1)
        return [self.views.picture(p, upsample=up) for p in self.planes]


def _lightfield(rig: Rig, camera: str | None, where: str) -> Camera:
    names = [c.name for c in rig.lightfield_cameras]
    if not names:
        raise UsageError(f"{where} has no light-field camera; perspective views need one")
    if camera is None:
        if len(names) > 1:
            raise UsageError(f"{where} has cameras {', '.join(names)}; give --camera NAME")
        return rig.lightfield_cameras[0]
    if camera not in [c.name for c in rig.camera]:
        raise UsageError(f"camera '{camera}' is not in {where} (it has {', '.join(c.name for c in rig.camera)})")
    cam = rig.camera_named(camera)
    if is_pinhole(cam):
        raise UsageError(f"camera '{camera}' is a pinhole camera; perspective views need a light-field camera "
                         f"({', '.join(names)})")
    return cam


def frame_of_run(run: PathLike, *, pair: int = 0, frame: str = "A", camera: str | None = None
                 ) -> tuple[Rig, Camera, np.ndarray]:
    """One raw frame of a run: (the run's rig, the camera, (rows, columns) uint16).

    Raises
    ------
    UsageError
        A frame other than A or B, a camera the run does not have or not a light-field one.
    lfcore.runstore.RunStoreError
        A pair the run does not hold or a lost frame, in one line.
    """
    from lfpiv.runs import open_run

    if str(frame).upper() not in ("A", "B"):
        raise UsageError(f"--frame is A or B, got {frame!r}")
    store = open_run(run)
    rig = store.rig
    cam = _lightfield(rig, camera, f"run {run}")
    return rig, cam, store.read_frame(cam.name, int(pair), 0 if str(frame).upper() == "A" else 1)


def frame_of_image(path: PathLike, camera: Camera) -> np.ndarray:
    """A raw image file of ``camera`` as (rows, columns) uint16, checked against its sensor.

    Raises
    ------
    UsageError
        A file that cannot be read, or of another size or bit depth than the camera's.
    """
    from lfpiv.formats import FormatError
    from lfpiv.formats.images import FrameSource, read_frame

    try:
        return read_frame(FrameSource(Path(path), 0), sensor_px=tuple(camera.sensor_px), bit_depth=camera.bit_depth)
    except FormatError as exc:
        raise UsageError(f"--image: camera '{camera.name}': {exc}") from None


def lattice_of(camera: Camera, calibration: PathLike | None) -> tuple[Lattice, Camera, np.ndarray | None, str]:
    """The micro-image lattice of ``camera``, the optics to use, its white image and where they came from.

    With a calibration store holding the camera's fitted grid (``lfpiv calibrate mla``), its
    lattice, its fitted camera model if it has one (``lfpiv calibrate fit``) and its white image;
    else the camera's nominal lattice.

    Returns
    -------
    tuple
        (lattice, camera, white image or None, source).
    """
    if calibration is None:
        return nominal_lattice(camera), camera, None, "the rig file's nominal MLA (no calibration store)"
    from lfpiv.jobs.calibrate import open_calibration

    store = open_calibration(calibration)
    if camera.name not in store.cameras:
        raise UsageError(f"camera '{camera.name}' is not in the calibration store {calibration} (it has "
                         f"{', '.join(store.cameras)}); use the calibration of this rig")
    grid = store.grid(camera.name)
    if grid is None:
        raise UsageError(f"camera '{camera.name}': the calibration store {calibration} holds no microlens grid; run "
                         f"'lfpiv calibrate mla' first")
    if tuple(grid.image_shape) != (camera.sensor_px[1], camera.sensor_px[0]):
        raise UsageError(f"camera '{camera.name}': the calibration's grid was fitted to a {grid.image_shape[1]} x "
                         f"{grid.image_shape[0]} image but the camera has {camera.sensor_px[0]} x "
                         f"{camera.sensor_px[1]} pixels; use the calibration of this rig")
    model = store.model(camera.name)
    optics = camera_from_dict(model["camera"]) if model else camera
    lattice = Lattice(origin_px=tuple(grid.origin_px), basis_px=np.asarray(grid.basis_px), grid=grid.grid)
    source = (f"the white image's fitted grid in {calibration} ({grid.rms_px:.2f} px RMS, {grid.n_lenslets} "
              "lenslets)" + ("" if model else "; the rig file's optics (no fitted model)"))
    return lattice, optics, store.white(camera.name), source


def _corrected(image: np.ndarray, white: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The raw frame (and white image) as the views sample them: the frame's background (from its
    darkest pixels, :func:`lfcore.camera_checks.background_noise`) subtracted from both, the
    camera's black level being the same. The per-pixel dark and white correction (issue 49, part
    1: the calibration store's dark and white frames) plugs in here in its place."""
    img = np.asarray(image, dtype=np.float32)
    b = np.float32(background_noise(img)[0])
    return img - b, None if white is None else np.asarray(white, dtype=np.float32) - b


def make_views(image: np.ndarray, camera: Camera, *, lattice: Lattice, depths_mm: Sequence[float] = (),
               white: np.ndarray | None = None, upsample: int = 1, radius_px: float | None = None) -> ViewsResult:
    """The views of a raw frame and its planes refocused at ``depths_mm`` (rig's z, mm).

    Raises
    ------
    UsageError
        A depth the camera cannot refocus on (its axis along the plane), a bad ``upsample``, a
        lattice that does not fit the image.
    """
    if upsample < 1:
        raise UsageError(f"--upsample must be a whole number of at least 1, got {upsample}")
    try:
        img, w = _corrected(image, white)
        v = sample_views(img, lattice, radius_px=radius_px, white=w)
        depths = np.asarray(list(depths_mm), dtype=np.float64)
        planes = (refocus_stack(v, camera, depths, upsample=upsample) if len(depths)
                  else np.zeros((0, *v.inside.shape), dtype=np.float32))
    except ValueError as exc:
        raise UsageError(f"camera '{camera.name}': {exc}") from None
    notes = ["the frame's background (from its darkest pixels) is subtracted; no dark frame is used"]
    if white is not None:
        notes.append("views divided by the white image's views (display normalisation of the micro-images' "
                      "vignetting; the raw frame is not flat-field corrected)")
    return ViewsResult(camera=camera.name, views=v, depths_mm=depths, planes=planes, lattice_source="", notes=notes)


def _scaled(img: np.ndarray, bits: int) -> np.ndarray:
    """A picture stretched from its 0.5th to its 99.5th percentile to the full range of ``bits``."""
    lo, hi = np.percentile(img, [0.5, 99.5]) if img.size else (0.0, 1.0)
    out = np.clip((img - lo) / max(hi - lo, 1e-12), 0.0, 1.0) * (2**bits - 1)
    return np.rint(out).astype(np.uint8 if bits == 8 else np.uint16)


def write_views(result: ViewsResult, out: PathLike, *, fmt: str = "png", every_view: bool = True) -> list[Path]:
    """Write the views and planes of ``result`` into the folder ``out``.

    Files: ``mosaic.png`` (every view tiled by offset), ``centre.png``; with ``every_view`` one
    file per view ``view_u{du}_v{dv}``; one per plane ``refocus_z{z}mm``; and ``views.png``, a
    figure of the mosaic, the central view and the planes. ``fmt`` "png" writes 16-bit PNGs
    stretched for display; "tiff" writes the float32 values (views and planes as they are).

    Returns
    -------
    list of Path
        Every file written (also kept in ``result.files``).
    """
    import imageio.v3 as iio
    import tifffile

    if fmt not in ("png", "tiff"):
        raise UsageError(f"--format is png or tiff, got {fmt!r}")
    folder = Path(out)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {folder} cannot be made ({exc.strerror or exc}); give a writable folder") from None

    def put(name: str, img: np.ndarray) -> Path:
        # each file whole or not at all: an interrupt or a full disk leaves the earlier one
        path = folder / f"{name}.{'png' if fmt == 'png' else 'tif'}"
        with replacing(path) as tmp:
            if fmt == "png":
                iio.imwrite(tmp, _scaled(img, 16), extension=".png")
            else:
                tifffile.imwrite(tmp, np.asarray(img, dtype=np.float32))
        return path

    files = [put("mosaic", result.mosaic), put("centre", result.centre_view)]
    if every_view:
        files += [put(f"view_u{du:+d}_v{dv:+d}", result.views.picture(img))
                  for img, (du, dv) in zip(result.views.images, result.views.offsets_px, strict=True)]
    for z, img in zip(result.depths_mm, result.plane_images(), strict=True):
        files.append(put(f"refocus_z{z:+.3f}mm", img))
    from lfpiv.plots import plot_views

    files.append(plot_views(result, folder / "views.png"))
    result.files = files
    return files


def views(*, run: PathLike | None = None, pair: int = 0, frame: str = "A", image: PathLike | np.ndarray | None = None,
          calibration: PathLike | None = None, rig: Rig | PathLike | None = None, camera: str | None = None,
          depths_mm: Sequence[float] | None = None, upsample: int = 1, out: PathLike | None = None,
          fmt: str = "png", every_view: bool = True) -> ViewsResult:
    """The perspective views and refocused planes of a run's frame or of a raw image file.

    Parameters
    ----------
    run, pair, frame
        A run store and which of its frames (pair index, "A" or "B").
    image
        A raw image file instead (PNG, TIFF, BMP; 8 or 16 bit), or a (rows, columns) array, of a
        camera of the calibration store's rig (or of ``rig``).
    calibration
        Calibration store with the camera's fitted microlens grid (and white image, fitted model).
    rig
        The rig of ``image`` when there is no calibration store (the nominal lattice is used).
    camera
        The light-field camera (default: the only one).
    depths_mm
        The planes to refocus on, z in the rig's frame, mm (default: 5 planes from the front to
        the back of the rig's volume; ``()`` for none).
    upsample
        Samples per lattice step of the refocused planes.
    out
        Folder to write the files to (:func:`write_views`), or None to write nothing.
    fmt, every_view
        See :func:`write_views`.

    Returns
    -------
    ViewsResult

    Raises
    ------
    UsageError
        Neither or both of a run and an image, an image without a calibration store or rig, and
        the errors of :func:`frame_of_run`, :func:`frame_of_image` and :func:`lattice_of`.
    """
    if (run is None) == (image is None):
        raise UsageError("give a run (RUN) or a raw image (--image FILE), not both or neither")
    if run is not None:
        rig_, cam, img = frame_of_run(run, pair=pair, frame=frame, camera=camera)
    else:
        if calibration is None and rig is None:
            raise UsageError("--image needs --calibration STORE (the fitted microlens grid), or --rig RIG for the "
                             "nominal one")
        if calibration is not None:
            from lfpiv.jobs.calibrate import open_calibration

            rig_ = open_calibration(calibration).rig
            where = f"the calibration store {calibration}"
        else:
            from lfpiv.rigfile import load_rig

            rig_ = rig if isinstance(rig, Rig) else load_rig(rig)
            where = "the rig"
        cam = _lightfield(rig_, camera, where)
        if isinstance(image, np.ndarray):
            img = image
            if img.shape != (cam.sensor_px[1], cam.sensor_px[0]):
                raise UsageError(f"the image is {img.shape[-1]} x {img.shape[0]} px but camera '{cam.name}' has "
                                 f"{cam.sensor_px[0]} x {cam.sensor_px[1]}")
        else:
            img = frame_of_image(image, cam)
    lattice, optics, white, source = lattice_of(cam, calibration)
    if depths_mm is None:
        lo, hi = rig_.volume.bounds_mm
        depths_mm = np.linspace(lo[2], hi[2], 5)
    result = make_views(img, optics, lattice=lattice, depths_mm=depths_mm, white=white, upsample=upsample)
    result.lattice_source = source
    if calibration is None:
        result.notes.insert(0, "the lattice is the rig file's nominal MLA; give --calibration STORE (lfpiv calibrate "
                               "mla) for the measured one")
    if out is not None:
        write_views(result, out, fmt=fmt, every_view=every_view)
    return result
