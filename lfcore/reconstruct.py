"""3D particle reconstruction: DRT-MART, the MART and MLOS-MART baselines, and MLOS-SMART.

The algorithms iterate over a frame's :class:`~lfcore.operator.Operator` (forward projection,
multiplicative update, scatter), given by an operator source that :mod:`lfcore.plan` chooses;
they never see which kind of operator it is.

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

import importlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy import ndimage

from lfcore import coarse as coarse_grids
from lfcore._deprecation import deprecated, moved_names
from lfcore.coarse import MAX_COARSE
from lfcore.device import available_bytes, out_of_memory_is_budget_error, warp
from lfcore.device_ops import VolumeOps
from lfcore.operator import (
    PROJECTORS,
    STORAGE,
    Operator,
    OperatorSource,
    Projector,
    applied_by,
    check_indexable,
    gather,
    log_ratio,
)
from lfcore.subsets import (
    MAX_SUBSETS,
    SUBSET_HALVING,
    SubsetOperator,
    groups_in_pass,
    ordered_pass,
    pixel_subsets,
    split,
    split_bytes,
)
from lfcore.warm import OWN_PAIR, WARM_BLEND, WARM_POWER, WARM_PREDICTORS, predictor_field, with_floor

if TYPE_CHECKING:  # the concrete operators are the planner's (lfcore.plan) to import
    from lfcore.matrix_free import DrtTemplates
    from lfcore.volume import VolumeGrid
    from lfcore.warm import Predictor, WarmStart
    from lfcore.weight_cache import WeightCache

__all__ = ["CAPPED", "COARSE_METHODS", "CONVERGED", "DRT_OPTIONS", "FIXED", "HANDED_OVER", "HANDOVER_RELAXATION",
           "HANDOVER_STOP_VOXELS", "LOS_STOP_VOXELS",
           "MASKED", "METHODS", "NO_VOXELS", "PROTOCOLS", "PRUNE", "PRUNE_PERCENTILE", "SEVERAL_CAMERAS",
           "SEVERAL_LIGHT_FIELD_CAMERAS", "STOP_REASONS", "STOP_TOLERANCE", "STOP_VOXELS", "WARM_HANDOVER",
           "WARM_LOS_ITERATIONS", "WARM_OWN_ITERATIONS", "WARM_SETTLE", "WARM_SHARE", "WARM_STOP_EVERY", "WEIGHTS",
           "CoarseBright",
           "FrameReconstructor", "Iterated", "ReconResult", "ReconSettings", "StoppingRule", "bright_voxels",
           "coarse_applies", "coarse_bright", "coarse_reconstructor", "estimate_background", "hands_over",
           "is_split", "light_field_plan", "preprocess",
           "preprocess_images", "protocol_settings", "prune_dark", "reconstruct", "relative_residual", "restrict_bytes",
           "smart_iterations", "stop_interval", "unexplained_added", "warm_count"]

METHODS = ("drt-mart", "mart", "mlos-mart", "mlos-smart")
#: The weights each method iterates on (the ``method`` of :meth:`lfcore.operator.Projector.operator`
#: and :class:`~lfcore.weight_cache.WeightCache`). ``mlos-smart`` is Tomo-PIV's MLOS-SMART on pinhole
#: cameras (:mod:`lfcore.pinhole_projector`); on light-field cameras it is MLOS-MART.
WEIGHTS = {"drt-mart": "drt", "mart": "los", "mlos-mart": "los", "mlos-smart": "los"}
#: The methods that may run coarse-to-fine elimination (:attr:`ReconSettings.coarse`): those that eliminate
#: on light-field cameras. On Mc2 (two cameras) MLOS-MART after a coarse grid at 2 reached Q 0.859 at 1/14
#: of the chapter protocol's CPU time (benchmarks/RESULTS.md, 2026-12-06).
COARSE_METHODS = ("drt-mart", "mlos-mart")
#: ``ReconSettings.prune``'s default: voxels dimmer than this fraction of the brightest leave the operator.
#: Measured against the truth (``benchmarks/convergence.py``): on the Mc crop (471,702 active voxels,
#: 784 particles) Q is the unpruned one at every count from 50 to 400 iterations (0.783 at 400) while
#: 14,851 voxels are left at the end and the iterations take 10.6x less time; on the tiny rig Q is
#: 0.003 higher at 100 iterations (the ghosts leave), in 2.3x less time (``benchmarks/RESULTS.md``).
PRUNE = 0.01
#: The percentile of the intensities that stands for the brightest voxels (their maximum is one voxel's).
PRUNE_PERCENTILE = 99.9
#: Above this the simultaneous update overshoots: every voxel on an under-projected pixel grows at
#: once (sequential MART takes the chapter's 2.5 because each pixel's step is small).
MAX_SIMULTANEOUS_RELAXATION = 2.0
#: Widest smoothing sigma accepted, voxels.
MAX_SMOOTH_VOXELS = 10.0
#: Most main-lens sub-apertures per axis for the DRT weights: the default is the pixels per
#: lenslet (about 14), and each voxel traces the square of this many bundles.
MAX_SUB_APERTURES = 64
FORMS = ("simultaneous", "sequential")
#: A warm-started frame's share of a cold one's iterations (``ReconSettings.warm_iterations``'s
#: default): benchmarks/warm.py measured frame B started from A by the last pair's field reaching
#: the cold frame's Q in this share.
WARM_SHARE = 0.2
#: A warm-started frame's line-of-sight iterations where its settings run some first
#: (``ReconSettings.los_iterations``, fewer if they ask for fewer): the carried start already holds
#: frame A's particles where they moved to, so a few are enough for what entered or the predictor
#: missed to grow and for the chance crossings of lines of sight to fade before DRT's weights are
#: built for the voxels still bright. On the tiny rig's vortex ring (``benchmarks/series.py``) 3 then
#: one pass of DRT's weights gave frames B a mean Q of 0.83 against 0.80 with none (DRT's weights for
#: every active voxel, twice the CPU).
WARM_LOS_ITERATIONS = 3
#: The least share of the brightest voxel's intensity a voxel of a warm-started frame needs after its
#: line-of-sight iterations to get DRT weights (the hand-over's threshold; the frame's own is taken
#: where higher). After 3 iterations the chance crossings of lines of sight have not faded as they
#: have after a cold frame's 20 or 30, and at the pruning's 1% a warm frame B of the demo rig built DRT
#: weights for 4 times the voxels of a cold one, its CPU 0.7 of frame A's; at 2% 0.5 of it, Q 0.852
#: against 0.848, and on the tiny rig Q 0.839 at both (at 3% 0.820 and 4-11 iterations instead of 4;
#: ``benchmarks/series.py``).
WARM_HANDOVER = 0.02
#: Iterations (passes through ordered subsets) between the stopping rule's measurements of a
#: warm-started frame. The rule there stops once the residual fell by less than its tolerance over
#: one of them, whatever the voxels leaving (:class:`StoppingRule`'s ``voxels`` test is for ghosts
#: still fading from a uniform start; a warm start's faded over frame A's iterations): after the
#: hand-over to DRT's weights the residual of a warm frame B no longer falls below the start's, and
#: its Q falls with every pass (tiny rig: 0.833 after 3 + 2, 0.812 after 3 + 8, 0.801 where the cold
#: rule stopped it, after 3 + 12 to 17).
WARM_STOP_EVERY = 1
#: Iterations a warm-started frame without line-of-sight iterations first (MLOS-MART's, or a method
#: that has none) runs before the stopping rule may stop it: the carried start is blurred
#: (:data:`lfcore.warm.WARM_BLUR`), its residual is flat from the first iteration, and the rule, measuring
#: every iteration, stops it as soon as it may while its particles still sharpen (after one iteration the
#: demo's were 3.5 voxels across against a cold frame's 2.8, tenth session). Own-pair frames B of the
#: rigs of two light-field cameras (``benchmarks/series.py``'s runs, fourteenth session), at 5, 10 and 15:
#: two_cameras_off_focus Q 0.922, 0.935, 0.939 (cold 0.943), two_cameras cropped 0.788, 0.809, 0.817 (cold
#: 0.838), the vectors the same within 0.015 voxel, CPU a frame B 1.3-1.6 s and 3.0-4.1 s; the demo's ring
#: 21.1%, 20.7%, 20.7% of its peak speed (frames B 0.876, 0.877, 0.874). Under the fast plan's 75
#: iterations 15 is also these frames' most (:data:`WARM_SHARE`), so they run exactly 15 and stop at the
#: cap; where ``warm_iterations`` allows more the rule stops them (at 15 or 16 with 25 allowed: Q 0.943 and
#: 0.820, the ring 20.8%).
WARM_SETTLE = 15
#: Line-of-sight iterations of a frame B (from the coarse grid's start where coarse-to-fine elimination
#: ran, else uniform) whose volume, correlated with frame A's, is the pair's own predictor
#: (``ReconSettings.warm_predictor`` ``"own"``, :data:`lfcore.warm.OWN_PAIR`).
WARM_OWN_ITERATIONS = 5


#: Why a frame's iterations ended (:attr:`ReconResult.stopped`): all it was asked for (no stopping
#: rule), the stopping rule, the most the rule allows, or nothing to iterate.
FIXED, CONVERGED, CAPPED, NO_VOXELS = "fixed count", "converged", "max iterations", "no active voxels"
STOP_REASONS = (FIXED, CONVERGED, CAPPED, NO_VOXELS)
#: Why MLOS-MART's line-of-sight iterations ended where the survivors go on with DRT weights
#: (:attr:`ReconSettings.handover_share`): not a frame's last reason, the DRT stage's is.
HANDED_OVER = "handed over"
#: The relaxation of the iterations on DRT weights after MLOS-MART's hand-over
#: (:attr:`ReconSettings.handover_share`): DRT-MART's own. At MLOS-MART's 2 the traced weights overshoot
#: (the two_cameras rig: Q 0.41 against 0.85 at 1).
HANDOVER_RELAXATION = 1.0
#: The stopping rule's defaults (the ``fast`` protocol's ``stop_tolerance`` and ``stop_voxels``): a frame
#: has converged when, over ``stop_every`` iterations, its projections' relative residual fell by less
#: than 0.3% of itself and fewer than 2% of its voxels left the operator. Measured against the truth
#: (``benchmarks/stopping.py``): the residual alone flattens at the same rate on the tiny rig (whose Q
#: peaks at about 100 iterations) and on the Mc crop (whose Q rises to 400, as ghosts fade below the
#: pruning's threshold), so the voxels leaving tell the two apart.
STOP_TOLERANCE = 0.003
STOP_VOXELS = 0.02
#: The stopping rule's share of the voxels leaving in its plan for several light-field cameras
#: (:data:`SEVERAL_LIGHT_FIELD_CAMERAS`, MLOS-MART at relaxation 2 on line-of-sight weights): their
#: dim ghosts leave at 3-7% per 10 iterations long after Q has settled, so at :data:`STOP_VOXELS`
#: the rule never ended a frame before its most (Mc2: 6.9% left between 30 and 40, 3.1% between 60
#: and 70, Q 0.866 at 40 and 0.869 at 75; S2, still gaining, 12.6% at 40). The margin is thin:
#: two_cameras_off_focus at 1 PPM, still gaining 0.004 after 70, left 7.5% there (8% stopped it).
#: After the hand-over to DRT weights the rule takes DRT-MART's :data:`STOP_VOXELS` again
#: (:data:`HANDOVER_STOP_VOXELS`). Measured against the truth (``benchmarks/RESULTS.md``, eleventh session).
LOS_STOP_VOXELS = 0.07
#: The stopping rule's share of the voxels leaving on DRT weights after MLOS-MART's hand-over
#: (:attr:`ReconSettings.handover_share`), or ``stop_voxels`` where that is stricter: DRT-MART's own, as its
#: relaxation is (:data:`HANDOVER_RELAXATION`). The hand-over's frames need their iterations (two_cameras:
#: Q 0.848 after 40 on DRT weights with 5.4% of the voxels leaving in the last 10, 0.857 at the most).
HANDOVER_STOP_VOXELS = STOP_VOXELS
#: Line-of-sight iterations on the coarse grid of coarse-to-fine elimination (``ReconSettings.coarse``):
#: on the Mc crop 20 iterations left bright 23% of the coarse voxels elimination kept, holding 98.8%
#: of the true particles (``benchmarks/mcfast.py``).
COARSE_ITERATIONS = 20


def warm_count(iterations: int, warm_iterations: int | None) -> int:
    """Iterations of a warm-started frame whose cold count is ``iterations``: ``warm_iterations``,
    or :data:`WARM_SHARE` of ``iterations`` (at least one)."""
    if warm_iterations is not None:
        return int(warm_iterations)
    return max(1, round(WARM_SHARE * iterations))


@dataclass(frozen=True)
class ReconSettings:
    """How to reconstruct.

    Attributes
    ----------
    method
        ``"drt-mart"``, ``"mart"`` (the conventional baseline), ``"mlos-mart"`` (DRT-MART's
        elimination with the baseline's weights) or ``"mlos-smart"`` (pinhole cameras' MLOS
        and line-of-sight weights, :class:`~lfcore.pinhole_projector.PinholeProjector`).
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
    lit_hysteresis
        Noise sigmas above the background at which a pixel next to a lit one (in its 3 x 3
        neighbourhood) is lit too (one step of the hysteresis thresholding of Canny's edge detector,
        which goes on through the pixels so lit; here only a lit pixel's neighbours): the dim rim of
        a particle's spot in a micro-image, which noise pushes below ``threshold_sigma``, stays lit, so
        that a strict elimination (``max_dark`` 0) keeps the particle's voxels, while a lone pixel of
        the background still needs ``threshold_sigma``. Only the lit mask (the elimination) takes it;
        the signal the iterations fit is unchanged. None (default): off; at most ``threshold_sigma``.
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
        weights do not fit is reconstructed slowly rather than refused. On the matrix-free
        projector the same choice holds for the templates' images of the voxels (stored where
        they fit, else applied from the templates in every iteration). Ray-traced DRT weights
        and the sequential form are always stored.
    projector
        What applies DRT-MART's operator: ``"stored"`` ray-traced weights, the ``"matrix-free"``
        templates of :mod:`lfcore.matrix_free` (simultaneous form only; their images stored as
        ``weight_storage`` allows), or ``"auto"``: per frame, the templates' images where they
        cost less to build than tracing the voxels (:meth:`lfcore.plan.AutoSource.templates_pay`)
        and fit in memory, else stored traced weights, and the templates applied in every
        iteration where neither fits (always the traced weights where the cameras have no
        templates).
    prune
        Every ``prune_every`` iterations (from that many on, until the last), the voxels dimmer
        than this fraction of the brightest (the :data:`PRUNE_PERCENTILE` percentile of the
        intensities) leave the operator: MART's multiplicative update keeps a dark voxel dark, so
        the later iterations touch only what may hold a particle (the ghosts leave as well). 0:
        every active voxel is iterated to the end (the chapter's protocol). The simultaneous form
        only (the sequential one iterates them all).
    prune_every
        Iterations between the prunings (and before the first).
    warm_start
        Along a series, start frame B of each pair from frame A's intensities carried by the
        predicted displacement (the last pair's measured field) instead of uniform, and iterate it
        ``warm_iterations`` times (:mod:`lfcore.warm`). The simultaneous form only. With the stopping
        rule (``stop_tolerance``) that is the most it runs: the rule measures a warm frame every
        :data:`WARM_STOP_EVERY` iterations, on the residual alone. Every warm start has the light it
        leaves unexplained added (:func:`unexplained_added`), with or without line-of-sight
        iterations; where ``los_iterations`` asks for them first, a warm frame runs
        :data:`WARM_LOS_ITERATIONS` of them from that start and hands the voxels above
        :data:`WARM_HANDOVER` of the brightest to DRT's weights.
    warm_iterations
        Iterations of a warm-started frame; None: :data:`WARM_SHARE` of ``iterations``.
    warm_predictor
        Where a warm-started frame B's predictor comes from (:data:`lfcore.warm.WARM_PREDICTORS`):
        ``"own"``, its own pair (frame A correlated with :data:`WARM_OWN_ITERATIONS` line-of-sight
        iterations of B; every pair's B warm-starts and depends on its pair alone), or ``"last"``, the
        field the last pair a reconstructor made measured (the first pair's B starts uniform). Read by
        the callers that keep a series (``lfpiv reconstruct``'s pairs).
    los_iterations
        DRT-MART's first iterations on the line-of-sight weights of the MART baseline (cheap to
        build) instead of its own; then the voxels still brighter than ``prune`` (or
        :data:`PRUNE`) of the brightest get DRT weights, and the remaining ``iterations -
        los_iterations`` start from their intensities. The DRT weights, the costliest part of a
        frame, are then built for the share of the active voxels that may hold a particle (a third
        on the Mc case). 0: DRT weights from the start. DRT-MART's simultaneous form, in memory or in
        depth slabs (:mod:`lfcore.slabs`, each slab's line-of-sight weights freed before its DRT weights).
    subsets
        Ordered subsets (OS-SMART, :mod:`lfcore.subsets`): each iteration updates the voxels from
        one of this many interleaved subsets of the pixels at a time, for about the work of one
        update from all of them. 1: the plain simultaneous form. Stored weights held whole, in
        memory or every depth slab's alike (:mod:`lfcore.slabs`; templates applied on the fly and
        weights partly made on the fly keep the plain form). The simultaneous form only.
    subset_halving
        Passes after which the subsets are joined in pairs, halving them, down to one (the plain
        form): many subsets go far in the first passes, and fewer of them then settle on one volume
        instead of cycling between the subsets' (:func:`lfcore.subsets.groups_in_pass`). 0: the same
        ``subsets`` in every pass.
    stop_tolerance
        The stopping rule (:class:`StoppingRule`): every ``stop_every`` iterations the projections'
        relative residual (:func:`relative_residual`) is measured, and the frame stops once it fell
        by less than this fraction of itself over the last ``stop_every`` iterations while fewer than
        ``stop_voxels`` of the voxels left the operator (the pruning); ``iterations`` (or the warm
        count) is then the most it runs. 0 (default): exactly ``iterations``, a fixed count.
    stop_voxels
        The stopping rule's share of the voxels that may leave the operator in ``stop_every``
        iterations of a converged frame (the later iterations' gain is ghosts fading out).
    stop_every
        Iterations between the stopping rule's measurements.
    coarse
        Coarse-to-fine elimination (:mod:`lfcore.coarse`): first ``coarse_iterations`` line-of-sight
        iterations (MLOS-MART's weights, the pruning) on a grid this many times coarser along every
        axis; then only the fine voxels inside the coarse voxels still brighter than ``prune`` (or
        :data:`PRUNE`) of the brightest are tested by the fine grid's elimination, and they start
        from their coarse voxel's intensity. The fine elimination, weights and iterations then touch
        a fraction of the voxels a whole-grid elimination keeps (on the Mc crop at 3: about half,
        the true particles' 98.8%). 1: the whole fine grid is tested (the plain elimination).
        DRT-MART's simultaneous form and MLOS-MART (:data:`COARSE_METHODS`; MLOS-MART only where ``coarse`` is
        given, a protocol's own ``coarse`` is DRT-MART's), on light-field cameras, in boxes of at least
        :data:`lfcore.coarse.COARSE_MIN_VOXELS` voxels (others eliminate the whole grid), in memory or
        in depth slabs (:mod:`lfcore.slabs`: the coarse grid in memory, each slab's fine voxels from
        it). A warm-started frame eliminates so too (its start is the warm one, not the coarse grid's).
    coarse_iterations
        The line-of-sight iterations on the coarse grid (``coarse`` above 1).
    coarse_prune
        Where coarse-to-fine elimination ran (``coarse``), the pruning's threshold on the fine grid (a
        fraction of the brightest, as ``prune``): the line-of-sight passes', the hand-over to DRT's
        weights (``los_iterations``) and the later passes'. The fine grid then starts from the coarse
        grid's volume, in which the ghosts (where lines of sight from lit pixels cross by chance) have
        had ``coarse_iterations`` to fade, so its particles stand further above them than after a
        uniform start, where a small box (the tiny rig: Q 0.772 against 0.786 with a 2% hand-over)
        keeps ``prune``. The coarse grid's own pruning stays at ``prune`` (at 2% it lost particles).
        0: ``prune`` everywhere.
    handover_share
        MLOS-MART's hand-over to DRT weights (:func:`hands_over`): after ``handover_at`` iterations of a
        cold frame, where more than this share of its active voxels are still in the operator (and the
        relative residual is below ``handover_residual``), the voxels still brighter than the pruning's
        threshold get DRT-MART's weights (traced, or the templates as ``projector`` ``"auto"`` chooses)
        and run the rest of ``iterations`` at :data:`HANDOVER_RELAXATION`: on a rig where the
        line-of-sight weights' ghosts leave slowly, DRT's sharper weights tell them from the particles.
        0 (default): never. MLOS-MART's simultaneous form, in memory (depth slabs run line-of-sight
        weights throughout); :data:`SEVERAL_LIGHT_FIELD_CAMERAS` sets it.
    handover_at
        The iteration after which ``handover_share`` is measured (after its pruning: a multiple of
        ``prune_every``).
    handover_residual
        The projections' relative residual (:func:`relative_residual`) the frame must be below to hand
        over: where noise keeps voxels lit the residual is high, and DRT weights do not remove them.
        None: the share alone.
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
    lit_hysteresis: float | None = None
    smooth: float = 0.6
    weight_storage: str = "auto"
    projector: str = "auto"
    prune: float = PRUNE
    prune_every: int = 10
    warm_start: bool = False
    warm_iterations: int | None = None
    warm_predictor: str = OWN_PAIR
    los_iterations: int = 0
    subsets: int = 1
    subset_halving: int = SUBSET_HALVING
    stop_tolerance: float = 0.0
    stop_voxels: float = STOP_VOXELS
    stop_every: int = 10
    coarse: int = 1
    coarse_iterations: int = COARSE_ITERATIONS
    coarse_prune: float = 0.0
    handover_share: float = 0.0
    handover_at: int = 20
    handover_residual: float | None = None

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
        if self.lit_hysteresis is not None and not 0 <= self.lit_hysteresis <= self.threshold_sigma:
            raise ValueError(f"lit_hysteresis must be from 0 to threshold_sigma ({self.threshold_sigma:g}) noise "
                             f"sigmas, or None (off), got {self.lit_hysteresis}")
        if not 0 <= self.smooth <= MAX_SMOOTH_VOXELS:
            # a sigma many voxels wide blurs particles (3 voxels across) into the background
            raise ValueError(f"smooth must be from 0 to {MAX_SMOOTH_VOXELS:g} voxels, got {self.smooth}")
        if self.sub_apertures is not None and not 1 <= self.sub_apertures <= MAX_SUB_APERTURES:
            # the build's time grows with the square: 1000 per axis took minutes on a tiny rig
            raise ValueError(f"sub_apertures must be from 1 to {MAX_SUB_APERTURES} per axis, got "
                             f"{self.sub_apertures}")
        if self.weight_storage not in STORAGE:
            raise ValueError(f"weight_storage must be one of {', '.join(STORAGE)}, got '{self.weight_storage}'")
        if self.weight_storage == "on-the-fly" and self.method == "drt-mart" and self.projector != "matrix-free":
            raise ValueError("DRT-MART's weights are made on the fly by the matrix-free projector alone; use projector "
                             "'matrix-free', or stored weights")
        if self.projector not in PROJECTORS:
            raise ValueError(f"projector must be one of {', '.join(PROJECTORS)}, got '{self.projector}'")
        if self.projector == "matrix-free" and self.method != "drt-mart":
            raise ValueError("the matrix-free projector applies DRT weights; use it with drt-mart")
        if self.projector == "matrix-free" and self.form == "sequential":
            raise ValueError("the matrix-free projector runs the simultaneous form; use form 'simultaneous'")
        if self.weight_storage == "on-the-fly" and self.form == "sequential":
            raise ValueError("the sequential form needs stored weights; use the simultaneous form for on-the-fly "
                             "weights")
        if not 0.0 <= self.prune < 1.0:
            raise ValueError(f"prune must be from 0 (none) to below 1 (a fraction of the brightest voxels' "
                             f"intensity), got {self.prune}")
        if self.prune_every < 1:
            raise ValueError(f"prune_every must be 1 or more iterations, got {self.prune_every}")
        if self.warm_start and self.form == "sequential":
            raise ValueError("a warm start runs the simultaneous form; use form 'simultaneous'")
        if self.los_iterations < 0:
            raise ValueError(f"los_iterations must be 0 or more, got {self.los_iterations}")
        if self.los_iterations and (self.method != "drt-mart" or self.form != "simultaneous"):
            raise ValueError("line-of-sight first iterations (los_iterations) are for drt-mart's simultaneous form")
        if self.los_iterations and self.los_iterations >= self.iterations:
            raise ValueError(f"los_iterations ({self.los_iterations}) must be fewer than the iterations "
                             f"({self.iterations}): DRT's weights take over after them")
        if not 1 <= self.subsets <= MAX_SUBSETS:
            raise ValueError(f"subsets must be from 1 (none) to {MAX_SUBSETS}, got {self.subsets}")
        if self.subset_halving < 0:
            raise ValueError(f"subset_halving must be 0 (never) or more passes, got {self.subset_halving}")
        if self.subsets > 1 and self.form != "simultaneous":
            raise ValueError("ordered subsets (subsets) are for the simultaneous form; use form 'simultaneous'")
        if not 0.0 <= self.stop_tolerance < 1.0:
            raise ValueError(f"stop_tolerance must be from 0 (a fixed count) to below 1 (a fraction of the residual), "
                             f"got {self.stop_tolerance}")
        if not 0.0 <= self.stop_voxels < 1.0:
            raise ValueError(f"stop_voxels must be from 0 to below 1 (a fraction of the voxels), got "
                             f"{self.stop_voxels}")
        if self.stop_every < 1:
            raise ValueError(f"stop_every must be 1 or more iterations, got {self.stop_every}")
        if self.warm_predictor not in WARM_PREDICTORS:
            raise ValueError(f"warm_predictor must be one of {', '.join(WARM_PREDICTORS)}, got '{self.warm_predictor}'")
        if self.warm_iterations is not None and self.warm_iterations < 1:
            raise ValueError(f"warm_iterations must be 1 or more, got {self.warm_iterations}")
        if not 1 <= self.coarse <= MAX_COARSE:
            raise ValueError(f"coarse must be from 1 (none) to {MAX_COARSE} fine voxels per coarse one, got "
                             f"{self.coarse}")
        if self.coarse > 1 and (self.method not in COARSE_METHODS or self.form != "simultaneous"):
            raise ValueError("coarse-to-fine elimination (coarse) is for drt-mart's simultaneous form and mlos-mart's")
        if self.coarse_iterations < 1:
            raise ValueError(f"coarse_iterations must be 1 or more, got {self.coarse_iterations}")
        if not 0.0 <= self.handover_share < 1.0:
            raise ValueError(f"handover_share must be from 0 (never) to below 1 (a share of the active voxels), got "
                             f"{self.handover_share}")
        if self.handover_share and (self.method != "mlos-mart" or self.form != "simultaneous"):
            raise ValueError("the hand-over to DRT weights (handover_share) is for mlos-mart's simultaneous form")
        if self.handover_at < 1:
            raise ValueError(f"handover_at must be 1 or more iterations, got {self.handover_at}")
        if self.handover_residual is not None and not self.handover_residual > 0:
            raise ValueError(f"handover_residual must be positive (a relative residual) or None (the share alone), "
                             f"got {self.handover_residual}")
        if not 0.0 <= self.coarse_prune < 1.0:
            raise ValueError(f"coarse_prune must be from 0 (the pruning's prune) to below 1 (a fraction of the "
                             f"brightest voxels' intensity), got {self.coarse_prune}")

    @property
    def warm_count(self) -> int:
        """Iterations of a warm-started frame: ``warm_iterations``, or :data:`WARM_SHARE` of
        ``iterations`` (at least one)."""
        return warm_count(self.iterations, self.warm_iterations)

    @property
    def stopping(self) -> bool:
        """Whether the stopping rule ends the frames (``stop_tolerance`` > 0) rather than a fixed count."""
        return self.stop_tolerance > 0

    @classmethod
    def chapter(cls, **changes) -> ReconSettings:
        """The chapter's protocol (:data:`PROTOCOLS` ``"chapter"``), as its studies run it: a uniform
        start, every active voxel iterated to the end (no pruning), a fixed count, with ``changes``
        (method, iterations, ...) applied."""
        return protocol_settings("chapter", **changes)

    @classmethod
    def protocol(cls, name: str, **changes) -> ReconSettings:
        """The settings of the named protocol (:data:`PROTOCOLS`) with ``changes`` applied
        (:func:`protocol_settings`)."""
        return protocol_settings(name, **changes)

    def as_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


#: Named protocols (``lfpiv reconstruct --protocol``): the settings each changes from
#: :class:`ReconSettings`' defaults.
#:
#: ``chapter``: the chapter's protocol, as ``lfpiv study`` runs it: a uniform start, 400 iterations of
#: every active voxel (no pruning), a fixed count, relaxation 1 in the simultaneous form (the chapter's
#: 2.5 is its sequential form's: ``form="sequential", relaxation=2.5``).
#: ``fixed``: 50 iterations with the dark voxels leaving the operator (``lfpiv reconstruct``'s default
#: before the stopping rule).
#: ``fast`` (``lfpiv reconstruct``'s default): the stopping rule (at most 400 iterations), line-of-sight
#: weights for the first 20 iterations of DRT-MART, the pruning, frame A from a uniform start and frame B
#: warm-started from frame A carried along the pair's own predictor (``warm_start``, ``warm_predictor``
#: ``"own"``: a volume depends on its own pair alone, not on which pairs a process made before it; on
#: the tiny rig's 10-pair series Q of frames B 0.838 against 0.787 from uniform starts, in 0.74 of their
#: CPU, and as good on the demo rig and Mc2: ``benchmarks/series.py``); 6 ordered subsets, the rule measuring per
#: pass (an iteration is then a pass through them), and coarse-to-fine elimination on a grid 3 times
#: coarser in boxes of at least :data:`lfcore.coarse.COARSE_MIN_VOXELS` voxels, with 30 line-of-sight
#: iterations there, after which the fine grid's
#: prunings keep the voxels brighter than 2% of the brightest (``coarse_prune``; 1% in smaller boxes, where
#: the tiny rig lost 0.014 of Q with a 2% hand-over). Measured by ``benchmarks/mcfast.py``
#: (``benchmarks/RESULTS.md``): on the Mc crop Q 0.784 (the chapter's 400 iterations: 0.783) for 1/23.6 to
#: 1/24.8 of the chapter protocol's CPU time in three runs (4 subsets and 20 coarse iterations: Q 0.785,
#: 1/21.0 to 1/22.0 in the same runs); the tiny rig 0.788 (0.786). On several cameras ``fast`` changes
#: as :data:`SEVERAL_CAMERAS` (DRT-MART) and, on light-field cameras without a method given,
#: :data:`SEVERAL_LIGHT_FIELD_CAMERAS` (MLOS-MART) say.
PROTOCOLS: dict[str, dict] = {
    "chapter": {"iterations": 400, "prune": 0.0, "relaxation": 1.0},
    "fixed": {"iterations": 50},
    "fast": {"iterations": 400, "stop_tolerance": STOP_TOLERANCE, "los_iterations": 20, "coarse": 3, "subsets": 6,
             "coarse_prune": 0.02, "coarse_iterations": 30, "warm_start": True},
}


#: What a named protocol changes on a rig of several cameras (:func:`protocol_settings` with
#: ``n_cameras`` above 1), where those settings are not given: ``fast`` drops its ordered subsets and
#: its coarse-to-fine elimination, stops by the rule within 75 iterations and runs the first 30 of them
#: (DRT-MART) on line-of-sight weights. Where depth is resolved
#: by the other camera, a subset that holds a voxel's few pixels in one camera and none in the other
#: updates it along that camera's line of sight alone, scaled up to stand for a full iteration, and
#: its ghosts grow unchecked; the coarse grid's line-of-sight iterations lose particles the fine grid
#: keeps; and Q peaks within 50-75 iterations, after which the ghosts at the crossings of the two
#: cameras' lines of sight grow while the rule, measured on one camera, runs on. Measured against the
#: truth (``benchmarks/mcfast.py --case S2``, ``--case Mc2``, the demo rig; ``benchmarks/RESULTS.md``):
#: Q 0.758 against ``fixed``'s 0.756 on S2 (0.742 with the one-camera settings), 0.811 against 0.805 on
#: the demo rig (0.755), 0.846 against 0.845 on Mc2 (0.808). One camera resolves depth from its own
#: micro-images, which every subset samples, and keeps the one-camera settings. The 30 line-of-sight
#: iterations (20 on one camera) leave DRT's weights to fewer voxels (25,320 of Mc2's 67,266 instead of
#: 34,853: 10% less CPU at the same Q 0.847) and took the demo's ring to 21.8% of its peak speed
#: (20 of 75: 22.2%; ``fixed``: 22.0%; ``benchmarks/ring.py``); a cap of 50 did as well on the demo but
#: cost the chapter's optics (the cropped ``two_cameras`` rig) 0.03 of Q.
#: These are DRT-MART's settings on several cameras: a method given (``--method``), and pinhole or
#: mixed rigs, keep them; rigs of several light-field cameras take :data:`SEVERAL_LIGHT_FIELD_CAMERAS`
#: where no method is given.
SEVERAL_CAMERAS: dict[str, dict] = {"fast": {"subsets": 1, "coarse": 1, "iterations": 75, "los_iterations": 30}}

#: What a named protocol changes on a rig of several light-field cameras (:func:`protocol_settings`
#: with ``n_cameras`` above 1 and ``camera_kind`` ``"light-field"``) where no method is given, on top of
#: :data:`SEVERAL_CAMERAS`: ``fast`` runs MLOS-MART (line-of-sight weights, no DRT weights traced) at
#: relaxation 2 (the most the simultaneous form takes), stopping by the rule within 75 iterations,
#: after coarse-to-fine elimination on a grid 2 times coarser with 15 line-of-sight iterations there
#: (in boxes of at least :data:`lfcore.coarse.COARSE_MIN_VOXELS` voxels). Measured against the truth
#: (``benchmarks/RESULTS.md``, eighth session): Q 0.856 on Mc2 (DRT-MART's best at any of the chapter's
#: counts: 0.844) in about 1/16 of the chapter protocol's CPU time (the 75-iteration DRT-MART plan:
#: 0.847 in 1/6); on the demo rig 0.855 against 0.819 and the demo's ring 20.5% of its peak speed
#: against 21.8%, at two thirds of the CPU; S2 0.767 against 0.761 at half. The elimination keeps its
#: default ``max_dark``: no dark check allowed (``max_dark`` 0) would take Mc2 to 1/22-1/25, but on
#: images with 3 times the renderer's noise it lost Q 0.817 -> 0.629 there (a particle's voxels
#: dropped by one noise-darkened check); on the demo rig and S2 (80 checks a camera) the two are the same.
#: The most was 20 until the ninth session: then the example rig two_cameras (the chapter's dual-camera
#: optics, cropped) reached only Q 0.741 there against DRT-MART's 0.849, and every rig gained from more:
#: at most 75, two_cameras 0.813, S2 0.807 (from 0.767), Mc2 0.869 (0.856, 6.4 against 5.6 CPU s),
#: two_cameras_off_focus at 1 PPM 0.877 (0.749); the demo's ring 21.0% (20.5%). Since the ninth session
#: the elimination is strict (``max_dark`` 0) on a lit mask with hysteresis (``lit_hysteresis`` 0.5
#: sigma: a pixel next to a lit one is lit above half a sigma), which keeps the particles whose spots'
#: dim rims noise darkens: Mc2 Q 0.869 on clean frames (the same), 0.833 at 3x noise (0.827) and 0.720
#: with 3x noise and a camera's response (0.552), the example rigs' clean frames within 0.001.
#: Since the tenth session a frame whose ghosts leave slowly hands its survivors to DRT weights
#: (``handover_share`` 0.4 at ``handover_at`` 20 with ``handover_residual`` 0.27, :func:`hands_over`):
#: where more than 40% of the active voxels are still in the operator after 20 iterations while the
#: projections' relative residual is below 0.27 (the light explained, by ghosts as much as by
#: particles), the voxels still brighter than the pruning's threshold get DRT weights and run the rest
#: of the 75 at DRT-MART's relaxation 1 (:data:`HANDOVER_RELAXATION`). Measured on frame A of each rig
#: (``benchmarks/RESULTS.md``, tenth session), after 20 iterations: two_cameras 46% left, residual 0.23
#: (0.5 PPM) and 49%, 0.20 (1 PPM); Mc2 30%, 0.28; S2 20%, 0.29 and 29%, 0.25; the demo rig 16%, 0.41;
#: two_cameras_off_focus 8%, 0.28 and 17%; Mc2 at 3 times its noise 42%, 0.33 and with a camera's response
#: 46%, 0.39 (the share alone handed those over: Q 0.833 -> 0.823, 0.720 -> 0.716, 1.6 times the CPU).
#: Only two_cameras switches: Q 0.857 against 0.814 (DRT-MART's plan 0.849) in 15.3-18.6 CPU s against
#: 8.3-9.0 (DRT-MART's 17.5), at 1 PPM 0.728 against 0.693 (0.710) in 49 against 27 s (61 s); every other
#: frame runs as before, to the same volume.
#: Since the eleventh session the rule's voxel share is :data:`LOS_STOP_VOXELS` (7% per 10 iterations
#: instead of 2%, DRT weights after a hand-over keeping 2%): Mc2 stops at 40 (Q 0.866 against 0.869 at 75),
#: at 3x noise and with a response too at 50 (0.833, 0.720: the same), S2 at 70 (the same Q); the demo,
#: two_cameras and two_cameras_off_focus run their 75 as before.
SEVERAL_LIGHT_FIELD_CAMERAS: dict[str, dict] = {
    "fast": {"method": "mlos-mart", "relaxation": 2.0, "iterations": 75, "coarse": 2, "coarse_iterations": 15,
             "los_iterations": 0, "max_dark": 0.0, "lit_hysteresis": 0.5, "handover_share": 0.4,
             "handover_at": 20, "handover_residual": 0.27, "stop_voxels": LOS_STOP_VOXELS},
}

#: Options that ask for DRT-MART's weights, so that a rig of several light-field cameras keeps
#: DRT-MART's settings (:data:`SEVERAL_CAMERAS`) where one is given without a method.
DRT_OPTIONS = ("los_iterations", "projector")


def light_field_plan(name: str, *, n_cameras: int = 1, camera_kind: str | None = None,
                     changes: dict | None = None) -> dict:
    """The settings the named protocol changes on a rig of several light-field cameras
    (:data:`SEVERAL_LIGHT_FIELD_CAMERAS`), or ``{}`` where they do not apply: one camera, another
    ``camera_kind`` (pinhole, ``"joint"``, or None: not said), a method given in ``changes``, or an
    option there that asks for DRT-MART's weights (:data:`DRT_OPTIONS`: ``los_iterations``, ``projector``
    other than auto)."""
    changes = changes or {}
    if n_cameras < 2 or camera_kind != "light-field" or changes.get("method") is not None:
        return {}
    if "los_iterations" in changes or changes.get("projector", "auto") != "auto":
        return {}
    return dict(SEVERAL_LIGHT_FIELD_CAMERAS.get(name, {}))


def protocol_settings(name: str, *, n_cameras: int = 1, camera_kind: str | None = None,
                      **changes) -> ReconSettings:
    """The :class:`ReconSettings` of the named protocol (:data:`PROTOCOLS`), with ``changes`` applied.

    A method other than DRT-MART's simultaneous form drops the line-of-sight first iterations and the
    coarse-to-fine elimination (they are DRT-MART's), and the sequential form the warm start and the
    ordered subsets; ``iterations`` given with a protocol that stops by the rule is the rule's most.
    ``n_cameras``, the cameras reconstructed jointly: above 1 the protocol's settings for rigs of
    several cameras (:data:`SEVERAL_CAMERAS`) apply where ``changes`` does not give them.
    ``camera_kind``, the cameras' kind (:func:`lfcore.plan.camera_kind`): ``"light-field"`` on several
    cameras with no method in ``changes`` applies the protocol's plan for several light-field cameras
    (:func:`light_field_plan`); None (the default) and the other kinds keep :data:`SEVERAL_CAMERAS`.
    A plan's ``lit_hysteresis`` is lowered to a ``threshold_sigma`` given below it (where it is the
    threshold itself, the hysteresis lights nothing more).

    Raises
    ------
    ValueError
        An unknown name, or changes :class:`ReconSettings` refuses.
    """
    if name not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {', '.join(PROTOCOLS)}, got '{name}'")
    changes = {k: v for k, v in changes.items() if not (k == "method" and v is None)}
    plan = light_field_plan(name, n_cameras=n_cameras, camera_kind=camera_kind, changes=changes)
    several = {**SEVERAL_CAMERAS.get(name, {}), **plan} if n_cameras > 1 else {}
    merged = {**PROTOCOLS[name], **several, **changes}
    simultaneous = merged.get("form", "simultaneous") == "simultaneous"
    if merged.get("method", "drt-mart") != "drt-mart" or not simultaneous:
        if "los_iterations" not in changes:
            merged["los_iterations"] = 0
        if "coarse" not in changes and not ("coarse" in plan and simultaneous):
            merged["coarse"] = 1  # a protocol's coarse grid is DRT-MART's, unless its plan gives one
        if merged.get("form", "simultaneous") != "simultaneous":
            for key, off in (("warm_start", False), ("subsets", 1)):
                if key not in changes:
                    merged[key] = off
    if (merged.get("method", "drt-mart") != "mlos-mart" or not simultaneous) and "handover_share" not in changes:
        merged.pop("handover_share", None)  # MLOS-MART's hand-over to DRT weights, not another method's
    hysteresis = merged.get("lit_hysteresis")
    if hysteresis is not None and "lit_hysteresis" not in changes:
        # a plan's hysteresis never above a threshold given lower (where it would light nothing more)
        merged["lit_hysteresis"] = min(hysteresis, merged.get("threshold_sigma", ReconSettings.threshold_sigma))
    los = merged.get("los_iterations", 0)
    if los and "los_iterations" not in changes and los >= merged.get("iterations", 50):
        merged["los_iterations"] = 0  # too few iterations for DRT's weights to take over after them
    return ReconSettings(**merged)


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
    projector
        What applied the operator in the words the run store records (:func:`lfcore.operator.applied_by`):
        ``"matrix-free"`` for the templates and their images, ``"stored"`` for every other stored
        weights (``weight_bytes`` is then the templates' memory and the voxels' indices).
    operator
        What the operator was, by name (:data:`lfcore.operator.ALL_KINDS`: ``"traced weights"``,
        ``"template images"``, ...; the kinds of a reconstruction in slabs joined by ``", "``).
    final_voxels
        Voxels left in the operator after the last pruning (``active_voxels`` without pruning;
        :attr:`ReconSettings.prune`).
    warm
        Whether the frame started from the last one's intensities carried by a predictor
        (:mod:`lfcore.warm`; ``iterations`` is then the warm count) rather than uniform.
    predictor_s
        Of a frame warm-started by its own pair's predictor (:data:`lfcore.warm.OWN_PAIR`), the seconds
        its predictor took (the line-of-sight operator's build, which the frame's first iterations then
        use, its iterations and the correlation; not in ``weights_s`` or ``iterate_s``).
    stopped
        Why the iterations ended (:data:`STOP_REASONS`): ``"fixed count"`` (no stopping rule),
        ``"converged"`` (the stopping rule, :attr:`ReconSettings.stop_tolerance`), ``"max iterations"``
        (the rule's most, ``iterations``, reached first) or ``"no active voxels"``; ``iterations`` is
        how many ran (the line-of-sight first ones included).
    handover
        Where MLOS-MART handed its survivors to DRT weights (:attr:`ReconSettings.handover_share`), why, in
        words (the voxels left after its ``handover_at`` iterations); ``""``: it did not.
    slabs
        Depth slabs the volume was reconstructed in (1: in memory; see :mod:`lfcore.slabs`).
    peak_bytes
        Of a reconstruction in slabs, the most bytes its weights and buffers took at once
        (0: not measured).
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
    projector: str = "stored"
    slabs: int = 1
    peak_bytes: int = 0
    operator: str = ""
    final_voxels: int = -1
    warm: bool = False
    stopped: str = FIXED
    predictor_s: float = 0.0
    handover: str = ""

    def __post_init__(self) -> None:
        if self.final_voxels < 0:
            self.final_voxels = self.active_voxels

    @property
    def ms_per_iteration(self) -> float:
        return 1e3 * self.iterate_s / max(self.iterations, 1)


#: The signal of a pixel the flat field masks (:func:`preprocess`): negative, which no measured
#: signal is, so the update and the uniform start skip it.
MASKED = -1.0


def estimate_background(image: np.ndarray) -> tuple[float, float]:
    """Background level and noise sigma of a raw image, in counts.

    Particle light only ever adds to the background, and at LF-PIV seeding densities it may
    cover most pixels, so the background is found as the mode of the image's histogram (a sharp
    peak of width sigma, where particle light spreads broadly) and sigma from the pixels below
    the mode, which particle light cannot reach.
    """
    image = np.asarray(image)
    v = image.astype(np.float64).ravel()
    v = v[np.isfinite(v)]  # a flat-field-corrected image is NaN where its pixels are masked
    if v.size == 0:
        return 0.0, 1e-6
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


def preprocess(image: np.ndarray, background: float, sigma: float, threshold_sigma: float, *, grow: int = 0,
               hysteresis: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Background-subtracted signal and the lit-pixel mask.

    A particle anywhere inside a voxel sends each sub-aperture's light to the same pixel under
    a lenslet as the voxel centre does (the pixel encodes the direction, which a shift within a
    voxel changes by far less than a pixel), so no margin is needed for ideal optics; ``grow``
    widens the lit mask by that many pixels to tolerate calibration error in real rigs.

    ``hysteresis`` (sigmas, :attr:`ReconSettings.lit_hysteresis`; None: off) lights, before the
    growing, every pixel above that many sigmas next to (in the 3 x 3 neighbourhood of) a pixel
    above ``threshold_sigma``: noise pushes the dim rim of a particle's spot below the threshold,
    not a whole spot, so a strict elimination then keeps the particle. The signal is not changed.

    A NaN pixel (masked by the flat field, :func:`lfcore.flatfield.correct`: unlit between
    micro-images, under dust, dead) measured nothing: its signal is :data:`MASKED`, which the
    update reads as no ratio at all (:func:`lfcore.operator.log_ratio`), and it counts as lit, so
    that it neither removes voxels in the elimination nor pulls them dark.

    Returns
    -------
    signal
        (rows, columns) float32, zero on unlit pixels, :data:`MASKED` on masked ones.
    lit
        (rows, columns) bool: signal above ``threshold_sigma`` sigmas (or above ``hysteresis`` next to
        such a pixel; grown by ``grow``), or masked.
    """
    s = np.asarray(image, dtype=np.float32) - np.float32(background)
    masked = np.isnan(s)
    lit = s > threshold_sigma * sigma
    signal = np.where(lit, s, np.float32(0.0)).astype(np.float32)
    if hysteresis is not None:
        near = ndimage.binary_dilation(lit, structure=np.ones((3, 3), bool))
        lit |= near & (s > hysteresis * sigma)
    if grow > 0:
        lit = ndimage.binary_dilation(lit, structure=np.ones((3, 3), bool), iterations=grow)
    if masked.any():
        signal[masked] = MASKED
        lit |= masked
    return signal, lit


def reconstruct(projector: Projector, images: Sequence[np.ndarray], settings: ReconSettings, *,
                progress: Callable[[int], None] | None = None, cache: WeightCache | None = None,
                budget_bytes: int | None = None) -> ReconResult:
    """Reconstruct one volume from one image per camera of the projector.

    A one-frame :class:`FrameReconstructor`; a stream of frames should keep one of those, which
    keeps its device buffers from frame to frame.

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
    frames = FrameReconstructor(projector, settings, cache=cache, budget_bytes=budget_bytes)
    return frames.reconstruct(images, progress=progress)


def preprocess_images(projector: Projector, images: Sequence[np.ndarray], settings: ReconSettings
                      ) -> tuple[list[np.ndarray], list[np.ndarray], list[float], list[float]]:
    """Check one image per camera of ``projector`` and preprocess each (:func:`preprocess`).

    Returns
    -------
    signals, lits : list of numpy.ndarray
        Per camera, the (rows, columns) background-subtracted signal and lit-pixel mask.
    backgrounds, noises : list of float
        Per camera, the background level used (``settings.background`` where given) and the
        estimated noise, in counts.

    Raises
    ------
    ValueError
        The wrong number of images, or an image of another size than its camera's sensor.
    """
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
        sig, lit = preprocess(img, level, sigma, settings.threshold_sigma, grow=settings.lit_grow,
                              hysteresis=settings.lit_hysteresis)
        signals.append(sig)
        lits.append(lit)
        backgrounds.append(level)
        noises.append(sigma)
    return signals, lits, backgrounds, noises


class Iterated(NamedTuple):
    """The intensities :meth:`FrameReconstructor.iterate` reached, and the time it took.

    Attributes
    ----------
    e
        (max(n, 1),) float32 Warp array on the projector's device: the intensities of the
        operator's n voxels, in their order (a view of the reconstructor's buffer, overwritten
        by its next frame, or after a pruning an array of its own).
    start_s
        Seconds of the uniform start (one forward projection and two sums).
    iterate_s
        Seconds of the iterations (with the prunings).
    op
        The operator the intensities are of: the one iterated, or what its last pruning left
        (:attr:`ReconSettings.prune`); the volume is :meth:`FrameReconstructor.volume` of it.
    iterations
        Iterations that ran (-1: not said).
    stopped
        Why they ended (:data:`STOP_REASONS`).
    """

    e: object
    start_s: float
    iterate_s: float
    op: Operator | None = None
    iterations: int = -1
    stopped: str = FIXED


def relative_residual(image, proj) -> float:
    """The projections' relative residual ||b - Wx|| / ||b|| over the measured pixels (the masked
    ones, :data:`MASKED`, left out; an unlit pixel's measurement is 0, so light projected onto it,
    a ghost's, counts).

    Parameters
    ----------
    image, proj
        (n_pixels,) float32 Warp arrays on one device: the measured signal b (background
        subtracted, zero on unlit pixels) and the forward projection Wx of the intensities, in counts.

    Returns
    -------
    float
        0 for a perfect fit; 1 for an empty volume; 0 where nothing was measured.
    """
    if image.device.is_cpu:
        b, p = image.numpy(), proj.numpy()
        ok = b >= 0
        both = np.array([np.sum(np.square(b - p, dtype=np.float64), where=ok), np.sum(np.square(b, dtype=np.float64),
                                                                                           where=ok)])
    else:
        from lfcore._kernels import mart as km

        wp = warp()
        out = wp.zeros(2, dtype=wp.float64, device=image.device)
        wp.launch(km.residual_sums, dim=int(image.shape[0]), inputs=[image, proj, out], device=image.device)
        both = out.numpy()
    return float(np.sqrt(both[0] / both[1])) if both[1] > 0 else 0.0


class StoppingRule:
    """When a frame's iterations stop (:attr:`ReconSettings.stop_tolerance`): every ``every`` iterations
    the projections' relative residual and the voxels left in the operator are measured, and the frame
    has converged once the residual fell by less than ``tolerance`` of itself since the last
    measurement while fewer than ``voxels`` of the voxels left. With ``tolerance`` 0 it never stops a
    frame (a fixed count).

    Why both: MART's residual flattens long before its volume has settled where ghosts still fade
    below the pruning's threshold (the Mc crop's Q rises from 0.750 to 0.783 between 100 and 400
    iterations while the residual falls by 1.5%), and ghosts leaving are seen as voxels leaving.
    """

    def __init__(self, tolerance: float, *, voxels: float = STOP_VOXELS, every: int = 10, least: int = 0) -> None:
        self.tolerance, self.voxels, self.every, self.least = float(tolerance), float(voxels), int(every), int(least)
        self.last: tuple[float, int] | None = None
        #: the (iterations done, relative residual, voxels) of every measurement, for benchmarks
        self.history: list[tuple[int, float, int]] = []

    @property
    def on(self) -> bool:
        return self.tolerance > 0

    def due(self, done: int) -> bool:
        """Whether to measure after ``done`` iterations (a projection of the intensities they left is at hand)."""
        return self.on and done % self.every == 0

    def converged(self, done: int, residual: float, n_voxels: int) -> bool:
        """Record a measurement after ``done`` iterations; True when the frame has converged."""
        self.history.append((done, residual, n_voxels))
        last, self.last = self.last, (residual, n_voxels)
        if last is None or last[0] <= 0 or done == 0 or done < self.least:
            return False
        fell = (last[0] - residual) / last[0]
        left = (last[1] - n_voxels) / max(last[1], 1)
        return fell < self.tolerance and left < self.voxels


def stop_interval(settings: ReconSettings, *, prune: bool, subsets: int = 1) -> int:
    """Iterations between the stopping rule's measurements: ``settings.stop_every``, or with pruning
    on the least common multiple of it and ``settings.prune_every``, so that every measurement
    window holds a pruning and the voxels leaving are seen (a window without one would pass the
    rule's voxel test whatever the ghosts do).

    With ``subsets`` ordered subsets (a pass through them goes about as far as that many plain
    iterations) both intervals count passes and are divided by ``subsets`` (rounded up,
    :func:`pass_prune_every`): the rule then measures over about as many plain iterations' worth as
    it does without subsets, instead of letting the subsets run ``subsets`` times further past their
    best between two measurements."""
    if subsets > 1:
        every = -(-settings.stop_every // subsets)
        return math.lcm(every, pass_prune_every(settings, subsets)) if prune else every
    return math.lcm(settings.stop_every, settings.prune_every) if prune else settings.stop_every


def pass_prune_every(settings: ReconSettings, subsets: int) -> int:
    """Passes between the prunings of a frame the stopping rule ends: ``settings.prune_every``
    divided by the ordered subsets (rounded up; :func:`stop_interval`)."""
    return -(-settings.prune_every // max(1, subsets))


def _kept_rows(ops: Sequence[Operator], es: Sequence, fraction: float) -> tuple[list[np.ndarray] | None, list]:
    """Each operator's rows (ascending int32) whose voxel is at least ``fraction`` of the brightest of
    all (the :data:`PRUNE_PERCENTILE` percentile of every operator's intensities together), and each
    operator's intensities on the host; None for the rows where no operator holds a voxel."""
    host = [np.asarray(e.numpy()[:op.n_voxels]) for op, e in zip(ops, es, strict=True)]
    values = np.concatenate(host) if host else np.zeros(0, np.float32)
    if values.size == 0:
        return None, host
    threshold = fraction * float(np.percentile(values, PRUNE_PERCENTILE))
    return [np.flatnonzero(h >= threshold).astype(np.int32) for h in host], host


def prune_dark(ops: Sequence[Operator], es: Sequence, fraction: float, *, spend: bool = False
               ) -> tuple[list[Operator], list]:
    """The operators and intensities without their dark voxels: those dimmer than ``fraction`` of
    the brightest of all (the :data:`PRUNE_PERCENTILE` percentile of every operator's intensities
    together: one threshold for the depth slabs of one volume).

    Parameters
    ----------
    ops
        Operators (:class:`~lfcore.operator.Operator`), one per depth slab, or one.
    es
        Their intensities, (n,) float32 Warp arrays (or longer: the first n count).
    fraction
        Of the brightest voxels' intensity, below which a voxel leaves.
    spend
        The operators are the caller's to let go: each one's stored rows go chunk by chunk as the
        kept ones are copied (:meth:`~lfcore.operator.Operator.restrict`), so that the copy and the
        whole never stand together (:func:`restrict_bytes`); a restricted operator is then spent.

    Returns
    -------
    ops, es
        Each operator restricted to its voxels that stay (:meth:`~lfcore.operator.Operator.restrict`),
        with their intensities; an operator that keeps every voxel is returned as it is.
    """
    wp = warp()
    keeps, _ = _kept_rows(ops, es, fraction)
    if keeps is None:
        return list(ops), list(es)
    out_ops, out_es = [], []
    for op, e, keep in zip(ops, es, keeps, strict=True):
        if keep.size == op.n_voxels:
            out_ops.append(op)
            out_es.append(e)
            continue
        rows = wp.array(keep, dtype=wp.int32, device=op.device)
        out_ops.append(op.restrict(rows, spend=spend))
        out_es.append(gather(e, rows) if keep.size else wp.zeros(1, dtype=float, device=op.device)[:0])
    return out_ops, out_es


def _stored_chunks(op) -> list:
    """The CSR chunks ``op`` holds (:class:`lfcore.weight_build.Weights`), its parts' (ordered subsets,
    depth slabs) included."""
    out = list(getattr(op, "chunks", None) or ())
    for part in getattr(op, "parts", None) or ():
        if part is not None:
            out += _stored_chunks(part)
    return out


def _let_go(op) -> None:
    """Let go of the rows of stored weights (:class:`lfcore.weight_build.Weights`) whose entries another
    operator holds now (their ordered subsets' split): they are spent, whoever still refers to them."""
    if hasattr(op, "spent") and hasattr(op, "chunks"):
        op.chunks, op.spent = [], True


def restrict_bytes(op: Operator, *, spend: bool = False) -> int:
    """The most bytes :func:`prune_dark` holds beside ``op`` while it restricts it: without ``spend``
    the copy of the rows it keeps (at most all of them, :attr:`~lfcore.operator.Operator.nbytes`); with
    it one chunk's copy at a time (the largest chunk's entries and row offsets), each chunk let go once
    copied. Both with the kept voxels' indices, intensities and (ordered subsets) scales."""
    n = int(op.n_voxels)
    per_voxel = 4 * n * (2 + int(getattr(op, "n_subsets", 0) or 0))
    if not spend:
        return int(op.nbytes) + per_voxel
    chunks = _stored_chunks(op)
    return max((8 * int(c.nnz) + 8 * (int(c.n) + 1) for c in chunks), default=0) + per_voxel


def bright_voxels(ops: Sequence[Operator], es: Sequence, fraction: float) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The voxels that :func:`prune_dark` would keep, and their intensities, without copying any
    operator's weights: what the next stage's operator is made for (the line-of-sight weights'
    survivors get DRT weights; the coarse grid's bright voxels, fine ones), so that the operators
    can be freed before it is made.

    Parameters
    ----------
    ops, es, fraction
        As :func:`prune_dark`.

    Returns
    -------
    voxels
        Per operator, (k,) int32 flat voxel indices into its grid (its :attr:`voxels` numbering), in
        its row order, on the host.
    values
        Per operator, (k,) float32 intensities of those voxels, on the host.
    """
    keeps, host = _kept_rows(ops, es, fraction)
    if keeps is None:
        keeps = [np.zeros(0, np.int32) for _ in ops]
    voxels = [np.asarray(op.voxels.numpy()[:op.n_voxels], dtype=np.int32)[keep] for op, keep in zip(ops, keeps,
                                                                                                     strict=True)]
    return voxels, [h[keep].astype(np.float32) for h, keep in zip(host, keeps, strict=True)]


def coarse_applies(projector: Projector, settings: ReconSettings) -> bool:
    """Whether frames of ``projector`` (the whole box's) run coarse-to-fine elimination
    (:attr:`ReconSettings.coarse`): DRT-MART's simultaneous form or MLOS-MART (:data:`COARSE_METHODS`) on
    light-field cameras alone (a projector whose elimination takes ``within``), in a box of at least
    :data:`lfcore.coarse.COARSE_MIN_VOXELS` voxels."""
    s = settings
    return (s.coarse > 1 and s.method in COARSE_METHODS and s.form == "simultaneous"
            and getattr(projector, "eliminates_within", False)
            and projector.grid.n_voxels >= coarse_grids.COARSE_MIN_VOXELS)


def coarse_reconstructor(projector: Projector, settings: ReconSettings, *,
                         budget_bytes: int | None = None) -> FrameReconstructor:
    """The reconstructor of coarse-to-fine elimination's coarse grid (:mod:`lfcore.coarse`): the cameras
    of ``projector`` on the grid ``settings.coarse`` times coarser than its (the whole box's), running
    ``settings.coarse_iterations`` of MLOS-MART's line-of-sight iterations with the pruning."""
    from lfcore.plan import projector_for  # the planner's (it imports this module)

    s = settings
    cgrid = coarse_grids.coarse_grid(projector.grid, s.coarse)
    cproj = projector_for(projector.cameras, cgrid, sub_apertures=s.sub_apertures, device=projector.device)
    cset = replace(s, method="mlos-mart", projector="stored", iterations=s.coarse_iterations, los_iterations=0,
                   subsets=1, stop_tolerance=0.0, warm_start=False, coarse=1, prune=s.prune or PRUNE)
    return FrameReconstructor(cproj, cset, budget_bytes=budget_bytes)


class CoarseBright(NamedTuple):
    """The coarse voxels still bright after the coarse grid's iterations (:func:`coarse_bright`).

    Attributes
    ----------
    voxels
        (m,) int64 flat indices of the coarse grid, ascending.
    values
        (m,) float32: their intensities.
    factor
        Fine voxels per coarse voxel along each axis.
    active
        Coarse voxels the coarse elimination kept.
    nbytes
        Device bytes of the coarse grid's operator (freed since).
    copy_bytes
        The most bytes its pruning held beside it (:func:`restrict_bytes`: one chunk's copy).
    """

    voxels: np.ndarray
    values: np.ndarray
    factor: int
    active: int = 0
    nbytes: int = 0
    copy_bytes: int = 0

    def inherited(self, fine: np.ndarray, grid: VolumeGrid, *, z0: int = 0) -> np.ndarray:
        """(n,) float32: the intensity of each fine voxel's coarse voxel (``fine``: flat indices of
        ``grid``'s planes from ``z0`` on, numbered from that plane; each inside a bright coarse voxel)."""
        of = np.searchsorted(self.voxels, coarse_grids.parents(fine, grid, self.factor, z0=z0))
        return self.values[of].astype(np.float32)


def coarse_bright(coarse: FrameReconstructor, lit, image, noise: Sequence[float], *, factor: int) -> CoarseBright:
    """Coarse-to-fine elimination's first stage (:mod:`lfcore.coarse`): the coarse grid's elimination and
    line-of-sight iterations (``coarse``, :func:`coarse_reconstructor`) on the whole box's ``lit``
    pixels and measured ``image``, and the coarse voxels then brighter than its ``settings.prune`` of
    the brightest (:func:`prune_dark`). The in-memory path (:meth:`FrameReconstructor.coarse_eliminate`)
    and the depth slabs (:class:`lfcore.slabs.SlabReconstructor`) both run it.

    Parameters
    ----------
    coarse
        The coarse grid's reconstructor.
    lit
        As :meth:`FrameReconstructor.eliminate` takes it (the whole box's cameras' pixels).
    image
        (n_pixels,) float32 Warp array on the device: the measured signal, in counts.
    noise
        Each camera's noise sigma, in counts.
    factor
        Fine voxels per coarse voxel along each axis (:attr:`ReconSettings.coarse`).

    Returns
    -------
    CoarseBright
        Empty where the coarse elimination kept nothing.
    """
    cvox = coarse.eliminate(lit)
    active = int(cvox.shape[0])
    if active == 0:
        return CoarseBright(np.zeros(0, np.int64), np.zeros(0, np.float32), int(factor))
    given = [coarse.operator(cvox)]
    nbytes, copy_bytes = int(given[0].nbytes), restrict_bytes(given[0], spend=True)
    done = coarse.iterate(given.pop(), image, noise, spend=True)
    (kept,), (values,) = bright_voxels([done.op], [done.e], coarse.settings.prune)
    kept = kept.astype(np.int64)
    del done
    order = np.argsort(kept, kind="stable")
    return CoarseBright(kept[order], values[order], int(factor), active, nbytes, copy_bytes)


def is_split(op) -> bool:
    """Whether ``op`` runs ordered subsets (:class:`lfcore.subsets.SubsetOperator`, or operators of
    depth slabs each split, :class:`lfcore.slabs.SlabOperators`): its iterations are passes through them."""
    return isinstance(op, SubsetOperator) or bool(getattr(op, "ordered_subsets", False))


def smart_iterations(op: Operator, e, image, proj, ratio, noise: Sequence[float], settings: ReconSettings, *,
                     iterations: int | None = None, relaxation: float | None = None,
                     progress: Callable[[int], None] | None = None, start=None, stop_tolerance: float | None = None,
                     split: Callable[[Operator], Operator] | None = None, t0: float | None = None,
                     started: Callable[[float], None] | None = None, prune: float | None = None,
                     warm: bool = False, handover: tuple[int, float, float | None] | None = None,
                     settle: int = 0, stop_voxels: float | None = None, spend: bool = False) -> Iterated:
    """MART's start and iterations on ``op`` in the buffers given: the one loop of
    :meth:`FrameReconstructor.iterate` (in memory) and :class:`lfcore.slabs.SlabReconstructor` (the
    operators of a volume's depth slabs as one, :class:`lfcore.slabs.SlabOperators`).

    Parameters
    ----------
    op
        The voxels and their operator.
    e
        (max(n, 1),) float32 Warp array on ``op``'s device: the intensities' buffer (overwritten).
    image, proj, ratio
        (n_pixels,) float32 Warp arrays: the measured signal in counts (:meth:`FrameReconstructor.iterate`),
        the projection's and the log ratios' scratch (``ratio`` None for the sequential form).
    noise, settings, iterations, relaxation, progress, start, stop_tolerance, prune, warm, stop_voxels
        As :meth:`FrameReconstructor.iterate` takes them.
    split
        Called with the scaled-start operator where ``settings.subsets`` asks for ordered subsets (the
        simultaneous form): the operator to iterate (split, or ``op`` where it is not).
    t0
        :func:`time.perf_counter` when the caller began (the start's seconds count from it).
    started
        Called with the start's seconds once the start is scaled (and the operator split), before the
        first iteration (the depth slabs' stage log).
    settle
        Iterations that run before the stopping rule may stop the frame (a warm start's blur to settle).
    handover
        (iteration, share, residual): after that iteration (and its pruning), where more than that share
        of the voxels it began with are still in the operator while the projections' relative residual
        is below ``residual`` (None: whatever it is), the iterations end there (:data:`HANDED_OVER`;
        :func:`hands_over`); None: never.
    spend
        ``op`` is the caller's to let go (it holds no other reference to it): its first pruning lets
        go of its rows chunk by chunk as the kept ones are copied (:func:`prune_dark`). The operators
        made here (the split, the pruned) are always let go so; ``op`` given without ``spend`` is left whole.

    Returns
    -------
    Iterated
    """
    wp, s = warp(), settings
    device = op.device
    its = s.iterations if iterations is None else int(iterations)
    mu = s.relaxation if relaxation is None else float(relaxation)
    t0 = time.perf_counter() if t0 is None else t0
    n = op.n_voxels
    if n == 0:  # nothing to reconstruct
        e.fill_(0.0)
        return Iterated(e, time.perf_counter() - t0, 0.0, op, 0, NO_VOXELS)
    # Start uniform (or warm), scaled so the projection carries the measured total signal.
    if start is None:
        e.fill_(1.0)
    else:
        if int(start.shape[0]) != n:
            raise ValueError(f"the start has {start.shape[0]} intensities for {n} voxels")
        wp.copy(e, start)
    op.forward(e, out=proj)
    total_proj = _total(proj)
    scale = _total_measured(image) / total_proj if total_proj > 0 else 0.0
    if start is None:
        e.fill_(scale)
    else:
        wp.launch(_mart_kernels().scale_shift, dim=n, inputs=[e, scale, 0.0], device=device)
    own = spend  # whether the pruning may let go of op's rows as it copies the kept ones
    if split is not None and s.subsets > 1 and s.form == "simultaneous":  # OS-SMART: the rows split by subset, once
        cut = split(op)
        if cut is not op:
            if own:  # the split holds every row again: the caller's whole rows go now, not at its return
                _let_go(op)
            own = True  # the split rows are this loop's own
        op = cut
        del cut
    wp.synchronize_device(device)
    t1 = time.perf_counter()
    if started is not None:
        started(t1 - t0)
    floor = max(s.floor * s.threshold_sigma * float(np.mean(noise)), 1e-6)
    transposed = op.transpose() if s.form == "sequential" else None  # stored weights (ReconSettings checks)
    prune = (s.prune if prune is None else float(prune)) if transposed is None else 0.0
    tolerance = s.stop_tolerance if stop_tolerance is None else float(stop_tolerance)
    ordered = is_split(op)
    # with the rule on, ordered subsets prune and measure per pass as often as the plain form per iteration
    per_pass = op.n_subsets if tolerance > 0 and ordered else 1
    prune_every = pass_prune_every(s, per_pass) if per_pass > 1 else s.prune_every
    if warm and tolerance > 0:
        # a warm start: measured (and pruned) every WARM_STOP_EVERY, on the residual alone
        prune_every = WARM_STOP_EVERY
        rule = StoppingRule(tolerance, voxels=math.inf, every=WARM_STOP_EVERY, least=settle)
    else:
        rule = StoppingRule(tolerance, voxels=s.stop_voxels if stop_voxels is None else float(stop_voxels),
                            every=stop_interval(s, prune=prune > 0, subsets=per_pass))
    ran, stopped = its, (CAPPED if rule.on else FIXED)
    for it in range(1, its + 1):
        measure = rule.due(it - 1)  # the stopping rule: on the projection of what it - 1 iterations left
        if (transposed is None and not ordered) or measure:
            op.forward(e, out=proj)  # the simultaneous update's projection serves the rule as well
        if measure and rule.converged(it - 1, relative_residual(image, proj), op.n_voxels):
            ran, stopped = it - 1, CONVERGED
            break
        if transposed is not None:
            op.sweep(transposed, image, e, mu, floor)
        elif ordered:  # one pass through the subsets
            ordered_pass(op, image, e, proj, ratio, floor, mu,
                         groups=groups_in_pass(op.n_subsets, s.subset_halving, it))
        else:
            op.update(log_ratio(image, proj, floor, ratio), e, mu)
        if prune > 0 and it % prune_every == 0 and it < its:  # the dark voxels leave
            kept = prune_dark([op], [e], prune, spend=own)
            own = own or kept[0][0] is not op  # a restricted copy is this loop's own
            (op,), (e,) = kept
            del kept
        if handover is not None and it == handover[0] and it < its and _hands_over(op, e, image, proj, n,
                                                                                     handover):
            ran, stopped = it, HANDED_OVER
            if progress is not None:
                progress(1)
            break
        if progress is not None:
            progress(1)
    if progress is not None and ran < its and stopped != HANDED_OVER:  # handed over: the DRT stage counts the rest
        progress(its - ran)  # the iterations the rule left out, for a bar sized for the most
    wp.synchronize_device(device)
    return Iterated(e, t1 - t0, time.perf_counter() - t1, op, ran, stopped)


def hands_over(active: int, left: int, share: float, *, residual: float | None = None,
               max_residual: float | None = None) -> bool:
    """MLOS-MART's hand-over rule (:attr:`ReconSettings.handover_share`): whether ``left`` of the
    ``active`` voxels a frame began with, still in the operator after ``handover_at`` line-of-sight
    iterations, are more than ``share`` of them while the projections' relative ``residual`` is below
    ``max_residual`` (:attr:`ReconSettings.handover_residual`; None: the share alone): the light is
    explained, by ghosts as much as by particles, which line-of-sight weights do not tell apart, so the
    survivors go on with DRT weights. Where the residual is high the voxels left are noise's (the
    images' noise lights pixels, and their voxels stay), which DRT weights do not remove (Mc2 at 3 times
    its noise: 42% left after 20, residual 0.33, Q 0.833 -> 0.823 handed over). Never where ``share``
    is 0 or nothing was active."""
    if not (share > 0 and active > 0 and left > share * active):
        return False
    return max_residual is None or (residual is not None and residual < max_residual)


def _hands_over(op: Operator, e, image, proj, active: int, handover: tuple[int, float, float | None]) -> bool:
    """:func:`hands_over` for :func:`smart_iterations`: the residual of ``e`` projected (into ``proj``)
    only where the share alone would hand over."""
    _, share, max_residual = handover
    if not hands_over(active, op.n_voxels, share):
        return False
    if max_residual is None:
        return True
    op.forward(e, out=proj)
    return hands_over(active, op.n_voxels, share, residual=relative_residual(image, proj),
                      max_residual=max_residual)


def unexplained_added(op: Operator, start, image, noise: Sequence[float], *, settings: ReconSettings):
    """A warm start with what it leaves unexplained added: the light of the measured ``image`` its
    projection does not account for (particles that entered the box, or that the predictor missed)
    put back along the lines of sight of the voxels whose pixels all saw it.

    MART grows a voxel by the mean log ratio over its pixels, so a particle that is not in the warm
    start, where some of its pixels are lit by carried ones, grows slowly from the start's floor
    (:func:`lfcore.warm.with_floor`) while the carried particles settle. The unexplained signal
    ``u = max(b - s Wx, 0)`` (``s`` the start's scale to the measured total) is turned into a
    multiplicative line-of-sight volume (MLOS: ``exp(sum_i w_iv ln(max(u_i, f) / f)) - 1``, ``f`` the
    update's floor: zero where a voxel's pixels are all explained) scaled to carry ``sum u``, and
    added.

    Parameters
    ----------
    op
        The frame's operator (its first one: line-of-sight weights where the frame runs them).
    start
        (n,) float32 Warp array on the device: the warm start (:meth:`lfcore.warm.WarmStart.start`).
    image
        (n_pixels,) float32 Warp array: the measured signal, in counts (:data:`MASKED` pixels left out).
    noise, settings
        Each camera's noise sigma in counts, and the settings (the update's floor,
        ``settings.floor * settings.threshold_sigma`` times their mean).

    Returns
    -------
    warp.array
        (n,) float32 on the device: the start, unscaled (the iterations scale it to the signal).
    """
    wp = warp()
    n = op.n_voxels
    if n == 0:
        return start
    device = op.device
    proj = wp.zeros(int(image.shape[0]), dtype=float, device=device)
    op.forward(start, out=proj)
    b, p = image.numpy().astype(np.float64), proj.numpy().astype(np.float64)
    ok = b >= 0
    measured, projected = float(b[ok].sum()), float(p.sum())
    if measured <= 0 or projected <= 0:
        return start
    scale = measured / projected
    u = np.where(ok, np.maximum(b - scale * p, 0.0), 0.0)
    total_u = float(u.sum())
    floor = max(settings.floor * settings.threshold_sigma * float(np.mean(noise)), 1e-6)
    if total_u <= 0:
        return start
    ratio = wp.array(np.log(np.maximum(u, floor) / floor).astype(np.float32), dtype=float, device=device)
    e_u = wp.full(n, 1.0, dtype=float, device=device)
    op.update(ratio, e_u, 1.0)
    mlos = np.maximum(e_u.numpy().astype(np.float64) - 1.0, 0.0)
    wp.copy(e_u, wp.array(mlos.astype(np.float32), dtype=float, device="cpu"))
    op.forward(e_u, out=proj)
    lit = float(proj.numpy().astype(np.float64).sum())
    if lit <= 0:
        return start
    out = scale * start.numpy().astype(np.float64) + (total_u / lit) * mlos
    return wp.array(out.astype(np.float32), dtype=float, device=device)


def _mart_kernels():
    from lfcore._kernels import mart as km

    return km


def _total(a) -> float:
    """Sum of a float32 Warp array: NumPy's (pairwise) where it is host memory, a device reduction
    elsewhere (no copy to the host)."""
    if a.device.is_cpu:
        return float(a.numpy().sum())
    return float(warp().utils.array_sum(a))


def _total_measured(a) -> float:
    """Sum of a measured signal (a float32 Warp array), its masked pixels (:data:`MASKED`) left out."""
    if a.device.is_cpu:
        v = a.numpy()
        return float(v.sum() if not (v < 0).any() else np.maximum(v, 0.0).sum())
    from lfcore._kernels import mart as km

    wp = warp()
    out = wp.zeros(1, dtype=wp.float64, device=a.device)
    wp.launch(km.positive_sum, dim=int(a.shape[0]), inputs=[a, out], device=a.device)
    return float(out.numpy()[0])


class FrameReconstructor:
    """Reconstruct frame after frame with one projector and settings, the device buffers kept.

    The stages of a frame are methods of their own, for a caller that has its images on the
    device already and times each stage (the live pipeline): :meth:`eliminate`,
    :meth:`operator`, :meth:`iterate` (the one simultaneous MART loop, batch and live) and
    :meth:`volume`; :meth:`reconstruct` runs them all on host images. The iterations see only the
    frame's :class:`~lfcore.operator.Operator`; where it comes from (a weight cache, the matrix-free
    templates, a per-frame choice) is the operator source's business, chosen by :mod:`lfcore.plan`.

    Parameters
    ----------
    projector
        Cameras and grid on a device (a :class:`~lfcore.operator.Projector`).
    settings
        Method, iterations, relaxation, form, thresholds (see :class:`ReconSettings`).
    cache
        Weights kept across frames, built on ``projector`` (see :func:`reconstruct`).
    budget_bytes
        Device memory the weights and the iterations may take; None: what the device has free
        (counting the buffers this reconstructor holds already as free to it).
    templates
        The matrix-free templates built already for the projector's box (on another of its depth
        slabs: :meth:`lfcore.matrix_free.DrtTemplates.on`), used instead of building them.
    source
        Where the frames' operators come from (:class:`~lfcore.operator.OperatorSource`); None:
        the one :func:`lfcore.plan.operator_source` chooses for the settings, ``cache`` and
        ``templates``.

    Raises
    ------
    MemoryBudgetError
        If the projector's grid has too many voxels to number (:data:`lfcore.operator.INDEX_LIMIT`:
        reconstruct it in depth slabs, :mod:`lfcore.slabs`).

    Notes
    -----
    Buffers on the projector's device, each allocated on first use and kept: the image, its
    projection and the update's log ratios ((n_pixels,) float32 each), the intensities (grown by
    half again when a frame has more active voxels than any before), the (z, y, x) float32 volume
    and its smoothing scratch. One thread at a time may use a reconstructor (and its projector).
    """

    #: Whether :meth:`reconstruct` hands the volume to a writer slab by slab (see
    #: :class:`lfcore.slabs.SlabReconstructor`) rather than returning it.
    in_slabs = False

    def __init__(self, projector: Projector, settings: ReconSettings, *, cache: WeightCache | None = None,
                 budget_bytes: int | None = None, templates: DrtTemplates | None = None,
                 source: OperatorSource | None = None) -> None:
        check_indexable(projector.grid)
        if cache is not None and cache.projector is not projector:
            raise ValueError("the weight cache belongs to another projector")
        self.projector = projector
        self.settings = settings
        self.cache = cache
        self.budget_bytes = budget_bytes
        self.wp = projector.wp
        self.device = projector.device
        self.ops = VolumeOps(projector.grid.shape, device=self.device)
        if source is None:
            from lfcore.plan import operator_source  # the planner chooses (it imports this module)

            source = operator_source(projector, settings, cache=cache, templates=templates)
        self.source = source
        self._image = None  # (n_pixels,) float32: the measured signal of reconstruct()
        self._proj = None  # (n_pixels,) float32: the forward projection
        self._ratio = None  # (n_pixels,) float32: the update's log ratios
        self._e = None  # the intensities, at least as long as the most active voxels so far
        self._volume = None  # (z, y, x) float32
        self._los_source = None  # line-of-sight weights for settings.los_iterations (made on first use)
        self._drt_source = None  # DRT weights after MLOS-MART's hand-over (settings.handover_share; on first use)
        self._subset_of = None  # (n_pixels,) int32: each pixel's subset, for settings.subsets (made on first use)
        self._coarse = None  # the coarse grid's reconstructor, for settings.coarse (made on first use)

    # --- one frame from host images --------------------------------------------------------------
    def reconstruct(self, images: Sequence[np.ndarray], *, progress: Callable[[int], None] | None = None,
                    warm: WarmStart | None = None, predictor: Predictor | str | None = None) -> ReconResult:
        """Reconstruct one volume from one raw image per camera.

        Parameters
        ----------
        images
            One raw (rows, columns) image per camera, in the projector's camera order, in counts.
        progress
            Called with 1 after each iteration.
        warm
            Where the series' intensities are kept: this frame's are kept there for the next one,
            and with a ``predictor`` this frame starts from the kept ones carried along it and runs
            ``settings.warm_iterations`` (:mod:`lfcore.warm`).
        predictor
            The displacement from the kept frame to this one; :data:`lfcore.warm.OWN_PAIR` (``"own"``):
            measured from this frame's own data before its fine iterations (:data:`WARM_OWN_ITERATIONS`
            line-of-sight iterations correlated with the kept frame), so that the frame depends on the
            kept one and its own images alone; None: a uniform start.

        Returns
        -------
        ReconResult
            Its ``volume`` is a host array of its own.

        Raises
        ------
        MemoryBudgetError
            If the weights or the iteration buffers do not fit in the device's memory.
        """
        p, settings = self.projector, self.settings
        signals, lits, backgrounds, noises = preprocess_images(p, images, settings)
        what = f"{settings.method} of a {p.grid.n_voxels:,}-voxel box"
        with out_of_memory_is_budget_error(p.device, what, "use a coarser --pvr or a smaller volume"):
            return self._reconstruct(signals, lits, backgrounds, noises, progress, warm, predictor)

    def _reconstruct(self, signals: list[np.ndarray], lits: list[np.ndarray], backgrounds: list[float],
                     noises: list[float], progress: Callable[[int], None] | None, warm: WarmStart | None = None,
                     predictor: Predictor | str | None = None) -> ReconResult:
        wp, p, settings = self.wp, self.projector, self.settings
        t0 = time.perf_counter()
        warmed = warm is not None and predictor is not None and warm.held and settings.form == "simultaneous"
        own = warmed and isinstance(predictor, str)
        if own and predictor != OWN_PAIR:
            raise ValueError(f"a frame's predictor is a Predictor, '{OWN_PAIR}' or None, got '{predictor}'")
        if self._image is None:
            self._image = wp.empty(p.n_pixels, dtype=float, device=self.device)
        flat = np.concatenate([s.ravel() for s in signals])
        wp.copy(self._image, wp.array(flat, dtype=float, device="cpu", copy=False))
        coarse = None
        cut = None  # the pruning's threshold: settings.prune, or coarse_prune after the coarse grid
        if self.coarse_applies():  # a warm frame's too: the whole grid's elimination costs most in a large box
            voxels, coarse = self.coarse_eliminate(lits, self._image, noises)
            if settings.prune > 0:  # no pruning asked for: none after the coarse grid either
                cut = settings.coarse_prune or None
        else:
            voxels = self.eliminate(lits)  # returns once counted: synced
        t_elim = t0 if settings.method == "mart" else time.perf_counter()
        cheap, predictor_s = None, 0.0
        if own:  # the pair's own predictor: frame A against a few line-of-sight iterations of this frame
            predictor, cheap, predictor_s = self._own_predictor(voxels, coarse, noises, warm)
            warmed = predictor is not None
        # a warm frame runs fewer line-of-sight iterations: its start holds frame A's particles already
        los_its = (min(settings.los_iterations, WARM_LOS_ITERATIONS, settings.warm_count - 1) if warmed
                   else settings.los_iterations)
        los_first = bool(los_its) and int(voxels.shape[0]) > 0
        if cheap is not None and (los_first or settings.method != "drt-mart"):
            op = cheap  # the predictor's line-of-sight operator is this frame's first one
        else:
            op = self.los_operator(voxels) if los_first else self.operator(voxels)
        del cheap
        active, kind = op.n_voxels, op.kind
        nbytes = int(op.nbytes) if los_first else self.operator_bytes(op)
        weights_s = time.perf_counter() - t0 - predictor_s
        its = settings.warm_count if warmed else settings.iterations
        # raised to WARM_POWER (1: as carried; 2 meets the cold Q, not the vectors) only where no line-of-sight
        # iterations come first: their hand-over would leave a dimmed new particle's voxels out
        start = (unexplained_added(op, warm.start(op, predictor, power=1.0 if los_first else WARM_POWER), self._image,
                                   noises, settings=settings) if warmed else coarse)
        del coarse
        iterate_s = 0.0
        if los_first:
            # the cheap weights first; DRT's then for the voxels still bright (a third of them on Mc)
            given = [op]
            del op  # the loop's own: once pruned, the whole line-of-sight operator goes
            first = self.iterate(given.pop(), self._image, noises, progress=progress, iterations=los_its,
                                 stop_tolerance=0.0, start=start, prune=cut, spend=True)
            weights_s += first.start_s
            iterate_s += first.iterate_s
            t = time.perf_counter()
            handover = cut or settings.prune or PRUNE
            if warmed:  # after a few iterations the chance crossings are still bright: a higher cut
                handover = max(handover, WARM_HANDOVER)
            (bright,), (e,) = bright_voxels([first.op], [first.e], handover)
            # a dark voxel may still grow under the sharper weights; the line-of-sight weights go first
            start = with_floor(wp.array(e, dtype=float, device=self.device), WARM_BLEND, copy=False)
            del first, e
            op = self.operator(wp.array(bright, dtype=wp.int32, device=self.device))
            del bright
            weights_s += time.perf_counter() - t
            its = max(1, its - los_its)
        nnz, n_fly, applied, last_kind = op.nnz, op.n_on_the_fly, applied_by(op), op.kind
        op_bytes = self.operator_bytes(op)
        ops = [op]
        del op  # iterate may split it into ordered subsets (settings.subsets): the unsplit rows may then go
        handing = ((settings.handover_at, settings.handover_share, settings.handover_residual)
                   if settings.handover_share and not warmed else None)
        # a warm start without line-of-sight iterations first settles its carried blur before the rule
        settle = WARM_SETTLE if warmed and not los_first else 0
        done = self.iterate(ops.pop(), self._image, noises, progress=progress, iterations=its, start=start, prune=cut,
                            warm=warmed, handover=handing, settle=settle, spend=True)
        del start
        handed = ""
        if done.stopped == HANDED_OVER:
            # MLOS-MART's ghosts leave slowly on this frame: the survivors go on with DRT weights
            first_its, left = done.iterations, done.op.n_voxels
            below = (f" with the residual below {settings.handover_residual:g}" if settings.handover_residual
                     else "")
            handed = (f"{left:,} of {active:,} voxels ({left / active:.0%}) left after {first_its} line-of-sight "
                      f"iterations, above {settings.handover_share:.0%}{below}: DRT weights for those still bright")
            weights_s += done.start_s
            iterate_s += done.iterate_s
            t = time.perf_counter()
            (bright,), (e,) = bright_voxels([done.op], [done.e], cut or settings.prune or PRUNE)
            start = with_floor(wp.array(e, dtype=float, device=self.device), WARM_BLEND, copy=False)
            del done, e
            op = self.drt_operator(wp.array(bright, dtype=wp.int32, device=self.device))
            del bright
            weights_s += time.perf_counter() - t
            nnz, n_fly, applied, last_kind = op.nnz, op.n_on_the_fly, applied_by(op), op.kind
            op_bytes = max(op_bytes, self.operator_bytes(op))
            given = [op]
            del op
            done = self.iterate(given.pop(), self._image, noises, progress=progress, iterations=max(1, its - first_its),
                                start=start, prune=cut, relaxation=HANDOVER_RELAXATION,
                                stop_voxels=min(settings.stop_voxels, HANDOVER_STOP_VOXELS), spend=True)
            del start
            done = done._replace(iterations=done.iterations + first_its)
        if warm is not None:
            warm.keep(done.op, done.e)
        vol = self.volume(done.op, done.e)
        volume = vol.numpy()  # a copy from a GPU, a view of the buffer on the CPU
        if self.device == "cpu":
            volume = volume.copy()
        return ReconResult(volume=volume, active_voxels=active, active_fraction=active / p.grid.n_voxels,
                           nnz=nnz, weight_bytes=max(nbytes, op_bytes),
                           weights_s=weights_s + done.start_s, iterate_s=iterate_s + done.iterate_s,
                           iterations=done.iterations + (los_its if los_first else 0),
                           stopped=done.stopped, background=backgrounds,
                           noise=noises, eliminate_s=t_elim - t0, on_the_fly_voxels=n_fly,
                           projector=applied,
                           operator=f"{kind}, then {last_kind}" if los_first or handed else kind,
                           final_voxels=done.op.n_voxels, warm=warmed, handover=handed,
                           predictor_s=predictor_s)

    def _own_predictor(self, voxels, coarse, noise: Sequence[float], warm: WarmStart
                       ) -> tuple[Predictor | None, Operator, float]:
        """A frame B's predictor from its own pair (:data:`lfcore.warm.OWN_PAIR`): :data:`WARM_OWN_ITERATIONS`
        line-of-sight iterations of ``voxels`` (from ``coarse``, the coarse grid's start, or uniform;
        no pruning, no stopping rule), their volume correlated with the kept frame A's
        (:func:`lfcore.warm.predictor_field`).

        Returns
        -------
        predictor
            None where the box is too thin to correlate, or no voxel is active (the frame then starts
            uniform).
        operator
            The line-of-sight operator of ``voxels`` (DRT-MART's first one, where it runs such
            iterations first; the other methods' only one).
        seconds
            The wall seconds taken.
        """
        t = time.perf_counter()
        settings = self.settings
        # DRT-MART's line-of-sight weights, or the other methods' own operator (line-of-sight ones)
        op = self.los_operator(voxels) if settings.method == "drt-mart" else self.operator(voxels)
        if op.n_voxels == 0:
            return None, op, time.perf_counter() - t
        first = self.iterate(op, self._image, noise, iterations=WARM_OWN_ITERATIONS, stop_tolerance=0.0,
                             start=coarse, prune=0.0)
        cheap = self.volume(first.op, first.e)
        del first
        predictor = predictor_field(warm.kept, cheap, device=self.device)
        return predictor, op, time.perf_counter() - t

    # --- the stages ------------------------------------------------------------------------------
    def eliminate(self, lit) -> object:
        """The voxels to reconstruct: the survivors of zero-voxel elimination, or every voxel of
        the box for the MART baseline.

        Parameters
        ----------
        lit
            The lit pixels, as :meth:`lfcore.operator.Projector.eliminate` takes them: one boolean
            (rows, columns) image per camera, or one (n_pixels,) uint8 Warp array on the device.

        Returns
        -------
        warp.array
            (n,) int32 flat voxel indices, ascending.
        """
        s = self.settings
        if s.method == "mart":
            return self.projector.all_voxels()
        return self.projector.eliminate(lit, min_seen=s.min_seen, max_dark=s.max_dark)

    def coarse_applies(self) -> bool:
        """Whether this reconstructor's frames run coarse-to-fine elimination (:attr:`ReconSettings.coarse`):
        DRT-MART's simultaneous form or MLOS-MART on light-field cameras alone (a projector whose elimination
        takes ``within``), in a box of at least :data:`lfcore.coarse.COARSE_MIN_VOXELS` voxels."""
        return coarse_applies(self.projector, self.settings)

    def coarse_eliminate(self, lit, image, noise: Sequence[float]) -> tuple[object, object]:
        """Coarse-to-fine elimination (:mod:`lfcore.coarse`): the fine voxels to reconstruct and their start.

        Parameters
        ----------
        lit
            As :meth:`eliminate` takes it.
        image
            (n_pixels,) float32 Warp array on the device: the measured signal (:meth:`iterate`).
        noise
            Each camera's noise sigma, in counts.

        Returns
        -------
        voxels
            (n,) int32 Warp array of flat fine voxel indices, ascending: those the fine elimination keeps
            of the ones inside the coarse voxels still bright after ``settings.coarse_iterations``.
        start
            (n,) float32 Warp array: each voxel's coarse voxel's intensity, plus a share of their mean
            (:func:`lfcore.warm.with_floor`) so that a voxel its coarse one left dim may still grow;
            None where no coarse voxel is left.
        """
        wp, p, s = self.wp, self.projector, self.settings
        f = s.coarse
        if self._coarse is None:
            self._coarse = coarse_reconstructor(p, s, budget_bytes=self.budget_bytes)
        bright = coarse_bright(self._coarse, lit, image, noise, factor=f)
        if bright.voxels.size == 0:
            return wp.zeros(0, dtype=wp.int32, device=self.device), None
        within = wp.array(coarse_grids.children(bright.voxels, p.grid, f), dtype=wp.int32, device=self.device)
        voxels = p.eliminate(lit, min_seen=s.min_seen, max_dark=s.max_dark, within=within)
        if int(voxels.shape[0]) == 0:
            return voxels, None
        start = wp.array(bright.inherited(voxels.numpy(), p.grid), dtype=float, device=self.device)
        return voxels, with_floor(start, WARM_BLEND, copy=False)

    def los_operator(self, voxels) -> Operator:
        """The line-of-sight weights of ``voxels`` ((n,) int32 on the device; MLOS-MART's) for DRT-MART's
        first ``settings.los_iterations``, within the memory budget."""
        if self._los_source is None:
            from lfcore.plan import operator_source

            los = replace(self.settings, method="mlos-mart", projector="stored", los_iterations=0, warm_start=False,
                          coarse=1)
            self._los_source = operator_source(self.projector, los)
        n = int(voxels.shape[0])
        return self._los_source.operator(voxels, budget=lambda: self._weight_budget(n))

    def drt_operator(self, voxels) -> Operator:
        """DRT-MART's operator of ``voxels`` ((n,) int32 on the device) for the iterations after
        MLOS-MART's hand-over (:attr:`ReconSettings.handover_share`), within the memory budget: traced
        weights or the templates, as ``projector`` ``"auto"`` chooses for DRT-MART."""
        if self._drt_source is None:
            from lfcore.plan import operator_source

            drt = replace(self.settings, method="drt-mart", relaxation=HANDOVER_RELAXATION, handover_share=0.0,
                          warm_start=False, coarse=1)
            self._drt_source = operator_source(self.projector, drt)
        n = int(voxels.shape[0])
        return self._drt_source.operator(voxels, budget=lambda: self._weight_budget(n))

    def operator(self, voxels) -> Operator:
        """The operator of ``voxels`` ((n,) int32 on the device), from this reconstructor's operator
        source within the memory budget (:meth:`_weight_budget`): from the cache where it has them
        and they fit, else built (line-of-sight ones partly on the fly where
        ``settings.weight_storage`` allows), or the templates (their images, or applied).

        Raises
        ------
        MemoryBudgetError
            If the operator does not fit.
        """
        n = int(voxels.shape[0])
        return self.source.operator(voxels, budget=lambda: self._weight_budget(n))

    @deprecated("FrameReconstructor.operator(voxels)", since="0.1.0")
    def weights(self, voxels) -> Operator:
        """Deprecated: :meth:`operator` (its name until the operator protocol)."""
        return self.operator(voxels)

    def prepare(self) -> None:
        """Build now what the first frame's operator would build in its own time (the matrix-free
        templates, where the operator source uses them alone): the live path calls it as it starts.

        Raises
        ------
        MemoryBudgetError, lfcore.operator.MatrixFreeUnsupported
            No room for the templates, or cameras without them.
        """
        self.source.prepare(budget=lambda: self._weight_budget(0))

    @property
    def templates(self) -> DrtTemplates | None:
        """The matrix-free templates held for the next frames (None until built, or let go)."""
        return self.source.templates

    @property
    def _templates(self) -> DrtTemplates | None:  # the name the tests and older scripts read
        return self.source.templates

    def templates_pay(self, voxels, *, host: np.ndarray | None = None) -> bool:
        """Whether ``projector = "auto"`` takes the templates' images for ``voxels`` (see
        :meth:`lfcore.plan.AutoSource.templates_pay`); False for a source that never chooses them."""
        pays = getattr(self.source, "templates_pay", None)
        return bool(pays is not None and pays(voxels, host=host))

    def operator_bytes(self, op: Operator) -> int:
        """Device bytes of ``op`` with what is kept for the next frames beside it: the templates its
        images were made from, or the weight cache's pool where ray-traced weights come from it (a
        second copy of each row)."""
        return int(op.nbytes) + int(self.source.held_bytes(op))

    def iterate(self, op: Operator, image, noise: Sequence[float], *, iterations: int | None = None,
                relaxation: float | None = None, progress: Callable[[int], None] | None = None,
                start=None, stop_tolerance: float | None = None, prune: float | None = None,
                warm: bool = False, handover: tuple[int, float, float | None] | None = None,
                settle: int = 0, stop_voxels: float | None = None, spend: bool = False) -> Iterated:
        """MART on ``weights``: a uniform start (or ``start``), then the iterations of ``settings.form``.

        The start is uniform (or ``start``), scaled so that its projection carries the measured total
        signal.
        The simultaneous form (SMART) then alternates a forward projection and the update of
        every voxel; the sequential form sweeps eq. 4.1 pixel by pixel. In the update a pixel's
        measurement counts as at least the floor, ``settings.floor`` times the lit threshold
        (``settings.threshold_sigma`` times the mean noise sigma).

        Parameters
        ----------
        op
            The voxels and their operator (:meth:`operator`).
        image
            (n_pixels,) float32 Warp array on the device: the background-subtracted signal of
            every camera (zero on unlit pixels), in counts.
        noise
            Each camera's noise sigma, in counts.
        iterations, relaxation
            Override ``settings.iterations`` and ``settings.relaxation`` (the live path changes
            them while it runs). With the stopping rule, ``iterations`` is the most that run.
        progress
            Called with 1 after each iteration (and with the iterations left out when the stopping
            rule ends the frame early).
        start
            (n,) float32 Warp array on the device: the voxels' relative start intensities (a warm
            start, :meth:`lfcore.warm.WarmStart.start`), all positive; None: uniform.
        stop_tolerance
            Overrides ``settings.stop_tolerance`` (:class:`StoppingRule`; 0: exactly ``iterations``).
        stop_voxels
            Overrides ``settings.stop_voxels`` (the rule's share of the voxels leaving; the DRT weights
            after MLOS-MART's hand-over take at most :data:`HANDOVER_STOP_VOXELS`).
        prune
            Overrides ``settings.prune`` (the threshold after coarse-to-fine elimination,
            ``settings.coarse_prune``); None: ``settings.prune``.
        warm
            Whether ``start`` is a warm start (:mod:`lfcore.warm`): the stopping rule then measures
            every :data:`WARM_STOP_EVERY` iterations, on the residual alone.
        settle
            Iterations that run before the stopping rule may stop the frame.
        handover
            (iteration, share, residual) of :func:`smart_iterations`: end there (:data:`HANDED_OVER`)
            where more than that share of the voxels are left and the residual is below that; None: never.
        spend
            ``op`` is handed over (the caller keeps no reference to it): once split into ordered subsets
            or pruned its rows go, and its first pruning lets them go chunk by chunk as the kept ones are
            copied (:func:`smart_iterations`), so that the whole operator and its copy do not stand
            together. Without it ``op`` is left whole, to be iterated again.

        Returns
        -------
        Iterated
            The intensities (in this reconstructor's buffer), the seconds taken, the iterations
            that ran and why they stopped.
        """
        wp, p, s = self.wp, self.projector, self.settings
        t0 = time.perf_counter()
        n = op.n_voxels
        if self._e is None or self._e.shape[0] < n:
            self._e = wp.empty(int(1.5 * n) + 1, dtype=float, device=self.device)
        if self._proj is None:
            self._proj = wp.zeros(p.n_pixels, dtype=float, device=self.device)
        if s.form == "simultaneous" and self._ratio is None:
            self._ratio = wp.empty(p.n_pixels, dtype=float, device=self.device)
        given = [op]
        del op  # handed over (spend): the loop's own from here, not held by this frame while it runs
        return smart_iterations(given.pop(), self._e[: max(n, 1)], image, self._proj, self._ratio, noise, s,
                                iterations=iterations, relaxation=relaxation, progress=progress, start=start,
                                stop_tolerance=stop_tolerance, split=self._ordered_subsets, t0=t0, prune=prune,
                                warm=warm, handover=handover, settle=settle, stop_voxels=stop_voxels, spend=spend)

    def _ordered_subsets(self, op: Operator) -> Operator:
        """``op`` split by ``settings.subsets`` pixel subsets (:func:`lfcore.subsets.split`), or
        ``op`` itself where it is not stored weights held whole, or where the split rows do not fit
        beside it in the memory budget (the plain form then runs)."""
        if split_bytes(op, self.settings.subsets) + int(op.nbytes) > self._weight_budget(op.n_voxels):
            return op
        if self._subset_of is None:
            p = self.projector
            host = pixel_subsets(p.pixel_offsets, p.cameras, self.settings.subsets)
            self._subset_of = self.wp.array(host, dtype=self.wp.int32, device=self.device)
        return split(op, self._subset_of, self.settings.subsets) or op

    def volume(self, op: Operator, e, *, out=None) -> object:
        """The dense (z, y, x) volume of intensities ``e`` of the weights' voxels, smoothed by
        ``settings.smooth`` voxels, on the device.

        Parameters
        ----------
        op, e
            The voxels' operator and their intensities (:meth:`iterate`).
        out
            (nz, ny, nx) float32 Warp array to write; None: this reconstructor's volume buffer
            (overwritten by its next frame).

        Returns
        -------
        warp.array
            The (nz, ny, nx) float32 volume.
        """
        if out is None:
            if self._volume is None:
                self._volume = self.ops.empty()
            out = self._volume
        vol = op.scatter(e, out=out)
        if self.settings.smooth > 0:  # on the device: a host filter would dominate a large GPU volume
            self.ops.smooth(vol, self.settings.smooth)
        return vol

    # --- memory ----------------------------------------------------------------------------------
    def _held_bytes(self, n_active: int) -> int:
        """Of what :meth:`_weight_budget` sets aside for the iterations, the bytes held already."""
        p = self.projector
        held = sum(4 * p.n_pixels for b in (self._image, self._proj, self._ratio) if b is not None)
        held += 0 if self._e is None else 4 * min(n_active, int(self._e.shape[0]))
        held += 0 if self._volume is None else 8 * p.grid.n_voxels  # with the smoothing's scratch
        return held

    def _weight_budget(self, n_active: int) -> int:
        """Bytes the weights of ``n_active`` voxels may take: the budget less what the iterations
        and the result need beside them (per pixel the image, its projection and log ratio; per
        active voxel its intensity; the dense volume and its smoothing). Without a budget, the
        device's free memory and the buffers held for those."""
        p = self.projector
        if self.budget_bytes is None:
            free = available_bytes(p.device) + self._held_bytes(n_active)
        else:
            free = int(self.budget_bytes)
        return free - 12 * p.n_pixels - 4 * n_active - 8 * p.grid.n_voxels


# the per-frame choice's costs, the planner's since the operator protocol (lfcore.plan; imported on first use)
__getattr__ = moved_names(__name__, {name: (lambda name=name: getattr(importlib.import_module("lfcore.plan"), name))
                                     for name in ("TEMPLATE_TRACES", "IMAGE_SHARE")}, since="0.1.0")
