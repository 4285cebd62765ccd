"""What the live path may be told: its reconstruction methods, monitoring settings and windows.

Nothing here runs anything: :class:`LiveSettings` (what may change while the pipeline runs),
:func:`monitoring_recon` (the fixed reconstruction settings of monitoring) and
:func:`default_windows` (correlation windows that fit the live volume). The staging, the
processing and the view of a pair (:mod:`realtime.staging`, :mod:`realtime.processing`,
:mod:`realtime.view`) and the pipeline that runs them (:mod:`realtime.pipeline`) take them
from here.
"""

from __future__ import annotations

from dataclasses import dataclass

from lfcore.reconstruct import ReconSettings

__all__ = ["AXES", "LIVE_METHODS", "LiveSettings", "check_live_method", "default_windows", "monitoring_recon"]

#: Slice axes: the axis normal to the slice.
AXES = ("x", "y", "z")

#: Reconstruction methods the live path runs: all eliminate zero voxels, so their weights
#: follow the particles and can be cached. ``mlos-smart`` is for pinhole (Tomo-PIV) cameras.
LIVE_METHODS = ("drt-mart", "mlos-mart", "mlos-smart")


def monitoring_recon(iterations: int = 5, relaxation: float = 1.0, method: str = "drt-mart", *,
                     projector: str = "auto", warm_start: bool = False) -> ReconSettings:
    """Settings for monitoring: few simultaneous iterations, the default thresholds.

    ``method`` is one of :data:`LIVE_METHODS`; ``projector`` one of
    :data:`lfcore.operator.PROJECTORS` (what applies DRT-MART's operator, as in
    :class:`~lfcore.reconstruct.ReconSettings`); ``warm_start``: frame B of each pair starts from
    frame A carried along the last pair's field (:mod:`lfcore.warm`).

    Raises
    ------
    ValueError
        A method the live path does not run, or a projector the method cannot use.
    """
    check_live_method(method)
    return ReconSettings(method=method, iterations=iterations, relaxation=relaxation, form="simultaneous",
                         projector=projector, warm_start=warm_start)


def check_live_method(method: str) -> None:
    """A :class:`ValueError` naming the live path's methods unless ``method`` is one of them."""
    if method not in LIVE_METHODS:
        raise ValueError(f"the live path runs {', '.join(LIVE_METHODS[:-1])} or {LIVE_METHODS[-1]}, not '{method}'")


def default_windows(shape: tuple[int, int, int], passes: int = 2) -> tuple[tuple[int, int, int], ...]:
    """Monitoring windows (x, y, z) for volumes of ``shape`` (z, y, x): ``passes`` sizes, halving.

    The first is the largest power of two no more than 0.6 of the volume along each axis (at
    most 64 voxels, at least 4); each further pass halves it (at least 4).
    """
    if passes not in (1, 2):
        raise ValueError(f"the live pipeline correlates in 1 or 2 passes, got {passes}")
    nz, ny, nx = shape
    first = []
    for n in (nx, ny, nz):
        w = 4
        while w * 2 <= min(64, 0.6 * n):
            w *= 2
        first.append(min(w, n))
    out = [tuple(first)]
    if passes == 2:
        out.append(tuple(max(4, w // 2) for w in first))
    return tuple(out)  # type: ignore[return-value]


@dataclass(frozen=True)
class LiveSettings:
    """What may change while the pipeline runs (taken at the start of each pair).

    Attributes
    ----------
    iterations
        DRT-MART iterations per frame (0: the elimination's uniform start only).
    relaxation
        DRT-MART relaxation (simultaneous form: at most 2).
    slice_axis
        ``"x"``, ``"y"`` or ``"z"``: the axis normal to the slice shown.
    slice_index
        Voxel index of the slice along ``slice_axis``; None for the middle. Clipped to the grid.
    background_every
        Re-estimate each camera's background level and noise every this many processed pairs
        (0: only on the first).
    """

    iterations: int = 5
    relaxation: float = 1.0
    slice_axis: str = "z"
    slice_index: int | None = None
    background_every: int = 50

    def __post_init__(self) -> None:
        monitoring_recon(self.iterations, self.relaxation)  # the reconstruction's own checks
        if self.slice_axis not in AXES:
            raise ValueError(f"slice_axis must be one of x, y, z, got '{self.slice_axis}'")
        if self.background_every < 0:
            raise ValueError(f"background_every must be 0 or more, got {self.background_every}")
