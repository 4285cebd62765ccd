"""The projector of pinhole (Tomo-PIV) cameras: MLOS elimination and line-of-sight weights.

:class:`PinholeProjector` binds pinhole cameras and a voxel grid on a device: a
:class:`~lfcore.operator.Projector` like the light-field one (elimination, the operator of a
frame's voxels), so :class:`~lfcore.reconstruct.FrameReconstructor` runs MLOS-SMART (Atkinson and
Soria 2009) on it unchanged:

- **weights** (line of sight): a voxel's light reaches each camera at the image of its centre,
  projected with the camera's model and its distortion (:func:`lfcore.pinhole.project`), and is
  shared among the pixels there by a Gaussian footprint integrated over each pixel, of sigma
  ``footprint`` times the voxel's projected width (a smooth stand-in for the overlap of the
  voxel's projected disc with the pixels, Elsinga et al. 2006). A voxel's weights are divided by
  their sum over all cameras, as the light-field projector's are; stored voxel-major in the
  :class:`~lfcore.weight_build.Weights` layout, so the projection and update kernels are the
  light-field ones;
- **MLOS elimination**: a voxel can hold a particle only if the pixel of its image is lit in
  every camera (the product of the lines of sight' intensities is not zero).

Forward projection, the updates and the scatter are :class:`~lfcore.weight_build.Weights`' own
(the operator of every kind of stored rows). :class:`JointProjector` reconstructs a mixed rig
(light-field and pinhole cameras) jointly. Both are siblings of
:class:`~lfcore.projector.LightFieldProjector` on the shared :class:`~lfcore.projector.BoundCameras`;
:func:`lfcore.plan.projector_for` picks the projector of a camera set.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Sequence

import numpy as np

from lfcore._deprecation import keyword_options, moved_names
from lfcore.device import (
    MemoryBudgetError,
    RowOffset,
    Rows,
    available_bytes,
    launch_rows,
    out_of_memory_is_budget_error,
)
from lfcore.operator import JOINT, PINHOLE, check_indexable
from lfcore.projector import BoundCameras, LightFieldProjector
from lfcore.rig import PinholeCamera, is_pinhole
from lfcore.volume import VolumeGrid
from lfcore.weight_build import ADVICE, BYTES_PER_WEIGHT, CHUNK_ENTRIES, WeightChunk, Weights

__all__ = ["DEFAULT_FOOTPRINT", "JointProjector", "PINHOLE_METHODS", "PinholeProjector", "footprint_sigma_px"]

#: The methods of pinhole (Tomo-PIV) cameras alone: MLOS-SMART, and MART on every voxel of the box.
#: DRT weights and MLOS-MART's elimination need microlenses.
PINHOLE_METHODS = ("mlos-smart", "mart")


#: Sigma of the footprint's Gaussian, in units of the voxel's projected width: 0.5 spreads a
#: voxel of one pixel over about the 2 x 2 pixels a disc of its size would touch.
DEFAULT_FOOTPRINT = 0.5
#: The footprint covers the pixels within this many sigmas of the voxel's image.
REACH_SIGMAS = 2.5
#: Voxels whose weights are traced at once (bounds the slots' scratch memory).
TRACE_VOXELS = 1 << 18


@keyword_options("footprint", since="0.1.0")
def footprint_sigma_px(camera: PinholeCamera, grid: VolumeGrid, *, footprint: float = DEFAULT_FOOTPRINT) -> float:
    """Sigma, in pixels, of the footprint of one of ``grid``'s voxels on ``camera``'s sensor.

    The voxel's projected width is its mean lateral edge (x and y, mm) over the camera's pixel
    in the volume (``object_pixel_mm``), so PVR 1 is one pixel wide.
    """
    width_px = 0.5 * (grid.voxel_mm[0] + grid.voxel_mm[1]) / camera.object_pixel_mm
    return max(float(footprint) * width_px, 0.05)


class PinholeProjector(BoundCameras):
    """Pinhole cameras and a voxel grid bound on one device (MLOS-SMART's
    :class:`~lfcore.operator.Projector`).

    Parameters
    ----------
    cameras
        One or more :class:`~lfcore.rig.PinholeCamera` (all of them are used jointly).
    grid
        The voxel grid.
    footprint
        Sigma of a voxel's Gaussian footprint on the sensor, in units of its projected width.
    grow
        Elimination: pixels around a voxel's image that may be the lit one (0: its own pixel);
        for a calibration that is off by a pixel or so.
    device
        Warp device; None for the first GPU, else the CPU.
    """

    kind = "pinhole"

    def __init__(self, cameras: Sequence[PinholeCamera], grid: VolumeGrid, *, footprint: float = DEFAULT_FOOTPRINT,
                 grow: int = 0, device: str | None = None) -> None:
        from lfcore._kernels import pinhole_weights as kp
        from lfcore._kernels.pinhole import pinhole_params

        cameras = tuple(cameras)
        if not cameras:
            raise ValueError("a pinhole projector needs at least one camera")
        other = [c.name for c in cameras if not is_pinhole(c)]
        if other:
            raise ValueError(f"camera '{other[0]}' is a light-field camera; the pinhole projector takes pinhole "
                             "cameras only")
        if not footprint > 0:
            raise ValueError(f"footprint must be positive, got {footprint}")
        if grow < 0:
            raise ValueError(f"grow must be 0 or more pixels, got {grow}")
        super().__init__(cameras, grid, device=device)
        wp = self.wp
        self._kp = kp
        views, self.cap = [], 0
        self.sigma_px = []
        for k, cam in enumerate(cameras):
            v = kp.PinholeView()
            v.cam = pinhole_params(cam)
            v.pix_offset = int(self.pixel_offsets[k])
            sigma = footprint_sigma_px(cam, grid, footprint=footprint)
            v.sigma_px = sigma
            v.reach_px = REACH_SIGMAS * sigma
            v.grow = int(grow)
            per_axis = int(math.floor(2.0 * v.reach_px)) + 2
            self.cap += per_axis * per_axis
            self.sigma_px.append(sigma)
            views.append(v)
        self.views = wp.array(views, dtype=kp.PinholeView, device=self.device)
        self.max_checks = 0

    # --- MLOS elimination ---------------------------------------------------------------
    def eliminate(self, lit, *, min_seen: float = 0.5, max_dark: float = 0.05) -> object:
        """Voxels whose image is on a lit pixel in every camera (MLOS).

        Parameters
        ----------
        lit
            One boolean (rows, columns) image per camera: pixels with signal; or, already on
            the device, one (n_pixels,) uint8 Warp array of all cameras' pixels.
        min_seen, max_dark
            Ignored (the light-field projector's sub-aperture fractions; a pinhole camera has
            one line of sight per pixel).

        Returns
        -------
        warp.array
            (n,) int32 flat voxel indices, ascending (a new array).
        """
        check_indexable(self.grid)
        wp, kp = self.wp, self._kp
        lit_dev = self._lit_on_device(lit)
        n = self.grid.n_voxels
        mask = self._scratch("mask", n, wp.int32)
        launch_rows(kp.mlos_eliminate, n, [self._grid, self.views, len(self.cameras), lit_dev, RowOffset(0),
                                                 Rows(mask)],
                    self.device)
        return self._compact(mask)

    @keyword_options("n_checks", "budget_bytes", since="0.1.0")
    def precompute_checks(self, *, n_checks: int | None = None, budget_bytes: int | None = None) -> int:
        """Nothing to precompute: MLOS looks up one pixel per camera (returns 0 bytes)."""
        return 0

    # --- weights ------------------------------------------------------------------------
    @keyword_options("method", "min_weight", "budget_bytes", "build", "sort", "storage", since="0.1.0")
    def weights(self, voxels, *, method: str = "los", min_weight: float = 1e-6, budget_bytes: int | None = None,
                build: str = "auto", sort: str = "auto", storage: str = "stored") -> Weights:
        """Line-of-sight weights of ``voxels`` in every pinhole camera, stored: the operator of
        kind ``"pinhole weights"``.

        Parameters
        ----------
        voxels
            (n,) int32 flat voxel indices on this projector's device.
        method
            ``"los"`` (the only kind a pinhole camera has; ``"drt"`` is refused).
        min_weight
            Entries below this fraction of the voxel's light are dropped.
        budget_bytes
            Memory the weights may take; default: what the device has free.
        build, sort, storage
            Accepted for the light-field projector's interface; pinhole weights are always
            built in one pass and stored (a handful per camera and voxel).

        Returns
        -------
        Weights

        Raises
        ------
        MemoryBudgetError
            If the weights would not fit, with their size.
        """
        if method not in ("los", "drt"):
            raise ValueError(f"unknown weight method '{method}'; use 'los'")
        if method == "drt":
            raise ValueError("pinhole cameras have line-of-sight weights only (no dense ray tracing); "
                             "use --method mlos-smart")
        n = int(voxels.shape[0])
        with out_of_memory_is_budget_error(self.device, f"the weights of {n:,} voxels", ADVICE):
            w = self._weights(voxels, float(min_weight),
                              available_bytes(self.device) if budget_bytes is None else int(budget_bytes))
        return self.bind(w, kind=PINHOLE)

    def operator(self, voxels, *, method: str = "los", min_weight: float = 1e-6, budget_bytes: int | None = None,
                 storage: str = "stored") -> Weights:
        """The :class:`~lfcore.operator.Operator` of ``voxels``: :meth:`weights`."""
        return self.weights(voxels, method=method, min_weight=min_weight, budget_bytes=budget_bytes, storage=storage)

    def _weights(self, voxels, min_weight: float, budget: int) -> Weights:
        wp, kp = self.wp, self._kp
        n = int(voxels.shape[0])
        dev, cap = self.device, self.cap
        chunks, total = [], 0
        per = max(1, min(TRACE_VOXELS, CHUNK_ENTRIES["cpu" if dev == "cpu" else "cuda"] // cap))
        for lo in range(0, n, per):
            hi = min(n, lo + per)
            m = hi - lo
            counts = wp.zeros(m, dtype=wp.int32, device=dev)
            pix = wp.empty(m * cap, dtype=wp.int32, device=dev)
            w = wp.empty(m * cap, dtype=float, device=dev)
            launch_rows(kp.pinhole_los, m, [self._grid, self.views, len(self.cameras), Rows(voxels[lo:hi]), cap,
                                            min_weight, Rows(counts), Rows(pix, scale=cap), Rows(w, scale=cap)], dev)
            offs = np.zeros(m + 1, dtype=np.int64)
            np.cumsum(counts.numpy(), out=offs[1:])
            nnz = int(offs[-1])
            if BYTES_PER_WEIGHT * (total + nnz) + 12 * n > budget:
                raise MemoryBudgetError(
                    f"the weights need at least {BYTES_PER_WEIGHT * (total + nnz) / 2**30:.1f} GiB for {n} voxels but "
                    f"{dev} has {budget / 2**30:.1f} GiB free; {ADVICE}")
            offsets = wp.array(offs, dtype=wp.int64, device=dev)
            out_pix = wp.empty(max(nnz, 1), dtype=wp.int32, device=dev)
            out_w = wp.empty(max(nnz, 1), dtype=float, device=dev)
            launch_rows(kp.gather_slots, m, [Rows(counts), Rows(offsets), cap, Rows(pix, scale=cap),
                                             Rows(w, scale=cap), out_pix, out_w], dev)
            del pix, w, counts
            chunks.append(WeightChunk(first=lo, n=m, offsets=offsets, pix=out_pix, w=out_w, nnz=nnz))
            total += nnz
        return Weights(voxels=voxels, chunks=chunks, nnz=total, min_weight=min_weight)


class JointProjector(BoundCameras):
    """Light-field and pinhole cameras reconstructed jointly: a mixed rig on one voxel grid.

    Each kind keeps its own projector (:class:`~lfcore.projector.LightFieldProjector`,
    :class:`PinholeProjector`); a voxel is kept where both eliminations keep it, and its weights are
    both kinds' rows joined (their pixels renumbered into this projector's global numbering, in the
    given camera order), each kind's weighted by its share of the cameras, so a voxel's weights
    still sum to one: the operator of kind ``"joint weights"``.

    Parameters
    ----------
    cameras
        Light-field and pinhole cameras, in the order of their images.
    grid
        The voxel grid.
    sub_apertures
        As :class:`~lfcore.projector.LightFieldProjector` takes it (the light-field cameras' DRT weights).
    device
        Warp device; None for the first GPU, else the CPU.
    """

    kind = "joint"

    def __init__(self, cameras: Sequence, grid: VolumeGrid, *, sub_apertures: int | None = None,
                 device: str | None = None) -> None:
        cameras = tuple(cameras)
        self._tomo = [k for k, c in enumerate(cameras) if is_pinhole(c)]
        self._lf = [k for k, c in enumerate(cameras) if not is_pinhole(c)]
        if not self._tomo or not self._lf:
            raise ValueError("a joint projector needs light-field and pinhole cameras; use lfcore.plan.projector_for")
        super().__init__(cameras, grid, device=device)
        self.lf = LightFieldProjector([cameras[k] for k in self._lf], grid, sub_apertures=sub_apertures,
                                      device=self.device)
        self.ph = PinholeProjector([cameras[k] for k in self._tomo], grid, device=self.device)
        self._grid = self.lf._grid
        self.max_checks = 0

    def _split(self, lit) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Each kind's lit images, in its projector's order (a device mask is copied to the host)."""
        if isinstance(lit, self.wp.array):
            flat = lit.numpy()
            lit = [flat[a:b].reshape(c.sensor_px[1], c.sensor_px[0])
                   for a, b, c in zip(self.pixel_offsets[:-1], self.pixel_offsets[1:], self.cameras, strict=True)]
        lit = list(lit)
        if len(lit) != len(self.cameras):
            raise ValueError(f"got {len(lit)} lit masks for {len(self.cameras)} cameras")
        return [lit[k] for k in self._lf], [lit[k] for k in self._tomo]

    def eliminate(self, lit, *, min_seen: float = 0.5, max_dark: float = 0.05) -> object:
        """Voxels that both kinds' eliminations keep (see :meth:`LightFieldProjector.eliminate
        <lfcore.projector.LightFieldProjector.eliminate>` and
        :meth:`PinholeProjector.eliminate`), as (n,) int32 flat indices, ascending."""
        lf_lit, ph_lit = self._split(lit)
        kept = np.intersect1d(self.lf.eliminate(lf_lit, min_seen=min_seen, max_dark=max_dark).numpy(),
                              self.ph.eliminate(ph_lit).numpy())
        return self.wp.array(kept.astype(np.int32), dtype=self.wp.int32, device=self.device)

    @keyword_options("n_checks", "budget_bytes", since="0.1.0")
    def precompute_checks(self, *, n_checks: int | None = None, budget_bytes: int | None = None) -> int:
        """No elimination table is kept for a joint projector (returns 0 bytes)."""
        return 0

    def planes(self, z0: int, z1: int) -> JointProjector:
        """A depth slab of this joint projector (see :meth:`BoundCameras.planes
        <lfcore.projector.BoundCameras.planes>`): each kind's projector on the same planes."""
        out = super().planes(z0, z1)
        out.lf, out.ph = self.lf.planes(z0, z1), self.ph.planes(z0, z1)
        out._grid = out.lf._grid
        return out

    @keyword_options("method", "min_weight", "budget_bytes", "build", "sort", "storage", since="0.1.0")
    def weights(self, voxels, *, method: str = "los", min_weight: float = 1e-6, budget_bytes: int | None = None,
                build: str = "auto", sort: str = "auto", storage: str = "stored") -> Weights:
        """Both kinds' weights of ``voxels`` joined row by row (``method`` is the light-field
        cameras' kind, ``"drt"`` or ``"los"``; the pinhole cameras' are line of sight), stored."""
        wp = self.wp
        parts = []
        lf = self.lf.weights(voxels, method=method, min_weight=min_weight, budget_bytes=budget_bytes, build=build,
                             sort=sort, storage="stored")
        ph = self.ph.weights(voxels, method="los", min_weight=min_weight, budget_bytes=budget_bytes)
        for sub, idx, w in ((self.lf, self._lf, lf), (self.ph, self._tomo, ph)):
            offs, pix, val = w.to_numpy()
            cam = np.searchsorted(sub.pixel_offsets, pix, side="right") - 1
            shift = self.pixel_offsets[idx] - sub.pixel_offsets[:-1]  # each camera's pixels renumbered
            parts.append((offs, (pix + shift[cam]).astype(np.int32), val * np.float32(len(idx) / len(self.cameras))))
        (o1, p1, w1), (o2, p2, w2) = parts
        n1, n2 = np.diff(o1), np.diff(o2)
        offs = np.zeros(len(n1) + 1, dtype=np.int64)
        np.cumsum(n1 + n2, out=offs[1:])
        nnz = int(offs[-1])
        pix = np.empty(nnz, dtype=np.int32)
        val = np.empty(nnz, dtype=np.float32)
        # a voxel's light-field entries first, then its pinhole ones
        at1 = np.repeat(offs[:-1] - o1[:-1], n1) + np.arange(len(p1))
        at2 = np.repeat(offs[:-1] + n1 - o2[:-1], n2) + np.arange(len(p2))
        pix[at1], val[at1], pix[at2], val[at2] = p1, w1, p2, w2
        if budget_bytes is not None and BYTES_PER_WEIGHT * nnz > budget_bytes:
            raise MemoryBudgetError(f"the joint weights need {BYTES_PER_WEIGHT * nnz / 2**30:.1f} GiB for "
                                    f"{len(n1)} voxels, more than the {budget_bytes / 2**30:.1f} GiB allowed; {ADVICE}")
        dev = self.device
        chunk = WeightChunk(first=0, n=len(n1), offsets=wp.array(offs, dtype=wp.int64, device=dev),
                            pix=wp.array(pix if nnz else np.zeros(1, np.int32), dtype=wp.int32, device=dev),
                            w=wp.array(val if nnz else np.zeros(1, np.float32), dtype=float, device=dev), nnz=nnz)
        return self.bind(Weights(voxels=voxels, chunks=[chunk], nnz=nnz, min_weight=float(min_weight)), kind=JOINT)

    def operator(self, voxels, *, method: str = "los", min_weight: float = 1e-6, budget_bytes: int | None = None,
                 storage: str = "stored") -> Weights:
        """The :class:`~lfcore.operator.Operator` of ``voxels``: :meth:`weights`."""
        return self.weights(voxels, method=method, min_weight=min_weight, budget_bytes=budget_bytes, storage=storage)


# the planner's since the operator protocol (imported on first use: lfcore.plan imports this module)
__getattr__ = moved_names(__name__, {name: (lambda name=name: getattr(importlib.import_module("lfcore.plan"), name))
                                     for name in ("projector_for", "default_method", "unsupported_method")},
                          since="0.1.0")
