"""What the live path may be told: its routes, reconstruction methods, monitoring settings and windows.

Nothing here runs anything: :data:`LIVE_ROUTES` (volumes and correlation, or particles and
tracks), :class:`LiveSettings` (what may change while the pipeline runs),
:func:`monitoring_recon` (the fixed reconstruction settings of monitoring),
:func:`monitoring_ipr` and :func:`monitoring_tracking` (the particle route's) and
:func:`default_windows` (correlation windows, and the particle route's bins, that fit the live volume). The staging, the
processing and the view of a pair (:mod:`realtime.staging`, :mod:`realtime.processing`,
:mod:`realtime.view`) and the pipeline that runs them (:mod:`realtime.pipeline`) take them
from here.
"""

from __future__ import annotations

from dataclasses import dataclass

from lfcore.ipr import IprSettings
from lfcore.reconstruct import ReconSettings
from lfcore.track import TrackSettings

__all__ = ["AXES", "DEFAULT_LIVE_PROTOCOL", "LIVE_METHODS", "LIVE_PROTOCOLS", "LIVE_ROUTES", "LiveSettings",
           "check_live_method", "check_live_route", "default_windows", "describe_plan", "live_protocol",
           "monitoring_ipr", "monitoring_recon", "monitoring_tracking"]

#: Slice axes: the axis normal to the slice.
AXES = ("x", "y", "z")

#: Reconstruction methods the live path runs: all eliminate zero voxels, so their weights
#: follow the particles and can be cached. ``mlos-smart`` is for pinhole (Tomo-PIV) cameras.
LIVE_METHODS = ("drt-mart", "mlos-mart", "mlos-smart")

#: The live path's routes from a pair's images to its vectors. ``voxels``: frames A and B
#: reconstructed into volumes (one of :data:`LIVE_METHODS`) and cross-correlated, as ``lfpiv
#: reconstruct`` and ``lfpiv correlate`` do; ``particles``: each frame's particles by iterative
#: particle reconstruction (:class:`lfcore.ipr.ParticleReconstructor`) and A's paired with B's
#: into tracks binned on a grid (:func:`lfcore.track.track_pair`), as ``lfpiv particles`` and
#: ``lfpiv track`` do.
LIVE_ROUTES = ("voxels", "particles")


#: Named monitoring plans (``lfpiv monitor --protocol``): the method of light-field cameras and
#: whether frame B of each pair starts warm (:func:`monitoring_recon`'s ``warm_start``); the
#: options a user gives change them (:func:`live_protocol`).
#:
#: ``fast``: MLOS-MART (DRT-MART's elimination, the line-of-sight weights: 4-10x cheaper to build
#: than the traced ones, and the weight cache's rows smaller) and frame B started from frame A
#: carried along the last pair's field with a fifth of the iterations. On the demo's rig (two 256 x
#: 256 light-field cameras, 73 x 73 x 73 voxels) it made a pair 3-4x faster than ``drt`` on a 2-core
#: CPU, its field as close to the truth or closer (``benchmarks/RESULTS.md``, the live pipeline).
#: ``drt``: DRT-MART's traced weights, every frame from the uniform start (the monitor's plan until
#: 2026-12).
LIVE_PROTOCOLS: dict[str, dict] = {
    "fast": {"method": "mlos-mart", "warm_start": True},
    "drt": {"method": "drt-mart", "warm_start": False},
}

#: The plan ``lfpiv monitor`` runs without ``--protocol``.
DEFAULT_LIVE_PROTOCOL = "fast"


def live_protocol(name: str, *, cameras_method: str, method: str | None = None, projector: str = "auto",
                  warm_start: bool | None = None) -> tuple[str, bool]:
    """The method and warm start of the named monitoring plan (:data:`LIVE_PROTOCOLS`), with the
    user's choices applied.

    Parameters
    ----------
    name
        A key of :data:`LIVE_PROTOCOLS`.
    cameras_method
        The cameras' default reconstruction (:func:`lfcore.plan.default_method`): ``"drt-mart"`` for
        light-field cameras (and mixed rigs), ``"mlos-smart"`` for pinhole ones, which every plan keeps.
    method
        The method the user asked for; None: the plan's.
    projector
        The projector asked for: one other than ``"auto"`` applies DRT-MART's operator, so without
        ``method`` it keeps light-field cameras on DRT-MART.
    warm_start
        The warm start asked for; None: the plan's.

    Returns
    -------
    tuple of (str, bool)
        The method and whether frame B starts warm.

    Raises
    ------
    ValueError
        An unknown plan.
    """
    if name not in LIVE_PROTOCOLS:
        raise ValueError(f"the live protocol is one of {', '.join(LIVE_PROTOCOLS)}, not '{name}'")
    plan = LIVE_PROTOCOLS[name]
    if method is None:
        if cameras_method != "drt-mart" or projector != "auto":
            method = cameras_method  # pinhole cameras' own method; or DRT's operator, which --projector picks
        else:
            method = plan["method"]
    return method, plan["warm_start"] if warm_start is None else bool(warm_start)


def describe_plan(protocol: str | None, recon: ReconSettings) -> str:
    """One line for the status line and the monitor's summary: the named plan (None: settings of
    one's own), the method and how frame B starts, e.g. ``"fast (mlos-mart, frame B warm)"``."""
    start = "frame B warm" if recon.warm_start else "uniform starts"
    return f"{protocol or 'custom'} ({recon.method}, {start})"


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


def check_live_route(route: str) -> None:
    """A :class:`ValueError` naming the live path's routes unless ``route`` is one of them."""
    if route not in LIVE_ROUTES:
        raise ValueError(f"the live path's route is {' or '.join(LIVE_ROUTES)}, not '{route}'")


def monitoring_ipr(candidate_iterations: int = 20, rounds: int = 2, *, method: str | None = None) -> IprSettings:
    """The particle route's monitoring settings: :class:`lfcore.ipr.IprSettings` with fewer
    candidate iterations and rounds than ``lfpiv particles``' defaults (50 and 3), and the
    particles modelled by their voxels' operator rows without relocation (``model="voxels"``,
    ``relocate_depth=0``), twice as fast a frame as the point model. The candidates' quick
    reconstruction is plain DRT-MART of a fixed count (``candidate_protocol="fixed"``), the
    candidates the figures below were measured with (``lfpiv particles`` defaults to ``fast``).

    On the demo's rig (two 256 x 256 light-field cameras, 73 x 73 x 73 voxels, 370 particles a
    frame) 20 iterations and 2 rounds found 368 particles in about 16 s a frame on a 2-core CPU
    and the tracks' field was within 12.5% of the peak speed (``benchmarks/RESULTS.md``). On one
    frame of the tiny rig with a second camera at 90 degrees (186 particles, 1000 rays each) the
    voxel model took 4.6 s and found 143 particles, the point model with relocation 8.6 s and 127.

    Raises
    ------
    ValueError
        Fewer than one iteration or round.
    """
    # One copy of the algorithm: the live route calls the same lfcore.ipr functions as ``lfpiv
    # particles``, only its settings differ. It keeps every pixel weighed alike and no residual mask
    # (flat + 0) on every rig, where ``lfpiv particles`` chooses shot + 3 for light-field cameras
    # (lfpiv.jobs.particles.fit_defaults): on the live route those cost 3.1x the CPU and found fewer
    # (benchmarks/RESULTS.md, twelfth session, issue 48).
    return IprSettings(method=method, candidate_iterations=candidate_iterations, candidate_protocol="fixed",
                       rounds=rounds, model="voxels", relocate_depth=0, noise_model="flat", residual_mask=0.0)


def monitoring_tracking(shape: tuple[int, int, int], *, passes: int = 2) -> TrackSettings:
    """The particle route's tracking for live volumes of ``shape`` (z, y, x): bins the size of
    the voxel route's last correlation window (:func:`default_windows`), so that both routes show
    a field on a like grid; the first search an eighth of its first window per axis, at least 4
    voxels (on the demo's rig a wider search, 6 voxels, paired more wrong particles: 15.8% of the
    peak speed instead of 13.1%); the defaults otherwise."""
    windows = default_windows(shape, passes)
    search = tuple(max(4.0, w / 8.0) for w in windows[0])
    return TrackSettings(search_voxels=search, bin_voxels=windows[-1])  # type: ignore[arg-type]


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
        DRT-MART iterations per frame (0: the elimination's uniform start only); the voxel route's
        (the particle route's reconstruction is fixed, :func:`monitoring_ipr`).
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
