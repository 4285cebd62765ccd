"""3D particle reconstruction from light-field images: DRT-MART and the MART baseline.

DRT-MART (the chapter's dense ray-tracing MART):

1. Preprocess each image: subtract the background and call a pixel lit if its signal is more
   than ``threshold_sigma`` noise sigmas above it.
2. Zero-voxel elimination: keep only voxels every sub-aperture of which lands on a lit pixel
   (the light-field analogue of MLOS: a voxel with a dark pixel holds no particle).
3. Dense ray-traced weights for the surviving voxels, stored sparsely, so memory follows the
   number of active voxels rather than the size of the box.
4. MART iterations (eq. 4.1) on those voxels only.

The MART baseline uses the conventional line-of-sight weights on every voxel of the box and no
elimination, with the same iteration code, so speed and quality ratios compare weights and
elimination, nothing else. MLOS-MART combines the two: DRT-MART's elimination, then the
baseline's line-of-sight weights on the surviving voxels only (the multiplicative
line-of-sight MART of tomographic PIV, Atkinson and Soria 2009, with the light-field lit-pixel
test). On the synthetic cases measured it reaches the baseline's quality, which is higher than
DRT-MART's, in a fraction of its time (``benchmarks/RESULTS.md``).

Two iteration forms are offered. ``simultaneous`` (the default) updates every voxel at once
from one forward projection, E_j <- E_j exp(mu sum_i w_ij ln(I_i / proj_i)) (SMART): each
update reads only its own weights, so it runs in parallel over voxels at memory bandwidth on a
GPU, and its result does not depend on an ordering. ``sequential`` is eq. 4.1 taken literally,
pixel after pixel with the projection refreshed each time: it converges in fewer iterations but
is inherently serial, so it suits small problems on the CPU.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from lfcore.device import MemoryBudgetError, available_bytes, out_of_memory_is_budget_error
from lfcore.device_ops import VolumeOps
from lfcore.projector import STORAGE, Projector
from lfcore.weight_cache import WeightCache

__all__ = ["METHODS", "WEIGHTS", "ReconResult", "ReconSettings", "estimate_background", "preprocess", "reconstruct"]

METHODS = ("drt-mart", "mart", "mlos-mart")
#: The weights each method iterates on (:meth:`Projector.weights` and :class:`WeightCache` names).
WEIGHTS = {"drt-mart": "drt", "mart": "los", "mlos-mart": "los"}
#: Above this the simultaneous update overshoots: every voxel on an under-projected pixel grows at
#: once (sequential MART takes the chapter's 2.5 because each pixel's step is small).
MAX_SIMULTANEOUS_RELAXATION = 2.0
#: Widest smoothing sigma accepted, voxels.
MAX_SMOOTH_VOXELS = 10.0
#: Most main-lens sub-apertures per axis for the DRT weights: the default is the pixels per
#: lenslet (about 14), and each voxel traces the square of this many bundles.
MAX_SUB_APERTURES = 64
FORMS = ("simultaneous", "sequential")


@dataclass(frozen=True)
class ReconSettings:
    """How to reconstruct.

    Attributes
    ----------
    method
        ``"drt-mart"``, ``"mart"`` (the conventional baseline) or ``"mlos-mart"`` (DRT-MART's
        elimination with the baseline's weights).
    iterations
        MART iterations (sweeps).
    relaxation
        mu of eq. 4.1. The chapter's sequential MART uses 2.5; the simultaneous form is fastest
        at about 1 and diverges above 2.
    form
        ``"simultaneous"`` or ``"sequential"`` (see the module docstring).
    sub_apertures
        Sub-apertures per axis for the DRT weights; None: the pixels per lenslet.
    background
        Background level in counts, one for all cameras; None: estimated per image.
    threshold_sigma
        A pixel is lit if its signal exceeds this many noise sigmas.
    min_seen
        Fraction of a voxel's sub-apertures that must land on the sensor of each camera.
    max_dark
        Fraction of a voxel's sub-apertures that may land on unlit pixels before elimination
        drops it (noise, and particles larger than a point, darken a few).
    floor
        In the update, a pixel's measured intensity counts as at least ``floor`` times the lit
        threshold: an unlit pixel may hold up to a threshold's worth of signal, so it suppresses
        its voxels firmly but without wiping out a particle whose weight barely touches it.
    lit_grow
        Pixels by which the lit mask is widened before elimination (for imperfect calibration).
    smooth
        Sigma, in voxels, of a Gaussian applied to the result (0: none). MART converges to
        particles about one voxel across, sharper than the 3-voxel particle images that
        cross-correlation needs to locate peaks without peak locking (and that Q_recon's truth
        is made of); 0.6 voxel brings them to that size, as in spatially filtered MART
        (Discetti et al. 2013).
    weight_storage
        Where the line-of-sight weights of ``mart`` and ``mlos-mart`` live: ``"auto"`` (stored
        if they fit in the device's memory; otherwise as many voxels' as fit, the rest computed
        again in each iteration), ``"stored"`` (all stored, or a :class:`MemoryBudgetError`) or
        ``"on-the-fly"`` (none stored). The volume is the same (to float round-off); weights
        made on the fly cost two traces per iteration instead of two reads, so a volume whose
        weights do not fit is reconstructed slowly rather than refused. DRT weights and the
        sequential form are always stored.
    """

    method: str = "drt-mart"
    iterations: int = 50
    relaxation: float = 1.0
    form: str = "simultaneous"
    sub_apertures: int | None = None
    background: float | None = None
    threshold_sigma: float = 2.0
    min_seen: float = 0.5
    max_dark: float = 0.01
    floor: float = 0.3
    lit_grow: int = 0
    smooth: float = 0.6
    weight_storage: str = "auto"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got '{self.method}'")
        if self.form not in FORMS:
            raise ValueError(f"form must be one of {', '.join(FORMS)}, got '{self.form}'")
        if self.iterations < 0:
            raise ValueError(f"iterations must be 0 or more, got {self.iterations}")
        if not self.relaxation > 0:
            raise ValueError(f"relaxation must be positive, got {self.relaxation}")
        if self.form == "simultaneous" and self.relaxation > MAX_SIMULTANEOUS_RELAXATION:
            raise ValueError(f"relaxation {self.relaxation:g} makes the simultaneous update diverge; use at most "
                             f"{MAX_SIMULTANEOUS_RELAXATION:g}, or the sequential form for the chapter's 2.5")
        if not self.threshold_sigma >= 0:
            raise ValueError(f"threshold_sigma must be 0 or more, got {self.threshold_sigma}")
        if not 0 <= self.smooth <= MAX_SMOOTH_VOXELS:
            # a sigma many voxels wide blurs particles (3 voxels across) into the background
            raise ValueError(f"smooth must be from 0 to {MAX_SMOOTH_VOXELS:g} voxels, got {self.smooth}")
        if self.sub_apertures is not None and not 1 <= self.sub_apertures <= MAX_SUB_APERTURES:
            # the build's time grows with the square: 1000 per axis took minutes on a tiny rig
            raise ValueError(f"sub_apertures must be from 1 to {MAX_SUB_APERTURES} per axis, got "
                             f"{self.sub_apertures}")
        if self.weight_storage not in STORAGE:
            raise ValueError(f"weight_storage must be one of {', '.join(STORAGE)}, got '{self.weight_storage}'")
        if self.weight_storage == "on-the-fly" and self.method == "drt-mart":
            raise ValueError("DRT-MART's weights are always stored; on-the-fly weights are for mart and mlos-mart")
        if self.weight_storage == "on-the-fly" and self.form == "sequential":
            raise ValueError("the sequential form needs stored weights; use the simultaneous form for on-the-fly "
                             "weights")

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass
class ReconResult:
    """A reconstructed volume and what it took.

    Attributes
    ----------
    volume
        (z, y, x) float32 intensities.
    active_voxels
        Voxels reconstructed (after elimination for DRT-MART; all for MART).
    active_fraction
        ``active_voxels`` over the voxels of the box.
    nnz
        Stored weights.
    weight_bytes
        Memory of the weights.
    weights_s, iterate_s
        Seconds spent on elimination plus weights, and on the iterations.
    eliminate_s
        Of ``weights_s``, the seconds of zero-voxel elimination (0 for the MART baseline).
    on_the_fly_voxels
        Voxels whose weights were made in each iteration instead of stored (0: all stored).
    background, noise
        Per camera: the background subtracted and the noise sigma, in counts.
    """

    volume: np.ndarray
    active_voxels: int
    active_fraction: float
    nnz: int
    weight_bytes: int
    weights_s: float
    iterate_s: float
    iterations: int
    background: list[float] = field(default_factory=list)
    noise: list[float] = field(default_factory=list)
    eliminate_s: float = 0.0
    on_the_fly_voxels: int = 0

    @property
    def ms_per_iteration(self) -> float:
        return 1e3 * self.iterate_s / max(self.iterations, 1)


def estimate_background(image: np.ndarray) -> tuple[float, float]:
    """Background level and noise sigma of a raw image, in counts.

    Particle light only ever adds to the background, and at LF-PIV seeding densities it may
    cover most pixels, so the background is found as the mode of the image's histogram (a sharp
    peak of width sigma, where particle light spreads broadly) and sigma from the pixels below
    the mode, which particle light cannot reach.
    """
    image = np.asarray(image)
    v = image.astype(np.float64).ravel()
    if v.size > 2_000_000:
        v = v[:: v.size // 2_000_000]
    lo, hi = np.percentile(v, [0.1, 90.0])
    if hi <= lo:
        return float(lo), 1e-6
    if np.issubdtype(image.dtype, np.integer) or np.array_equal(v, np.round(v)):
        # Whole counts: bins a whole number of counts wide and centred on them; narrower ones
        # would leave most bins empty and put the histogram's peak anywhere.
        width = max(1, int(np.ceil((hi - lo + 1) / 4096)))
        lo = np.floor(lo) - 0.5
        bins = max(1, int(np.ceil((np.ceil(hi) + 0.5 - lo) / width)))
        hi = lo + bins * width
    else:
        bins = int(min(4096, max(64, np.ceil(hi - lo))))
    hist, edges = np.histogram(v, bins=bins, range=(lo, hi))
    smooth = ndimage.gaussian_filter1d(hist.astype(np.float64), 2.0)
    k = int(np.argmax(smooth))
    near = v[(v >= edges[max(k - 2, 0)]) & (v < edges[min(k + 3, bins)])]
    # the peak located finer than a bin
    level = float(near.mean()) if near.size else float(0.5 * (edges[k] + edges[k + 1]))
    below = v[v < level] - level
    sigma = float(np.sqrt(np.mean(below**2))) if below.size > 10 else 1e-6
    return level, max(sigma, 1e-6)


def preprocess(image: np.ndarray, background: float, sigma: float, threshold_sigma: float, grow: int = 0
               ) -> tuple[np.ndarray, np.ndarray]:
    """Background-subtracted signal and the lit-pixel mask.

    A particle anywhere inside a voxel sends each sub-aperture's light to the same pixel under
    a lenslet as the voxel centre does (the pixel encodes the direction, which a shift within a
    voxel changes by far less than a pixel), so no margin is needed for ideal optics; ``grow``
    widens the lit mask by that many pixels to tolerate calibration error in real rigs.

    Returns
    -------
    signal
        (rows, columns) float32, zero on unlit pixels.
    lit
        (rows, columns) bool: signal above ``threshold_sigma`` sigmas (grown by ``grow``).
    """
    s = np.asarray(image, dtype=np.float32) - np.float32(background)
    lit = s > threshold_sigma * sigma
    signal = np.where(lit, s, np.float32(0.0)).astype(np.float32)
    if grow > 0:
        lit = ndimage.binary_dilation(lit, structure=np.ones((3, 3), bool), iterations=grow)
    return signal, lit


def reconstruct(projector: Projector, images: Sequence[np.ndarray], settings: ReconSettings,
                progress: Callable[[int], None] | None = None, cache: WeightCache | None = None,
                budget_bytes: int | None = None) -> ReconResult:
    """Reconstruct one volume from one image per camera of the projector.

    Parameters
    ----------
    projector
        Cameras and grid on a device.
    images
        One raw (rows, columns) image per camera, in the projector's camera order, in counts.
    settings
        Method, iterations, relaxation, form, thresholds.
    progress
        Called with 1 after each iteration.
    cache
        Weights kept across calls (built on ``projector``): each frame then traces only the
        voxels no earlier frame kept. Used by DRT-MART when it holds DRT weights and by
        MLOS-MART when it holds line-of-sight ones (ignored otherwise, and when its weights
        would not fit); None: build them directly.
    budget_bytes
        Device memory the weights and the iterations may take; None: what the device has free.
        With ``settings.weight_storage = "auto"``, line-of-sight weights beyond it are made on
        the fly.

    Returns
    -------
    ReconResult

    Raises
    ------
    MemoryBudgetError
        If the weights or the iteration buffers do not fit in the device's memory.
    """
    if cache is not None and cache.projector is not projector:
        raise ValueError("the weight cache belongs to another projector")
    if len(images) != len(projector.cameras):
        raise ValueError(f"got {len(images)} images for {len(projector.cameras)} cameras")
    signals, lits, backgrounds, noises = [], [], [], []
    for img, cam in zip(images, projector.cameras, strict=True):
        if img.shape != (cam.sensor_px[1], cam.sensor_px[0]):
            raise ValueError(f"camera '{cam.name}' images are {cam.sensor_px[1]} x {cam.sensor_px[0]}, "
                             f"got {img.shape[0]} x {img.shape[1]}")
        level, sigma = estimate_background(img)
        if settings.background is not None:
            level = settings.background
        sig, lit = preprocess(img, level, sigma, settings.threshold_sigma, settings.lit_grow)
        signals.append(sig)
        lits.append(lit)
        backgrounds.append(level)
        noises.append(sigma)

    what = f"{settings.method} of a {projector.grid.n_voxels:,}-voxel box"
    with out_of_memory_is_budget_error(projector.device, what, "use a coarser --pvr or a smaller volume"):
        return _reconstruct(projector, signals, lits, backgrounds, noises, settings, progress, cache, budget_bytes)


def _weight_budget(projector: Projector, n_active: int, budget_bytes: int | None) -> int:
    """Bytes the weights of ``n_active`` voxels may take: the budget less what the iterations
    and the result need beside them (per pixel the image, its projection and log ratio; per
    active voxel its intensity; the dense volume and its smoothing)."""
    free = available_bytes(projector.device) if budget_bytes is None else int(budget_bytes)
    return free - 12 * projector.n_pixels - 4 * n_active - 8 * projector.grid.n_voxels


def _reconstruct(projector: Projector, signals: list[np.ndarray], lits: list[np.ndarray], backgrounds: list[float],
                 noises: list[float], settings: ReconSettings, progress: Callable[[int], None] | None,
                 cache: WeightCache | None, budget_bytes: int | None) -> ReconResult:
    wp = projector.wp
    t0 = time.perf_counter()
    t_elim = t0
    kind = WEIGHTS[settings.method]
    storage = "stored" if kind == "drt" or settings.form == "sequential" else settings.weight_storage
    if settings.method == "mart":
        voxels = projector.all_voxels()
    else:
        voxels = projector.eliminate(lits, settings.min_seen, settings.max_dark)  # returns once counted: synced
        t_elim = time.perf_counter()
    weights = None
    if cache is not None and cache.method == kind and settings.method != "mart" and storage != "on-the-fly":
        try:
            weights = cache.weights(voxels)
        except MemoryBudgetError:
            if storage == "stored":
                raise
    if weights is None:
        budget = _weight_budget(projector, int(voxels.shape[0]), budget_bytes)
        weights = projector.weights(voxels, kind, budget_bytes=budget, storage=storage)
    dev = projector.device
    image = wp.array(np.concatenate([s.ravel() for s in signals]), dtype=float, device=dev)
    n = weights.n_voxels
    e = wp.full(max(n, 1), 1.0, dtype=float, device=dev)
    proj = projector.forward(weights, e)
    # Start uniform, scaled so the projection carries the measured total signal.
    total_proj = float(proj.numpy().sum())
    start = float(image.numpy().sum()) / total_proj if total_proj > 0 else 0.0
    e.fill_(start)
    wp.synchronize_device(dev)
    t1 = time.perf_counter()
    floor = settings.floor * settings.threshold_sigma * float(np.mean(noises))
    floor = max(floor, 1e-6)
    transposed = projector.transpose(weights) if settings.form == "sequential" and n else None
    for _ in range(settings.iterations if n else 0):
        if transposed is not None:
            projector.mart_sweep(transposed, image, e, settings.relaxation, floor)
        else:
            projector.forward(weights, e, proj)
            projector.smart_update(weights, image, proj, e, settings.relaxation, floor)
        if progress is not None:
            progress(1)
    wp.synchronize_device(dev)
    t2 = time.perf_counter()
    vol = projector.scatter(weights, e)
    if settings.smooth > 0:  # on the device: a host filter would dominate a large GPU volume
        VolumeOps(projector.grid.shape, dev).smooth(vol, settings.smooth)
    volume = vol.numpy()
    return ReconResult(volume=volume, active_voxels=n, active_fraction=n / projector.grid.n_voxels,
                       nnz=weights.nnz, weight_bytes=weights.nbytes, weights_s=t1 - t0, iterate_s=t2 - t1,
                       iterations=settings.iterations, background=backgrounds, noise=noises,
                       eliminate_s=t_elim - t0, on_the_fly_voxels=weights.n_on_the_fly)
