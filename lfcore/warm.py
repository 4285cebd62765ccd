"""Warm starts along a series: a frame's MART starts from the last frame's intensities carried along
the predicted displacement, instead of from a uniform volume.

Frame B of a pair shows frame A's particles moved by the flow over ``dt``; where the displacement is
predicted (the last pair's measured field, in batch and live), A's reconstructed intensities carried
along it are already most of B's answer, and MART needs a fraction of its iterations to correct what
the predictor missed (motion-tracking-enhanced MART, Novara, Batenburg and Scarano 2010; Lynch and
Scarano 2015 for time series). On the small light-field rig, B started from A carried by the true
displacement reaches Q 0.80 in 5 iterations where the uniform start needs 50 for 0.76.

MART's update is multiplicative: a voxel that starts at zero stays at zero. So the start is the
carried intensities blurred by ``blur`` voxels (the predictor's error: a carried particle must
overlap where it really is), plus ``blend`` times their mean on every active voxel (what the
predictor missed, or what entered the box, can still grow); the reconstructor then scales it so its
projection carries the measured signal, as it does the uniform start. A predictor half a displacement
off still starts B better than uniform at equal iterations (benchmarks/warm.py).

Arrays are (z, y, x) volumes on the device; displacements are (x, y, z) in voxels, like the vector
fields of :mod:`lfcore.correlate`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfcore.correlate import MIN_WINDOW, CorrelationConfig, correlate
from lfcore.device import RowOffset, launch_rows, resolve_device, warp
from lfcore.device_ops import VolumeOps
from lfcore.operator import Operator, gather

__all__ = ["LAST_PAIR", "OWN_PAIR", "PREDICTOR_WINDOW", "WARM_BLEND", "WARM_BLUR", "WARM_POWER", "WARM_PREDICTORS",
           "Predictor", "WarmStart", "predictor_config", "predictor_field", "sharpened", "with_floor"]

#: Gaussian sigma, voxels, of the carried intensities: the predictor's error it forgives.
WARM_BLUR = 0.5
#: Share of the carried intensities' mean added on every active voxel, so that what the predictor
#: missed can grow (MART cannot grow a zero).
WARM_BLEND = 0.1
#: Power the carried (and blurred) intensities are raised to, before the blend, where the warm frame runs
#: no line-of-sight iterations first (MLOS-MART's: the plan for several light-field cameras;
#: :meth:`WarmStart.start`, :func:`sharpened`); 1: as carried. Raised, the carried particles start
#: narrower and frame A's dim ghosts dimmer, and frames B reach the cold Q in the warm count, but the
#: vectors lose what the warm start gave them (fifteenth session, own predictor, 15 iterations; Q of
#: frames B, vector RMS of all pairs x, y, z voxel): ``two_cameras`` cropped (10 pairs; uniform starts
#: 0.839 in 75) at 1: Q 0.817 (0.808 after 10), 0.397, 0.594, 0.408; at 2: **Q 0.843** (0.837 after 10),
#: CPU a frame B 4.1 -> 2.7 s, but 0.551, 0.707, 0.601 (at 1.5: 0.837, 0.417, 0.610, 0.476);
#: ``two_cameras_off_focus`` (6 pairs; 0.943) at 1:
#: 0.939, 0.528, 0.664, 0.524; at 1.5 0.948, 0.657, 0.696, 0.641; at 2 0.948, 0.702, 0.707, 0.696 (worse
#: than uniform starts' 0.681, 0.716, 0.600 of pairs 2-6); the demo's ring 20.7% -> 20.8%; the live
#: monitor's warm frames (raised by hand: it calls :meth:`WarmStart.start` without a power) 23.55% ->
#: 25.39%. So 1: the vectors are the product. Where line-of-sight iterations come first (one camera's
#: DRT-MART) the start is never raised: after its 3 the hand-over to DRT weights keeps the voxels above
#: 2% of the brightest (``lfcore.reconstruct.WARM_HANDOVER``), and a raised start's entering particles
#: fell below it (two cameras so run: found 0 of 8 against 5, Q 0.742 against 0.814).
WARM_POWER = 1.0
#: Where a warm-started frame B's predictor comes from (``ReconSettings.warm_predictor``): ``"own"``, the
#: pair's own data (frame A's volume correlated with a cheap line-of-sight volume of B, made before B's
#: fine iterations: B then depends on its own pair alone, and every pair's B warm-starts, the first
#: included); ``"last"``, the field the last pair a reconstructor made measured (B then depends on which
#: pair that was; the first pair's B starts uniform).
OWN_PAIR, LAST_PAIR = "own", "last"
WARM_PREDICTORS = (OWN_PAIR, LAST_PAIR)


@dataclass(frozen=True)
class Predictor:
    """A displacement field from one frame to the next, on a regular grid of points.

    Attributes
    ----------
    displacement
        (nz, ny, nx, 3) float32 displacements (x, y, z), in voxels, at the grid's points.
    origin
        Voxel coordinates (x, y, z) of point [0, 0, 0].
    step
        Spacing (x, y, z) of the points, in voxels (positive).
    """

    displacement: np.ndarray
    origin: tuple[float, float, float]
    step: tuple[float, float, float]

    def __post_init__(self) -> None:
        d = np.asarray(self.displacement, dtype=np.float32)
        if d.ndim != 4 or d.shape[3] != 3 or 0 in d.shape:
            raise ValueError(f"a predictor's displacement is (nz, ny, nx, 3), got {d.shape}")
        if not np.all(np.isfinite(d)):
            raise ValueError("a predictor's displacements must be finite (replace the missing vectors first)")
        if len(self.step) != 3 or not all(s > 0 for s in self.step):
            raise ValueError(f"a predictor's step is three positive spacings (x, y, z), got {self.step}")
        object.__setattr__(self, "displacement", np.ascontiguousarray(d))
        object.__setattr__(self, "origin", tuple(float(o) for o in self.origin))
        object.__setattr__(self, "step", tuple(float(s) for s in self.step))

    @classmethod
    def uniform(cls, shift: tuple[float, float, float]) -> Predictor:
        """The same displacement (x, y, z voxels) everywhere."""
        return cls(np.asarray(shift, dtype=np.float32).reshape(1, 1, 1, 3), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    @classmethod
    def from_field(cls, field) -> Predictor:
        """The predictor of a correlation's :class:`~lfcore.correlate.VectorField`: its displacements
        at its window centres, those it could not measure (NaN) set to the median of the others
        (zero where none was measured)."""
        d = np.array(field.displacement, dtype=np.float32)
        bad = ~np.all(np.isfinite(d), axis=-1)
        if bad.all():
            d[:] = 0.0
        elif bad.any():
            d[bad] = np.median(d[~bad], axis=0)
        g = field.grid
        return cls(d, tuple(float(v) for v in g.origin), tuple(float(v) for v in g.step))

    def mean(self) -> np.ndarray:
        """The mean displacement (x, y, z), voxels."""
        return self.displacement.reshape(-1, 3).mean(axis=0)

#: Largest window side, voxels, of the predictor's correlation (:func:`predictor_config`).
PREDICTOR_WINDOW = 48


def predictor_config(shape: tuple[int, int, int]) -> CorrelationConfig:
    """The correlation that measures a pair's predictor for the next pair: two FFT passes, the first
    with windows of about a third of the box per axis and the second half as large (multiples of
    4, from twice :data:`lfcore.correlate.MIN_WINDOW` to :data:`PREDICTOR_WINDOW` voxels), at 50% overlap,
    outliers replaced: coarse and cheap, a warm start forgives a voxel of error (:data:`WARM_BLUR`).

    Parameters
    ----------
    shape
        (nz, ny, nx) of the volumes.
    """
    def side(n: int, share: float) -> int:
        # never longer than the volume along the axis (a box thinner than a window has it whole)
        return int(min(PREDICTOR_WINDOW, n, max(2 * MIN_WINDOW, int(n * share) // 4 * 4)))

    nz, ny, nx = (int(n) for n in shape)
    first = (side(nx, 1 / 3), side(ny, 1 / 3), side(nz, 1 / 3))
    second = tuple(min(w, max(2 * MIN_WINDOW, w // 2 // 4 * 4)) for w in first)
    windows = (first,) if second == first else (first, second)
    return CorrelationConfig(windows=windows, overlap=0.5, deform_iterations=0)


def predictor_field(volume_a, volume_b, *, device: str | None = None) -> Predictor | None:
    """A pair's displacement field as the next pair's predictor: the correlation of
    :func:`predictor_config` of its two volumes ((nz, ny, nx) float32, host or device); None where
    the box is too thin to correlate (fewer than :data:`lfcore.correlate.MIN_WINDOW` voxels along an
    axis): the next frame then starts uniform."""
    shape = tuple(int(n) for n in volume_a.shape)
    if min(shape) < MIN_WINDOW:
        return None
    config = predictor_config(shape)
    return Predictor.from_field(correlate(volume_a, volume_b, config=config, device=device))


class WarmStart:
    """A frame's intensities kept on the device, and the next frame's start made from them.

    Parameters
    ----------
    shape
        (nz, ny, nx) of the volume.
    device
        Warp device; None for the first GPU, else the CPU.
    blur
        Gaussian sigma, voxels, applied to the carried intensities (:data:`WARM_BLUR`).
    blend
        Share of their mean added on every active voxel (:data:`WARM_BLEND`).

    Notes
    -----
    Holds two (z, y, x) float32 volumes on the device (the kept intensities and the carried ones)
    and the smoothing's scratch. One thread at a time.
    """

    def __init__(self, shape: tuple[int, int, int], *, device: str | None = None, blur: float = WARM_BLUR,
                 blend: float = WARM_BLEND) -> None:
        if not 0 <= blur <= 10:
            raise ValueError(f"the warm start's blur must be from 0 to 10 voxels, got {blur}")
        if not 0 < blend <= 10:
            raise ValueError(f"the warm start's blend must be above 0 (MART cannot grow a zero) and at most 10, "
                             f"got {blend}")
        from lfcore._kernels import correlate as kc

        self._kc = kc
        self.wp = warp()
        self.device = resolve_device(device)
        self.shape = tuple(int(n) for n in shape)
        self.blur = float(blur)
        self.blend = float(blend)
        self.ops = VolumeOps(self.shape, device=self.device)
        self._kept = None  # (z, y, x): the last kept frame's intensities
        self._carried = None  # (z, y, x): them carried along a predictor
        self.held = False

    def keep(self, op: Operator, e) -> None:
        """Keep the intensities ``e`` ((n,) float32 on the device) of ``op``'s voxels as the next start's
        source (unsmoothed: the reconstruction's own smoothing is for the correlation)."""
        if self._kept is None:
            self._kept = self.ops.empty()
        op.scatter(e, out=self._kept)
        self.held = True

    @property
    def kept(self):
        """The kept frame's (z, y, x) float32 intensities on the device (None before :meth:`keep`)."""
        return self._kept if self.held else None

    def forget(self) -> None:
        """Start the next frame uniform (a new series, or a frame that is not the last one's successor)."""
        self.held = False

    def start(self, op: Operator, predictor: Predictor, *, power: float = 1.0):
        """The start of ``op``'s voxels: the kept intensities carried along ``predictor``, blurred, raised
        to ``power`` (:func:`sharpened`; :data:`WARM_POWER` where the frame runs no line-of-sight
        iterations first), with :attr:`blend` of their mean added; unscaled (the reconstructor scales it
        to the signal).

        Returns
        -------
        warp.array
            (n,) float32 on the device, n = ``op.n_voxels``.

        Raises
        ------
        RuntimeError
            If no frame was kept (:meth:`keep`).
        ValueError
            If ``power`` is below 1 or above 4.
        """
        if not self.held:
            raise RuntimeError("no frame kept to start from; keep() one first")
        if not 1 <= power <= 4:
            raise ValueError(f"the warm start's power must be from 1 to 4, got {power}")
        wp = self.wp
        if self._carried is None:
            self._carried = self.ops.empty()
        pred = wp.array(predictor.displacement, dtype=wp.vec3, device=self.device)
        launch_rows(self._kc.advect_volume, self.shape[0],
                    [self._kept, pred, wp.vec3(*predictor.origin), wp.vec3(*predictor.step), RowOffset(0),
                     self._carried], self.device, rest=self.shape[1:])
        self.ops.smooth(self._carried, self.blur)
        flat = self._carried.reshape(int(np.prod(self.shape)))
        # sharper (a carried ghost dimmer beside a carried particle), then every active voxel gets a share
        # of the mean: a uniform start where nothing was carried
        return with_floor(sharpened(gather(flat, op.voxels), power, copy=False), self.blend, copy=False)


def sharpened(e, power: float, *, copy: bool = True):
    """``e`` raised to ``power``, each element taken as a share of their mean first (so the values
    stay of the order of 1 whatever their scale; a start is scaled to the signal later): the bright
    voxels of a carried volume brighter against the dim ones, a particle's spot narrower.

    Parameters
    ----------
    e
        (n,) float32 Warp array of intensities, non-negative (a negative one is taken as zero where
        ``power`` is not 1).
    power
        1 or more; 1 returns ``e`` as it is (copied where ``copy``).
    copy
        Return a new array (else ``e`` changed in place).

    Returns
    -------
    warp.array
        (n,) float32 on ``e``'s device; all zero where ``e`` is.

    Raises
    ------
    ValueError
        If ``power`` is below 1 (or not a number).
    """
    from lfcore._kernels import mart as km

    if not power >= 1:
        raise ValueError(f"the power must be 1 or more, got {power}")
    wp = warp()
    out = wp.clone(e) if copy else e
    n = int(out.shape[0])
    if n and power != 1:
        mean = _sum(out) / n
        # no positive mean (all zero, or no more light than the negative values take away): only the
        # negative values set to zero
        wp.launch(km.power_of_share, dim=n, inputs=[out, 1.0 / mean if mean > 0 else 1.0, float(power)],
                  device=str(out.device))
    return out


def with_floor(e, share: float, *, copy: bool = True):
    """``e`` plus ``share`` of its mean on every element (1 everywhere where it is all zero): a start
    MART can grow everywhere from (its update multiplies, so a zero stays zero).

    Parameters
    ----------
    e
        (n,) float32 Warp array of intensities, non-negative.
    share
        Of the mean, added to each.
    copy
        Return a new array (else ``e`` changed in place).

    Returns
    -------
    warp.array
        (n,) float32 on ``e``'s device.
    """
    from lfcore._kernels import mart as km

    wp = warp()
    out = wp.clone(e) if copy else e
    n = int(out.shape[0])
    if n:
        mean = _sum(out) / n
        wp.launch(km.scale_shift, dim=n, inputs=[out, 1.0, share * mean if mean > 0 else 1.0], device=str(out.device))
    return out


def _sum(a) -> float:
    if a.device.is_cpu:
        return float(a.numpy().astype(np.float64).sum())
    return float(warp().utils.array_sum(a))
