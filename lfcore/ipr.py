"""Iterative particle reconstruction (IPR): particles, not voxels, fitted to the cameras' images.

Where DRT-MART reconstructs the intensity of every voxel that may hold light, IPR (Wieneke 2013,
the reconstruction step of Shake-the-Box) reconstructs a list of particles, each a position
(x, y, z) and an intensity, whose images together explain the recorded ones. The work then follows
the particles, not the voxels, and a position comes sub-voxel without the window averaging of
cross-correlation. This module does it on the rig's own forward model:

1. **Candidates**: a quick reconstruction (:class:`lfcore.reconstruct.FrameReconstructor` with the
   settings of the named protocol :attr:`IprSettings.candidate_protocol`, ``lfpiv reconstruct``'s
   ``fast`` by default, and at most :attr:`IprSettings.candidate_iterations` iterations) and its
   sub-voxel peaks (:func:`lfcore.metrics.detect_particles`).
2. **Fit** ("shake"): every particle's position and intensity fitted to the images at once by
   damped Gauss-Newton (Levenberg-Marquardt) steps, each position step at most
   :attr:`IprSettings.max_step_voxels` per axis, a step kept only where it lowers the residual.
3. **Split** the particles about twice as bright as the median in two (two overlapping particles
   the quick reconstruction showed as one peak) and fit again.
4. **Prune**: particles too faint (below :attr:`IprSettings.min_intensity` of the median: the
   frame's, or, along a laser sheet that lights the box unevenly, the median of the particles
   nearest in the sheet's normal, :attr:`IprSettings.intensity_axis`), too
   close to a brighter one (within :attr:`IprSettings.merge_voxels`: merged, intensities added,
   the position intensity-weighted) or outside the box (by more than
   :attr:`IprSettings.box_margin_voxels` with the point model) leave; the rest are fitted again.
5. **Residual rounds**: the images' residual (recorded minus the particles' model) is
   reconstructed again and its peaks, where no particle is near, join the list; fit and prune
   again (:attr:`IprSettings.rounds` in all). A round whose candidates are few
   (:attr:`IprSettings.local_refit_share` of the particles) fits only them and the particles whose
   images share pixels with theirs, the others held.
6. Optionally, the particles whose fitted position is unsure (:attr:`IprSettings.max_position_std`)
   are left out.

The forward model of a particle
-------------------------------
By default (:attr:`IprSettings.model` ``"point"``) a particle is a point, and its image is computed
at its own sub-voxel position, each camera its own way: a light-field camera's dense ray tracing
(:func:`lfcore._kernels.weights.drt_points`: the DRT weights' arithmetic, traced from the point
instead of a voxel centre, through twice as many sub-apertures, with the main lens' diffraction
blur on the MLA that the renderer applies), a pinhole camera's Gaussian spot of
:attr:`IprSettings.particle_image_px` where the point projects, distortion included. Against a
rendered point on the tiny rig its error is 0.03 of the image's RMS off focus and 0.06 near it,
where the voxels' blend below was 0.21 and 0.56. The Jacobian is by forward differences of 0.05
voxel. A light-field camera's image of a particle changes slowly with depth, so after each round's
fit every particle is also tried a few whole voxels away (:attr:`IprSettings.relocate_depth`) and
moved where it explains more of the images.

``"voxels"``, the first model: a particle at a sub-voxel point is modelled as the trilinear blend
of its 8 neighbouring voxels' images: the voxels' rows of the reconstruction's own operator
(ray-traced DRT weights for light-field cameras, line-of-sight weights for pinhole ones, both
jointly for a mixed rig), built with :meth:`lfcore.operator.Projector.operator` on the voxels
around the particles only. A voxel's row is the image of a voxel-sized box of light at its centre,
and between voxel centres the blend moves the image's centroid linearly with the position (the
centroid of the blend is the blend of the centroids), which is what locates a particle sub-voxel;
the image's shape is approximated. The model is linear in the intensities and piecewise linear in
the positions, so its Jacobian is exact within a voxel cell.

Positions are world mm (x, y, z); internally voxel index coordinates (z, y, x) of the grid, voxel
centres at whole numbers.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import partial

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import cg, splu
from scipy.spatial import cKDTree

from lfcore.metrics import detect_particles
from lfcore.operator import Projector
from lfcore.reconstruct import (
    PROTOCOLS,
    WEIGHTS,
    FrameReconstructor,
    ReconSettings,
    estimate_background,
    protocol_settings,
)
from lfcore.volume import VolumeGrid

__all__ = ["CANDIDATE_SOURCES", "CANDIDATE_WEIGHTS", "LOCAL_MEDIAN_PARTICLES", "MODELS", "PARTICLE_FIELDS",
           "IprSettings", "ParticleReconstructor", "ParticleResult", "local_median", "to_index", "to_mm"]

#: The columns of a frame's particles as :class:`ParticleResult` and the run store's ``particles/``
#: keep them.
PARTICLE_FIELDS = ("x_mm", "y_mm", "z_mm", "intensity", "residual")

#: Where IPR's candidates come from (:attr:`IprSettings.candidate_source`): the peaks of a quick
#: reconstruction, or ray bundling (:mod:`lfcore.raybundle`).
CANDIDATE_SOURCES = ("reconstruction", "rays")

#: The weights of the candidates' quick reconstruction (:attr:`IprSettings.candidate_weights`): its
#: protocol's own (``"protocol"``: ``fast`` traces DRT weights for the voxels still bright after its
#: line-of-sight iterations) or line-of-sight weights throughout (``"line-of-sight"``: MLOS-MART on the
#: protocol's grids, no DRT weight traced).
CANDIDATE_WEIGHTS = ("protocol", "line-of-sight")

#: The particle models of :attr:`IprSettings.model`.
MODELS = ("point", "voxels")

#: How much more of the residual a particle's new position must explain than its old one for
#: :func:`_relocate` to move it (a fraction of what the old one explains).
RELOCATE_MARGIN = 0.02

#: How many sets of positions' images the point model keeps (:meth:`_PointModel.unit_images`): the fit's
#: current positions and its trial step's, whose images it asks for again (on the 512 x 512 Mc crop a
#: third of the fit's tracings were such repeats).
MEMO_IMAGES = 2

#: The most points :func:`_relocate` traces at once (its moves of every particle, a batch of moves a launch):
#: on issue 48's 512 x 512 rig a point's tracing takes up to 4,000 entries, about 80 kB of working memory.
RELOCATE_POINTS = 4096

#: How many of a particle's moves :func:`_relocate`'s screen (:attr:`IprSettings.relocate_screen`) passes
#: to the full tracing: its best by the coarse tracing's gain.
RELOCATE_KEEP = 3

#: A particle's moves pass :func:`_relocate`'s screen only where the best of them explains at least this
#: share of what its position explains in the coarse tracing (below it no move can win by the full
#: tracing's :data:`RELOCATE_MARGIN`, unless the coarse tracing misjudged it by more than a tenth).
RELOCATE_SCREEN_SLACK = 0.9

#: The points :func:`_canonical_columns` orders at once (a part whose entries stay in the cache: on the tiny
#: rig 128 points' took 0.8 of the time of 4,000 points' at once).
CANONICAL_POINTS = 128

#: How far either side along x the two halves of a split particle start, voxels
#: (:attr:`IprSettings.split_intensity`).
SPLIT_VOXELS = 0.75

#: How far outside the box a particle of the point model is kept and fitted, voxels (each face):
#: a particle just outside the box still lights the cameras (in frame B, those the flow carried
#: out of it), and left out, its light pulls the particles whose images overlap its own, bright
#: and off, to explain it (``benchmarks/RESULTS.md``, fifteenth session, issue 48). The voxels'
#: model (:attr:`IprSettings.model` ``"voxels"``) has no image outside the box: none there.
BOX_MARGIN_VOXELS = 2.0

#: A residual round whose new candidates are at most this share of the particles found so far refits
#: only them and the particles whose images share pixels with theirs, the others held
#: (:attr:`IprSettings.local_refit_share`): on L's optics crop a third round's 12 candidates among 870
#: particles took 18 CPU s so against 89 refitting every one, with the same quality
#: (``benchmarks/RESULTS.md``, sixteenth session).
LOCAL_REFIT_SHARE = 0.02

#: The noise models of the fit (:attr:`IprSettings.noise_model`).
NOISE_MODELS = ("shot", "flat")

#: The fewest particles whose median judges a particle's intensity along
#: :attr:`IprSettings.intensity_axis` (:func:`local_median`).
LOCAL_MEDIAN_PARTICLES = 25

# the 8 corners of a voxel cell, (z, y, x) offsets
_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=np.int64)


@dataclass(frozen=True)
class IprSettings:
    """How particles are reconstructed (:class:`ParticleReconstructor`).

    Attributes
    ----------
    method
        The reconstruction whose operator models the particles and gives the candidates
        (:data:`lfcore.reconstruct.METHODS`); None: DRT-MART for light-field cameras, MLOS-SMART
        for pinhole ones (:func:`lfcore.plan.default_method`).
    candidate_iterations
        Iterations of the quick reconstruction whose peaks are the candidates (with a protocol that
        stops by the rule, ``fast``, the most it runs).
    candidate_protocol
        The quick reconstruction's protocol (:data:`lfcore.reconstruct.PROTOCOLS`, as ``lfpiv
        reconstruct --protocol`` takes it, resolved for the projector's cameras by
        :func:`lfcore.reconstruct.protocol_settings`), with :attr:`candidate_iterations` iterations
        at most and no warm start. ``"fast"``: on light-field cameras, DRT-MART's first iterations on
        line-of-sight weights, DRT weights only for the voxels still bright, ordered subsets, the
        stopping rule, and in boxes of a million voxels or more coarse-to-fine elimination: on the
        512 x 512 Mc crop 20 CPU s a reconstruction against ``"fixed"``'s 88, and on the tiny rig
        focused beyond its box better candidates (recall 0.84 against 0.74, ghosts 9% against 15%)
        and particles (``benchmarks/RESULTS.md``). ``"fixed"``: plain DRT-MART on DRT weights from
        the start (the candidates before this setting existed).
    candidate_threshold
        Peaks below this fraction of the brightest voxel are no candidates.
    candidate_source
        Where the candidates come from (:data:`CANDIDATE_SOURCES`): ``"reconstruction"``, the peaks of
        the quick reconstruction above (its cost grows with the box's voxels), or ``"rays"``, ray
        bundling (:func:`lfcore.raybundle.ray_candidates`: the bright pixels' rays voted into bins a
        lenslet wide, the most voted bins' voxels checked against each lenslet's own pixel; its cost
        grows with the bright pixels and the bins, not the voxels). The fit, the prunings and the
        residual rounds are the same. ``benchmarks/RESULTS.md`` (issue 48, eighth session) has both
        measured.
    candidate_weights
        The quick reconstruction's weights (:data:`CANDIDATE_WEIGHTS`): ``"protocol"``, those of
        :attr:`candidate_protocol` as resolved for the cameras, or ``"line-of-sight"``, MLOS-MART's
        line-of-sight weights for every iteration (the protocol's coarse-to-fine elimination, subsets,
        relaxation and stopping rule kept; no line-of-sight first iterations and no hand-over to DRT
        weights, which are DRT's): no DRT weight is traced, the
        costliest stage of ``fast``'s plan on large boxes. The fit, the relocation and the residual
        rounds refine and complete the candidates. Other methods (pinhole cameras' MLOS-SMART, MART)
        have line-of-sight weights already: unchanged.
    candidate_smoothing
        The quick reconstruction's volume smoothed by a Gaussian of this sigma (voxels along the grid's y
        and x; along z a third of it) before its peaks are found; 0 (the default): none. Line-of-sight
        weights sample a voxel's light at the lenslets' centres: on L's deep box (``benchmarks/particles.py
        --case Lc``) their volume was speckled, 7,542 peaks for 878 particles (recall 0.32 within a
        voxel, 96% ghosts), and smoothed by 3 it gave 905 (0.70, 33%; DRT weights' own 1,114: 0.68,
        47%); on the tiny rig's 1.6 mm box their peaks need none, and 2 lost a fifth of the candidates' recall
        (``benchmarks/RESULTS.md``, seventeenth session).
    ray_keep_bins
        Ray bundling's share of the vote's bins (the most voted first) whose points are checked
        against the lenslets' pixels (``keep_bins`` of :func:`lfcore.raybundle.ray_candidates`): 1
        checks every bin a ray reaches.
    ray_min_score
        Ray bundling's least check of a candidate, as a share of the 99th percentile of the checks'
        local maxima (``min_score`` of :func:`lfcore.raybundle.ray_candidates`).
    shakes
        Fit iterations (damped Gauss-Newton steps of every position and intensity) per fit.
    max_step_voxels
        The largest position step of one fit iteration, voxels per axis.
    min_intensity
        Particles fainter than this fraction of the median intensity are pruned (ghosts are faint):
        the frame's median, or that of the particles nearest along :attr:`intensity_axis`.
    intensity_axis
        ``"x"``, ``"y"`` or ``"z"``: each particle's intensity is judged against the median of the
        :attr:`intensity_share` of the particles nearest it along this axis (a running median of
        the particles' own intensities: the light where it is), not the frame's median. A laser
        sheet's normal (``[laser] sheet_axis``), where the sheet lights the box unevenly: a Gaussian
        sheet dims the particles towards its faces, and against the frame's median the dim real
        ones are pruned as ghosts (issue 48's 512 x 512 rig: a 16 mm sheet over a 12 mm box lights
        its faces at 0.32 of its peak; ``benchmarks/RESULTS.md``, tenth session). The running
        median needs no profile: it follows the light the particles show, whatever the sheet.
        None: the frame's median.
    intensity_share
        The share of the frame's particles (at least :data:`LOCAL_MEDIAN_PARTICLES`) whose median
        judges each particle along :attr:`intensity_axis`.
    merge_voxels
        Particles closer than this, voxels (each axis in its own voxels), are merged.
    rounds
        Passes of candidates, fit and prune; after the first, candidates come from the residual.
    split_intensity
        After the first fit, particles brighter than this many times the median are split in two
        of half the intensity, :data:`SPLIT_VOXELS` either side along x, and fitted again (0: never).
        Two particles whose images overlap so closely that the quick reconstruction shows one peak
        come back as one particle of about twice the light; split, the fit separates them, and
        where they were one particle after all they fall together and are merged again. On one
        frame of the tiny rig at 0.5 PPM it raises recall from 0.75 to 0.83 and lowers the ghosts
        from 17.6% to 15.3% (``benchmarks/RESULTS.md``).
    model
        How a particle's image is modelled (:data:`MODELS`): ``"point"``, the image of a point at the
        particle's own position (a light-field camera's DRT weights traced from it, a pinhole camera's
        Gaussian spot of :attr:`particle_image_px`), or ``"voxels"``, the trilinear blend of its 8
        neighbouring voxels' operator rows (the first model; see the module docstring).
    point_sub_apertures
        Sub-apertures per aperture diameter of the point model's tracing; 0: twice each camera's
        pixels per lenslet.
    particle_image_px
        The point model's particle image in a pinhole camera: a Gaussian spot of this 1/e^2
        diameter, pixels (as the rig's ``[render] particle_image_px`` draws synthetic ones).
    relocate_depth
        After each round's fit, every particle is tried at whole-voxel moves up to this many voxels
        either side along each camera's depth and one voxel either side laterally, the others held, and moved where
        its image explains more of the residual, then fitted again (the point model only; 0:
        never). The fit only finds the nearest minimum; on one frame of the tiny rig at 0.5 PPM
        these moves lower the images' residual by a third.
    relocate_screen
        With the point model, :attr:`relocate_depth`'s moves are first traced at this share of its
        sub-apertures per aperture diameter (its square of the rays; at least one); only each
        particle's :data:`RELOCATE_KEEP` best moves by that coarse tracing (and only where the best
        explains at least :data:`RELOCATE_SCREEN_SLACK` of what the particle's position explains
        there) are traced in full and decide the move, as without the screen. 0: no screen,
        every move traced in full.
    jacobian_reuse
        With the point model, a fit's Jacobian keeps a particle's position columns (its image's
        derivatives per unit intensity, times its current intensity) from the last shake that traced
        them while the particle has moved by at most this many voxels along every axis since; only
        the particles that moved more are traced again (an inexact Gauss-Newton; a fit's first shake
        traces every particle). 0: every particle traced every shake.
    max_position_std
        At the end, particles whose fitted position is less sure than this on any axis (its
        standard deviation from its own image's Jacobian and the residual's noise, voxels) are
        left out; 0: none. Near a light-field camera's focal plane a particle's image hardly
        changes as it moves, and most particles found there are a voxel or more off: on one frame
        of the tiny rig at 0.5 PPM, 79% of the ghosts and 6% of the particles found right lie
        within 3 voxels of it (``benchmarks/RESULTS.md`` has the trade of recall for ghosts).
    wavelength_nm
        The laser's wavelength, for the point model's diffraction blur in light-field cameras
        (0: none). ``lfpiv particles`` and ``lfpiv.particles`` take it, and ``particle_image_px``,
        from the run's rig.
    noise_model
        How the fit weighs the pixels (:data:`NOISE_MODELS`): ``"shot"``, each pixel by the inverse
        of its noise variance, ``sigma0^2 + k m`` of the background's noise ``sigma0`` (each camera's,
        from its image) and the particles' model image ``m`` there, ``k`` (counts of variance per
        count of signal: shot noise, the renderer's rays) fitted to the residual of each camera after
        every fit (:func:`noise_weights`); ``"flat"`` (the default), every pixel alike (plain least
        squares, the fit before this setting existed). A pixel on a bright in-focus particle is many
        times noisier than one on a far-out-of-focus particle's thinly spread light; weighed alike,
        the bright pixels' noise moves the dim particles that share them. On issue 48's 512 x 512
        rig, fitted from the true positions, the near quarter's (9-13 mm out of focus) RMS error
        falls from 0.21, 0.20, 0.85 to 0.17, 0.17, 0.70 voxel and the far quarter's depth error from
        0.34 to 0.16, and IPR's A1 pair from recall 0.878 and 7.6% ghosts to 0.893 and 5.5%; on the
        tiny rig focused beyond its box it lost recall (0.919 to 0.892), on the demo's two-camera
        ring more (0.905 to 0.772): not the default
        (``benchmarks/RESULTS.md``, eleventh session).
    noise_floor
        With ``noise_model`` ``"shot"``: no pixel weighed less than this share of its camera's
        background (its variance taken as at most ``sigma0^2 / noise_floor``); 0 (the default): no
        floor, 1: every pixel alike. Where the images differ from the model by more on bright
        pixels than their noise allows (synthetic images of a few thousand rays a particle), the
        unfloored weights take a bright particle's core down hundreds of times and the fit leans
        on its wings (``benchmarks/RESULTS.md``, eleventh session, issue 48).
    residual_mask
        In the residual rounds, the pixels where the particles found so far are brighter than this
        many times their camera's background noise are masked (NaN) in the residual images whose
        quick reconstruction gives the round's candidates; 0 (the default): none. There the
        residual is the bright particles' noise and the model's error, often below the background
        (a fitted particle's image taken off noisy pixels), and the quick reconstruction's
        elimination takes every voxel whose rays meet a dark pixel away: a faint particle spread
        far out of focus over a bright one's pixels loses its voxels there, and no candidate comes.
        A masked pixel neither removes voxels nor pulls them dark (:func:`lfcore.reconstruct.preprocess`),
        and a background estimated from the residual image, which those pixels' noise widens, is
        not. ``benchmarks/RESULTS.md`` (twelfth session, issue 48) has it measured.
    box_margin_voxels
        With the point model, particles up to this far outside the box (voxels, on each face) are
        kept and fitted (:data:`BOX_MARGIN_VOXELS`, the default; 0: inside the box only, the rule
        before the fifteenth session). The voxels' model has no image outside the box: none there.
    local_refit_share
        A residual round that finds at most this share of the particles found so far as new
        candidates (:data:`LOCAL_REFIT_SHARE`, the default; 0: never, every particle refitted each
        round, the rule before the sixteenth session) fits, splits, relocates and prunes only the new
        candidates and the particles whose images share a pixel with theirs; the other particles
        are held (their image taken off the recorded one). A round with more candidates (on two
        cameras, hundreds of noise candidates that act as the fit's starts) refits every particle.

    ``noise_model`` and ``residual_mask`` keep their defaults here (``"flat"`` and 0): this class
    is explicit. ``lfpiv particles`` and ``lfpiv.particles`` choose them from the cameras used
    (``"shot"`` and 3 where a light-field camera is among them, ``"flat"`` and 0 for pinhole
    cameras alone: ``lfpiv.jobs.particles.fit_defaults``); the live route keeps ``"flat"`` and 0.
    """

    method: str | None = None
    candidate_iterations: int = 50
    candidate_protocol: str = "fast"
    candidate_threshold: float = 0.05
    candidate_source: str = "reconstruction"
    candidate_weights: str = "protocol"
    candidate_smoothing: float = 0.0
    ray_keep_bins: float = 1.0
    ray_min_score: float = 0.1
    shakes: int = 12
    max_step_voxels: float = 0.5
    min_intensity: float = 0.5
    intensity_axis: str | None = None
    intensity_share: float = 0.1
    merge_voxels: float = 1.0
    rounds: int = 3
    split_intensity: float = 1.4
    model: str = "point"
    point_sub_apertures: int = 0
    particle_image_px: float = 3.0
    wavelength_nm: float = 532.0
    relocate_depth: int = 4
    relocate_screen: float = 0.0
    jacobian_reuse: float = 0.0
    max_position_std: float = 0.0
    noise_model: str = "flat"
    noise_floor: float = 0.0
    residual_mask: float = 0.0
    box_margin_voxels: float = BOX_MARGIN_VOXELS
    local_refit_share: float = LOCAL_REFIT_SHARE

    def __post_init__(self) -> None:
        if not 0.0 <= self.local_refit_share <= 1.0:
            raise ValueError(f"local_refit_share is a share of the particles found, from 0 (never) to 1, got "
                             f"{self.local_refit_share}")
        if not 0.0 <= self.box_margin_voxels <= 16.0:
            raise ValueError(f"box_margin_voxels is how far outside the box particles are kept, voxels, from 0 to 16, "
                             f"got {self.box_margin_voxels}")
        if self.candidate_iterations < 1 or self.shakes < 0 or self.rounds < 1:
            raise ValueError("candidate_iterations and rounds must be at least 1 and shakes at least 0")
        if self.candidate_protocol not in PROTOCOLS:
            raise ValueError(f"the candidates' protocol is one of {', '.join(PROTOCOLS)}, got "
                             f"{self.candidate_protocol!r}")
        if self.candidate_source not in CANDIDATE_SOURCES:
            raise ValueError(f"the candidates' source is one of {', '.join(CANDIDATE_SOURCES)}, got "
                             f"{self.candidate_source!r}")
        if self.candidate_weights not in CANDIDATE_WEIGHTS:
            raise ValueError(f"the candidates' weights are one of {', '.join(CANDIDATE_WEIGHTS)}, got "
                             f"{self.candidate_weights!r}")
        if not 0.0 <= self.candidate_smoothing <= 16.0:
            raise ValueError(f"candidate_smoothing is a sigma in voxels from 0 (none) to 16, got "
                             f"{self.candidate_smoothing}")
        if not (0.0 < self.ray_keep_bins <= 1.0 and 0.0 <= self.ray_min_score < 1.0):
            raise ValueError(f"ray_keep_bins is a share above 0 and at most 1 and ray_min_score one from 0 to below 1, "
                             f"got {self.ray_keep_bins} and {self.ray_min_score}")
        if not 0.0 < self.candidate_threshold < 1.0:
            raise ValueError(f"the candidate threshold (--threshold) is a fraction of the brightest voxel above 0 and "
                             f"below 1, got {self.candidate_threshold}")
        if self.model not in MODELS:
            raise ValueError(f"the particle model is one of {', '.join(MODELS)}, got {self.model!r}")
        if not 0.0 < self.particle_image_px <= 64.0:
            raise ValueError(f"particle_image_px is a particle image's diameter in pixels, above 0 and at most 64, "
                             f"got {self.particle_image_px}")
        if not 0.0 <= self.wavelength_nm < 1e5:
            raise ValueError(f"wavelength_nm is the laser's wavelength in nm (0: no diffraction blur), got "
                             f"{self.wavelength_nm}")
        if self.noise_model not in NOISE_MODELS:
            raise ValueError(f"the noise model is one of {', '.join(NOISE_MODELS)}, got {self.noise_model!r}")
        if not 0.0 <= self.noise_floor <= 1.0:
            raise ValueError(f"noise_floor is a share of the background's weight, from 0 (none) to 1, got "
                             f"{self.noise_floor}")
        if not self.residual_mask >= 0:
            raise ValueError(f"residual_mask is a number of background noise sigmas, 0 (none) or more, got "
                             f"{self.residual_mask}")
        if self.max_position_std < 0:
            raise ValueError(f"max_position_std is a standard deviation in voxels, 0 (keep all) or more, got "
                             f"{self.max_position_std}")
        if not 0.0 <= self.relocate_screen <= 1.0:
            raise ValueError(f"relocate_screen is a share of the sub-apertures, 0 (no screen) to 1, got "
                             f"{self.relocate_screen}")
        if not 0.0 <= self.jacobian_reuse < 1.0:
            raise ValueError(f"jacobian_reuse is a move in voxels, 0 (every particle traced) to below 1, got "
                             f"{self.jacobian_reuse}")
        if self.relocate_depth < 0:
            raise ValueError(f"relocate_depth is a number of voxels, 0 (no moves) or more, got {self.relocate_depth}")
        if self.point_sub_apertures < 0:
            raise ValueError(f"point_sub_apertures must be 0 (twice the pixels per lenslet) or more, got "
                             f"{self.point_sub_apertures}")
        if self.split_intensity < 0:
            raise ValueError(f"split_intensity must be 0 (no splitting) or more, got {self.split_intensity}")
        if self.intensity_axis not in (None, "x", "y", "z"):
            raise ValueError(f"intensity_axis is 'x', 'y', 'z' or None (the frame's median), got "
                             f"{self.intensity_axis!r}")
        if not 0.0 < self.intensity_share <= 1.0:
            raise ValueError(f"intensity_share is a share of the particles above 0 and at most 1, got "
                             f"{self.intensity_share}")
        if self.max_step_voxels <= 0 or self.merge_voxels < 0 or self.min_intensity < 0:
            raise ValueError("max_step_voxels must be positive, merge_voxels and min_intensity at least 0")

    def as_dict(self) -> dict:
        """The settings as JSON-compatible values (the run store's ``particles/`` attributes)."""
        return asdict(self)


@dataclass
class ParticleResult:
    """One frame's particles.

    Attributes
    ----------
    positions_mm
        (n, 3) world positions (x, y, z), mm; with the point model up to
        :attr:`IprSettings.box_margin_voxels` outside the grid's box.
    intensity
        (n,) intensities in the operator's units: a particle of intensity E at a voxel centre adds E
        times that voxel's weights to the images (background-subtracted counts).
    residual
        (n,) the fit residual of each particle: the RMS of the images' residual over the pixels the
        particle lights, over the RMS of its own image there (0: explained exactly).
    candidates
        Candidates found, over all rounds.
    rounds
        Rounds run.
    rms_residual
        RMS of the images' residual over the pixels the particles' model lights, counts.
    unsure
        Particles left out because their fitted position was less sure than
        :attr:`IprSettings.max_position_std` (0 where it is 0).
    seconds
        Wall time per stage: ``candidates``, ``operator``, ``fit``.
    """

    positions_mm: np.ndarray
    intensity: np.ndarray
    residual: np.ndarray
    candidates: int = 0
    rounds: int = 0
    rms_residual: float = float("nan")
    seconds: dict = field(default_factory=dict)
    unsure: int = 0

    @property
    def n(self) -> int:
        return len(self.intensity)

    def table(self) -> np.ndarray:
        """(n, 5) float64: x, y, z (mm), intensity, residual (:data:`PARTICLE_FIELDS`)."""
        return np.column_stack([self.positions_mm, self.intensity, self.residual]).reshape(-1, 5)


def to_mm(grid: VolumeGrid, u: np.ndarray) -> np.ndarray:
    """World (x, y, z) mm of voxel index coordinates ``u`` (n, 3) (z, y, x)."""
    return np.asarray(grid.origin_mm) + np.asarray(u, dtype=np.float64)[:, ::-1] * np.asarray(grid.voxel_mm)


def to_index(grid: VolumeGrid, points_mm: np.ndarray) -> np.ndarray:
    """Voxel index coordinates (z, y, x) of world points ``points_mm`` (n, 3) (x, y, z) mm."""
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    return ((p - np.asarray(grid.origin_mm)) / np.asarray(grid.voxel_mm))[:, ::-1]


class _Model:
    """The images of particles near a set of voxels: the operator's rows of those voxels as a sparse
    (pixels, voxels + 1) matrix (the last column empty: where a corner falls outside the set)."""

    def __init__(self, projector: Projector, method: str, u: np.ndarray) -> None:
        grid = projector.grid
        self.shape = np.asarray(grid.shape, dtype=np.int64)
        # the 4 x 4 x 4 voxels around each particle: room for its fit to move a voxel or so
        base = np.floor(u).astype(np.int64)
        offs = np.array([[a, b, c] for a in range(-1, 3) for b in range(-1, 3) for c in range(-1, 3)])
        near = (base[:, None, :] + offs[None]).reshape(-1, 3)
        near = near[np.all((near >= 0) & (near < self.shape), axis=1)]
        self.voxels = np.unique(self._flat(near)).astype(np.int32)
        wp = projector.wp
        op = projector.operator(wp.array(self.voxels, dtype=wp.int32, device=projector.device),
                                method=WEIGHTS[method], storage="stored")
        to_numpy = getattr(op, "to_numpy", None)
        if to_numpy is None:  # pragma: no cover - every projector's operator() stores its rows
            raise ValueError(f"the {op.kind} operator keeps no rows to model particles with")
        offsets, pix, w = to_numpy()
        nv = len(self.voxels)
        at = sparse.csr_matrix((w.astype(np.float64), pix.astype(np.int64), offsets.astype(np.int64)),
                               shape=(nv, projector.n_pixels))
        self.a = sparse.vstack([at, sparse.csr_matrix((1, projector.n_pixels))]).T.tocsr()  # (pixels, nv + 1)
        self.nv = nv

    def _flat(self, idx: np.ndarray) -> np.ndarray:
        return (idx[:, 0] * self.shape[1] + idx[:, 1]) * self.shape[2] + idx[:, 2]

    def corners(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Columns (n, 8) of each particle's cell corners, their trilinear weights (n, 8) and the
        weights' derivatives along z, y, x (n, 8, 3)."""
        base = np.floor(u).astype(np.int64)
        f = u - base
        idx = base[:, None, :] + _CORNERS[None]  # (n, 8, 3)
        inside = np.all((idx >= 0) & (idx < self.shape), axis=2)
        flat = self._flat(idx.reshape(-1, 3)).reshape(idx.shape[:2])
        col = np.searchsorted(self.voxels, np.where(inside, flat, 0))
        col = np.minimum(col, self.nv - 1)
        found = inside & (self.voxels[col] == flat)
        col = np.where(found, col, self.nv)
        # per axis, the weight of the corner's side: f on the far side, 1 - f on the near one
        side = np.where(_CORNERS[None] == 1, f[:, None, :], 1.0 - f[:, None, :])  # (n, 8, 3)
        sign = np.where(_CORNERS == 1, 1.0, -1.0)[None]  # d side / d u
        w = side.prod(axis=2)
        dw = np.stack([sign[..., a] * np.prod(np.delete(side, a, axis=2), axis=2) for a in range(3)], axis=2)
        return col, w, dw

    def columns(self, u: np.ndarray, intensity: np.ndarray, *, jacobian: bool) -> sparse.csc_matrix:
        """The (voxels + 1, n) or, with ``jacobian``, (voxels + 1, 4n) voxel-space columns: each
        particle's blend weights (its image per unit intensity), and with ``jacobian`` besides its
        image's derivatives along z, y and x (columns 4p, 4p + 1, 4p + 2, 4p + 3)."""
        n = len(u)
        col, w, dw = self.corners(u)
        if not jacobian:
            return sparse.csc_matrix((w.ravel(), (col.ravel(), np.repeat(np.arange(n), 8))), shape=(self.nv + 1, n))
        vals = np.concatenate([w[:, :, None], intensity[:, None, None] * dw], axis=2)  # (n, 8, 4)
        rows = np.broadcast_to(col[:, :, None], vals.shape)
        cols = 4 * np.arange(n)[:, None, None] + np.arange(4)[None, None, :]
        cols = np.broadcast_to(cols, vals.shape)
        return sparse.csc_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(self.nv + 1, 4 * n))

    def image(self, u: np.ndarray, intensity: np.ndarray) -> np.ndarray:
        """The particles' model image, (n_pixels,) counts."""
        return self.a @ (self.columns(u, intensity, jacobian=False) @ intensity)

    def unit_images(self, u: np.ndarray) -> sparse.csc_matrix:
        """(pixels, n): each particle's image per unit intensity."""
        return (self.a @ self.columns(u, np.ones(len(u)), jacobian=False)).tocsc()

    def jacobian(self, u: np.ndarray, intensity: np.ndarray) -> sparse.csc_matrix:
        """(pixels, 4n): per particle its image per unit intensity and its derivatives along z, y, x."""
        return (self.a @ self.columns(u, intensity, jacobian=True)).tocsc()


class _PointModel:
    """The images of particles as points, each camera's own way: a light-field camera's DRT weights
    traced from the particle's own position (:func:`lfcore._kernels.weights.drt_points`), not a
    blend of its neighbouring voxels'; a pinhole camera's Gaussian spot of ``particle_image_px``
    (1/e^2 diameter) where the particle projects, distortion included, integrated over each pixel
    (the spot :class:`lfcore.render.PinholeRenderer` draws).

    A light-field camera's footprints are traced through ``sub_apertures`` sub-apertures per
    aperture diameter (None: twice its pixels per lenslet) from a small box whose lateral spread on
    the MLA has the second moment of the main lens' diffraction blur there (Gaussian, sigma = 0.42
    lambda N of its image-side f-number N, at ``wavelength_nm``; as the renderer blurs a ray's
    lenslet): near focus, where a particle's footprint is a few microns across, the blur decides
    which lenslets share its light (the model's error against a rendered point falls from 0.31 to
    0.06 relative RMS there). The Jacobian is by forward differences of ``step`` voxels.
    """

    def __init__(self, projector: Projector, *, sub_apertures: int | None = None, wavelength_nm: float = 532.0,
                 particle_image_px: float = 3.0, step: float = 0.05, sub_share: float = 1.0) -> None:
        from lfcore._kernels import weights as kw
        from lfcore.chief_ray import diffraction_sigma_mm
        from lfcore.plan import projector_for
        from lfcore.rig import is_pinhole

        grid = projector.grid
        self.grid = grid
        self.n_pixels = projector.n_pixels
        self._kw = kw
        self.device = projector.device
        self.sigma_px = 0.25 * float(particle_image_px)
        self.step = float(step)
        self._init = dict(sub_apertures=sub_apertures, wavelength_nm=wavelength_nm,
                          particle_image_px=particle_image_px, step=step)
        self._projector = projector
        self._coarse: dict[float, _PointModel] = {}
        # per camera in image order: a light-field camera's own projector (its views and
        # sub-apertures) and the half-extent of the box it traces, or None for a pinhole camera
        floor = 0.01 * float(min(grid.voxel_mm))  # a footprint in focus keeps an area
        self._cams = []
        for cam in projector.cameras:
            if is_pinhole(cam):
                self._cams.append((cam, None, 0.0))
            else:
                n_sub = sub_apertures or max(1, 2 * round(cam.pixels_per_lenslet))
                n_sub = max(1, round(sub_share * n_sub)) if sub_share != 1.0 else n_sub
                # a box of half-width h has the variance h^2 / 3 of a Gaussian of sigma h / sqrt(3);
                # object-side, the blur on the MLA over the magnification
                blur = np.sqrt(3.0) * diffraction_sigma_mm(wavelength_nm, cam.image_side_f_number) / abs(
                    cam.magnification)
                self._cams.append((cam, projector_for([cam], grid, sub_apertures=n_sub, device=projector.device),
                                   max(float(blur), floor)))
        self.wp = kw.wp
        self._capacity: dict[int, int] = {}  # entries per point a light-field camera's tracing needed
        # the last positions' images (the fit asks for the same ones up to three times a step: the
        # trial's cost, then the next step's Jacobian and residual; the same tracing, so the same images)
        self._memo: list[tuple[bytes, sparse.csc_matrix]] = []

    def coarse(self, share: float) -> _PointModel:
        """This model traced at ``share`` of its sub-apertures per aperture diameter (at least one):
        the same cameras, blur and pinhole spots, a cheaper and rougher light-field image (made once,
        kept). :func:`_relocate`'s screen of its moves."""
        if share not in self._coarse:
            self._coarse[share] = _PointModel(self._projector, sub_share=share, **self._init)
        return self._coarse[share]

    def _light_field(self, lf, half: float, pts_mm: np.ndarray) -> sparse.csc_matrix:
        """(camera pixels, n): DRT weights of world points ``pts_mm`` (n, 3) in one light-field camera."""
        from lfcore.device import Rows, launch_rows

        wp, kw = self.wp, self._kw
        n = len(pts_mm)
        pts = wp.array(pts_mm.astype(np.float32), dtype=wp.vec3, device=self.device)
        common = [lf.views, 1, lf.sub_a, lf.sub_w, Rows(pts), half]
        counts = wp.zeros(n, dtype=wp.int64, device=self.device)
        # one pass into slots of the capacity the last call needed (a pass again where it was short)
        while True:
            cap = self._capacity.get(id(lf), 1024)
            pix = wp.empty(n * cap, dtype=wp.int32, device=self.device)
            w = wp.empty(n * cap, dtype=float, device=self.device)
            slots = wp.array(np.arange(n, dtype=np.int64) * cap, dtype=wp.int64, device=self.device)
            launch_rows(kw.drt_points, n, [*common, Rows(slots), wp.int64(0), 1e-6, 1, wp.int64(cap), Rows(counts),
                                           pix, w], self.device)
            cnt = counts.numpy().astype(np.int64)
            if cnt.max() <= cap:
                break
            self._capacity[id(lf)] = int(1.25 * cnt.max()) + 16
        keep = (np.arange(cap)[None, :] < cnt[:, None]).ravel()
        offs = np.concatenate([[0], np.cumsum(cnt)])
        return _canonical_columns(w.numpy()[keep], pix.numpy()[keep], offs, lf.n_pixels)

    def _pinhole(self, cam, pts_mm: np.ndarray) -> sparse.csc_matrix:
        """(camera pixels, n): Gaussian spots of world points ``pts_mm`` (n, 3) in one pinhole camera."""
        from scipy.special import erf

        from lfcore.pinhole import project

        ncols, nrows = cam.sensor_px
        n = len(pts_mm)
        uv = project(cam, pts_mm)  # (n, 2) column, row; pixel c spans [c, c + 1)
        ok = np.all(np.isfinite(uv), axis=1)
        uv = np.where(ok[:, None], uv, -1e6)
        half = int(np.ceil(4.0 * self.sigma_px)) + 1
        k = np.arange(-half, half + 1)
        scale = 1.0 / (self.sigma_px * np.sqrt(2.0))
        cols = np.floor(uv[:, :1]) + k[None]  # (n, 2 half + 1)
        rows = np.floor(uv[:, 1:]) + k[None]
        fx = 0.5 * (erf((cols + 1.0 - uv[:, :1]) * scale) - erf((cols - uv[:, :1]) * scale))
        fy = 0.5 * (erf((rows + 1.0 - uv[:, 1:]) * scale) - erf((rows - uv[:, 1:]) * scale))
        w = fy[:, :, None] * fx[:, None, :]  # (n, rows, cols)
        inside = ((rows >= 0) & (rows < nrows))[:, :, None] & ((cols >= 0) & (cols < ncols))[:, None, :] & ok[:, None,
                                                                                                                None]
        flat = rows[:, :, None] * ncols + cols[:, None, :]
        p = np.broadcast_to(np.arange(n)[:, None, None], w.shape)
        return sparse.csc_matrix((w[inside], (flat[inside].astype(np.int64), p[inside])), shape=(nrows * ncols, n))

    def unit_images(self, u: np.ndarray) -> sparse.csc_matrix:
        """(pixels, n): each particle's image at voxel index coordinates ``u`` (n, 3) per unit intensity.
        The last :data:`MEMO_IMAGES` sets of positions' images are kept and given again for the same
        positions (the caller must not change them in place)."""
        key = np.ascontiguousarray(u, dtype=np.float64).tobytes()
        for i, (k, m) in enumerate(self._memo):
            if k == key:
                self._memo.append(self._memo.pop(i))  # most recently used last
                return m
        m = self._traced(u)
        self._memo = [*self._memo[-(MEMO_IMAGES - 1):], (key, m)]
        return m

    def traced(self, u: np.ndarray) -> sparse.csc_matrix:
        """(pixels, n): :meth:`unit_images` traced, not memoised (images used once: the Jacobian's moved
        particles, :func:`_relocate`'s moves). Each point's image is its own, whatever else is traced
        with it: ``traced(vstack([u, v]))`` is ``hstack([traced(u), traced(v)])`` to the bit."""
        return self._traced(u)

    def _traced(self, u: np.ndarray) -> sparse.csc_matrix:
        """(pixels, n): :meth:`unit_images`, traced."""
        n = len(u)
        if n == 0:
            return sparse.csc_matrix((self.n_pixels, 0))
        pts = to_mm(self.grid, u)
        parts = [self._pinhole(cam, pts) if lf is None else self._light_field(lf, half, pts)
                 for cam, lf, half in self._cams]
        return sparse.vstack(parts).tocsc() if len(parts) > 1 else parts[0]

    def image(self, u: np.ndarray, intensity: np.ndarray) -> np.ndarray:
        """The particles' model image, (n_pixels,) counts."""
        return self.unit_images(u) @ intensity

    def jacobian(self, u: np.ndarray, intensity: np.ndarray, *, reuse: dict | None = None,
                 reuse_below: float = 0.0) -> sparse.csc_matrix:
        """(pixels, 4n): per particle its image per unit intensity, then its image's derivatives along
        z, y and x (columns 4p .. 4p + 3).

        ``reuse``: a dict this call keeps its unit derivatives in (the positions they were traced at
        and the three derivative columns per particle); a particle that moved by at most
        ``reuse_below`` voxels along every axis since its derivatives were traced keeps them (scaled by
        its current intensity: an inexact Newton), and only the others are traced again. An empty dict
        or ``reuse_below`` 0: every particle traced. The particles must be the same ones, in the same
        order, from call to call with one dict (a fit's shakes)."""
        n = len(u)
        here = self.unit_images(u)
        fresh = np.ones(n, dtype=bool)
        if reuse and reuse_below > 0 and len(reuse["u"]) == n:
            fresh = np.max(np.abs(u - reuse["u"]), axis=1) > reuse_below
        idx = np.flatnonzero(fresh)
        # the three moved copies of every particle traced at once (one launch: each point's image is its
        # own, whatever else is traced beside it), not kept: used once
        moved = self.traced(np.vstack([u[idx] + self.step * np.eye(3)[a] for a in range(3)]))
        k = len(idx)
        here_f = here[:, idx]
        units = [(moved[:, a * k:(a + 1) * k] - here_f) / self.step for a in range(3)]  # forward differences
        if k < n:  # the kept particles' columns from the last tracing, the fresh ones in their places
            pos = np.empty(n, dtype=np.int64)
            keep = np.flatnonzero(~fresh)
            pos[idx] = np.arange(k)
            pos[keep] = k + np.arange(len(keep))
            units = [sparse.hstack([units[a], reuse["d"][a][:, keep]]).tocsc()[:, pos] for a in range(3)]
            last_u = reuse["u"].copy()
            last_u[idx] = u[idx]
        else:
            units = [m.tocsc() for m in units]
            last_u = np.array(u, dtype=np.float64)
        if reuse is not None:
            reuse["u"], reuse["d"] = last_u, units
            reuse["traced"] = reuse.get("traced", 0) + k
        blocks = [here] + [units[a] @ sparse.diags(intensity) for a in range(3)]
        j = sparse.hstack(blocks).tocsc()
        order = np.arange(4 * n).reshape(4, n).T.ravel()  # (unit, dz, dy, dx) per particle
        return j[:, order]


def _canonical_columns(w: np.ndarray, pix: np.ndarray, offsets: np.ndarray, n_pixels: int) -> sparse.csc_matrix:
    """(``n_pixels``, n) the columns ``offsets[p] .. offsets[p + 1]`` of entries ``w`` at pixels ``pix``
    (in any order, a pixel repeated), each column's pixels sorted and a pixel's entries summed in
    float64 (scipy's canonical format): what ``sum_duplicates`` makes of them, to the bit.

    A tracing writes a point's entries in the order of its sub-apertures, the same pixel several
    times. Where ``sum_duplicates`` sorts every column (a comparison sort: on the tiny rig a seventh of
    the point model's tracing time), the columns' pixels are ordered here by two counting sorts (to
    pixel-major and back: each stable, O(entries + pixels)), in parts of :data:`CANONICAL_POINTS`
    points. A pixel's entries are summed in their tracing order where ``sum_duplicates`` sums them in
    its sort's; both sums are exact, so the matrices are equal to the bit: float32 weights from
    ``min_weight`` (1e-6) to 1, at most 2**20 apart, up to 256 of them on one pixel, add up in
    float64's 53 bits without rounding (24 + 20 + 1 + 8; ``test_ipr`` checks the bits on points off
    focus and on the focal plane, where one pixel takes the most)."""
    n = len(offsets) - 1
    offsets = np.asarray(offsets, dtype=np.int64)
    if n <= CANONICAL_POINTS:
        return _canonical_part(w, pix, offsets, n_pixels)
    parts = [_canonical_part(w[offsets[p]:offsets[q]], pix[offsets[p]:offsets[q]], offsets[p:q + 1] - offsets[p],
                             n_pixels)
             for p, q in ((p, min(p + CANONICAL_POINTS, n)) for p in range(0, n, CANONICAL_POINTS))]
    return sparse.hstack(parts, format="csc")  # in cache-sized parts


def _canonical_part(w: np.ndarray, pix: np.ndarray, offsets: np.ndarray, n_pixels: int) -> sparse.csc_matrix:
    """:func:`_canonical_columns` of one part."""
    n = len(offsets) - 1
    a = sparse.csr_matrix((np.asarray(w, dtype=np.float64), np.asarray(pix), offsets),
                          shape=(n, n_pixels)).tocsc().tocsr()  # rows = points, each row's pixels sorted
    m = sparse.csc_matrix((a.data, a.indices, a.indptr), shape=(n_pixels, n))
    m.sum_duplicates()  # sorted already (a linear check): the adjacent repeats summed in one pass
    return m


def _fit(model: _Model, b: np.ndarray, u: np.ndarray, intensity: np.ndarray, *, shakes: int,
         max_step: float, weights: np.ndarray | None = None,
         jacobian_reuse: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every particle's (intensity, z, y, x) at once against the images
    ``b``, each pixel's squared residual times its ``weights`` (None: 1); returns the fitted ``u``
    and ``intensity``. ``jacobian_reuse`` (voxels, a point model's; 0: none): a particle that moved
    at most this far since its Jacobian's columns were traced keeps them
    (:attr:`IprSettings.jacobian_reuse`)."""
    if len(u) == 0:
        return u, intensity
    w = np.ones(len(b)) if weights is None else weights
    cost = float(np.sum(w * (b - model.image(u, intensity)) ** 2))
    lam = 1e-3
    memo: dict = {}  # the point model's last unit derivatives (the first shake traces every particle)
    for _ in range(shakes):
        j = (model.jacobian(u, intensity, reuse=memo, reuse_below=jacobian_reuse)  # (pixels, 4n)
             if jacobian_reuse > 0 and isinstance(model, _PointModel) else model.jacobian(u, intensity))
        r = b - model.image(u, intensity)
        jw = j if weights is None else (sparse.diags(w) @ j).tocsc()
        jtj = (j.T @ jw).tocsc()
        g = jw.T @ r
        d = jtj.diagonal().copy()
        d[d <= 0] = 1.0
        x0 = None
        for _ in range(6):  # raise the damping until a step lowers the residual
            step = _damped_step(jtj, lam * d, g, x0=x0)
            x0 = step
            step = step.reshape(-1, 4)
            new_u = u + np.clip(step[:, 1:], -max_step, max_step)
            new_i = np.maximum(intensity + step[:, 0], 0.0)
            new_cost = float(np.sum(w * (b - model.image(new_u, new_i)) ** 2))
            if new_cost < cost:
                u, intensity, cost = new_u, new_i, new_cost
                lam = max(lam / 3.0, 1e-6)
                break
            lam *= 10.0
        else:
            break
    return u, intensity


def _damped_step(jtj: sparse.csc_matrix, damping: np.ndarray, g: np.ndarray, *, x0: np.ndarray | None = None,
                 cg_from: int = 1000, cg_iterations: int = 60, cg_rtol: float = 1e-6) -> np.ndarray:
    """The Levenberg-Marquardt step ``x`` of ``(jtj + diag(damping)) x = g``.

    Parameters
    ----------
    jtj : scipy.sparse.csc_matrix
        The weighted normal matrix J^T W J, symmetric positive semi-definite.
    damping : numpy.ndarray
        The damping added to its diagonal, every entry positive: the system is positive definite.
    g : numpy.ndarray
        The right-hand side J^T W r.
    x0 : numpy.ndarray or None
        Where conjugate gradients start (the step of a trial that failed with less damping); None: zero.
    cg_from : int
        Systems of at least this many unknowns are tried by conjugate gradients first.
    cg_iterations : int
        The most conjugate-gradient iterations before the direct solve takes over.
    cg_rtol : float
        Conjugate gradients stop at a residual this many times ``|g|``.

    Returns
    -------
    numpy.ndarray
        The step. Conjugate gradients preconditioned by the diagonal, where they converge within
        ``cg_iterations`` (a heavily damped system), else a sparse LU (SuperLU) in a minimum-degree order of
        the symmetric pattern with pivots on the diagonal (no pivoting is needed for a positive definite
        matrix): about half the cost of ``spsolve``'s column order and partial pivoting, the same solution
        to rounding.
    """
    a = (jtj + sparse.diags(damping)).tocsc()
    if a.shape[0] >= cg_from:
        x, info = cg(a, g, x0=x0, M=sparse.diags(1.0 / a.diagonal()), rtol=cg_rtol, maxiter=cg_iterations)
        if info == 0:
            return x
    lu = splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return lu.solve(g)


def _variance_slopes(m: np.ndarray, y: np.ndarray, model_error: bool) -> tuple[float, float]:
    """The non-negative least-squares ``k, e2`` of ``y ~ k m + e2 m^2`` (``e2`` 0 without
    ``model_error``)."""
    a = np.stack([m, m * m], axis=1) if model_error else m[:, None]
    best, best_cost = (0.0, 0.0), float(np.sum(y * y))
    for cols in ([[0, 1], [0], [1]] if model_error else [[0]]):
        ac = a[:, cols]
        coef = np.linalg.lstsq(ac, y, rcond=None)[0]
        if np.any(coef < 0):
            continue
        cost = float(np.sum((y - ac @ coef) ** 2))
        if cost < best_cost:
            full = [0.0, 0.0]
            for c, v in zip(cols, coef, strict=True):
                full[c] = float(v)
            best, best_cost = (full[0], full[1]), cost
    return best


def noise_weights(b: np.ndarray, m: np.ndarray, sigma0: np.ndarray, sizes: Sequence[int], *,
                  model_error: bool = False, floor: float = 0.0) -> np.ndarray:
    """Each pixel's weight, the inverse of its noise variance ``sigma0^2 + k m`` (and, with
    ``model_error``, ``+ (e m)^2``), ``k`` (and ``e``) per camera fitted to the residual, scaled to
    1 on the background of the quietest camera.

    Parameters
    ----------
    b
        (pixels,) the background-subtracted images of all cameras, counts.
    m
        (pixels,) the particles' model image there.
    sigma0
        (cameras,) each camera's background noise, counts.
    sizes
        Each camera's pixels, in ``b``'s order.
    model_error
        Add the model's own error, a share ``e`` of the signal: ``(e m)^2``. A synthetic image
        rendered from a few thousand rays a particle, or a real one, differs from the model by
        more on a bright pixel than its shot noise allows; with this term such a pixel is trusted
        no more than the model's accuracy there.
    floor
        No pixel's weight below ``floor`` times its camera's background's (its variance at most
        ``sigma0^2 / floor``); 0: no floor.

    Returns
    -------
    numpy.ndarray
        (pixels,) ``1 / (sigma0^2 + k m [+ e^2 m^2])`` with ``k`` (and ``e^2``) the non-negative
        least-squares fit of the squared residual less ``sigma0^2`` against ``m`` (and ``m^2``)
        over the pixels the particles light: photon shot noise is ``k`` = the gain (counts per
        electron), and a renderer's rays each carrying several counts add to it; times
        ``min(sigma0)^2`` (unscaled where any camera's ``sigma0`` is 0).
    """
    w = np.empty(len(b))
    offs = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    for c in range(len(sizes)):
        sl = slice(offs[c], offs[c + 1])
        mc = np.maximum(np.asarray(m[sl], dtype=np.float64), 0.0)
        v0 = max(float(sigma0[c]) ** 2, 1e-12)
        lit = mc > 0
        k, e2 = (_variance_slopes(mc[lit], (b[sl][lit] - mc[lit]) ** 2 - v0, model_error) if np.any(lit)
                 else (0.0, 0.0))
        var = v0 + k * mc + e2 * mc * mc
        if floor > 0:
            var = np.minimum(var, v0 / floor)
        w[sl] = 1.0 / var
    return w * (float(np.min(sigma0)) ** 2 if np.min(sigma0) > 0 else 1.0)  # 1 on the background of the quietest


def _move_gains(trace, moves: np.ndarray, wc0: sparse.csc_matrix, wr: np.ndarray,
                intensity: np.ndarray, w: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``moves`` (m, 4: a particle's index, then its new position z, y, x, voxels): its
    image's weighted norm ``nk`` and its weighted product ``dot`` with what the other particles
    leave unexplained, traced by ``trace`` :data:`RELOCATE_POINTS` at a time (each point's image
    its own, whatever is traced beside it)."""
    m = len(moves)
    nks, dots = np.empty(m), np.empty(m)
    for first in range(0, m, RELOCATE_POINTS):
        part = moves[first:first + RELOCATE_POINTS]
        p = part[:, 0].astype(np.int64)
        ck = trace(np.ascontiguousarray(part[:, 1:]))
        nks[first:first + len(p)] = np.asarray(ck.multiply(ck if w is None else sparse.diags(w) @ ck).sum(axis=0)
                                               ).ravel()
        cross = np.asarray(ck.multiply(wc0[:, p]).sum(axis=0)).ravel()
        dots[first:first + len(p)] = np.asarray(ck.T @ wr).ravel() + intensity[p] * cross
    return nks, dots


def _gain(nk: np.ndarray, dot: np.ndarray) -> np.ndarray:
    """What a position's image at its best intensity explains: ``dot^2 / nk`` (0 where either is not
    positive)."""
    return np.where((nk > 0) & (dot > 0), dot**2 / np.where(nk > 0, nk, 1.0), 0.0)


def _stay_gains(c0: sparse.csc_matrix, b: np.ndarray, intensity: np.ndarray, w: np.ndarray | None
                ) -> tuple[sparse.csc_matrix, np.ndarray, np.ndarray]:
    """For the particles' unit images ``c0`` (pixels, n): ``w`` times them, ``w`` times the residual
    ``b - c0 @ intensity`` (``w``: each pixel's weight, None: alike), and what each particle's own
    position explains of what the others leave (:func:`_gain`)."""
    wc0 = c0 if w is None else (sparse.diags(w) @ c0).tocsc()
    wr = (b - c0 @ intensity) * (1.0 if w is None else w)
    n0 = np.asarray(c0.multiply(wc0).sum(axis=0)).ravel()
    return wc0, wr, _gain(n0, np.asarray(c0.T @ wr).ravel() + intensity * n0)


def _screened_moves(coarse, b: np.ndarray, u: np.ndarray, intensity: np.ndarray, offsets: np.ndarray,
                    weights: np.ndarray | None) -> np.ndarray:
    """(n, :data:`RELOCATE_KEEP`) each particle's best moves (indices into ``offsets``, ascending;
    -1: none) by ``coarse``'s images: its moves that explain the most of what the others leave,
    where the best explains at least :data:`RELOCATE_SCREEN_SLACK` of what its own position does."""
    n, k = len(u), len(offsets)
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    wc0, wr, stay = _stay_gains(coarse.traced(u), b, intensity, w)
    idx = np.tile(np.arange(n), k)
    moves = np.column_stack([idx, np.vstack([u + off for off in offsets])])  # move m's particles in m n ..
    gains = _gain(*_move_gains(coarse.traced, moves, wc0, wr, intensity, w)).reshape(k, n).T  # (n, k)
    keep = min(RELOCATE_KEEP, k)
    top = np.argpartition(-gains, keep - 1, axis=1)[:, :keep] if keep < k else np.tile(np.arange(k), (n, 1))
    worth = gains.max(axis=1) >= RELOCATE_SCREEN_SLACK * stay
    top = np.sort(top, axis=1)
    top[~worth] = -1
    return top


def _relocate(model, b: np.ndarray, u: np.ndarray, intensity: np.ndarray, offsets: np.ndarray,
              weights: np.ndarray | None = None, *, screen: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Each particle moved to the best of its position and ``offsets`` (k, 3) voxels (z, y, x) from
    it, the others held: the position whose image, at its best intensity, explains most of what
    the others leave unexplained. The fit only finds the nearest minimum of the residual; a
    light-field camera's image of a particle changes slowly with depth (and alike either side of
    the focal plane), so a particle fitted a voxel or two off in depth stays there unless moved.
    With ``weights`` (each pixel's, :func:`noise_weights`) the products are weighted alike.
    ``screen`` (a point model's, :attr:`IprSettings.relocate_screen`, above 0): the moves first
    traced at that share of its sub-apertures, only each particle's best few by that
    (:func:`_screened_moves`) traced in full and compared as without it."""
    if len(u) == 0 or len(offsets) == 0:
        return u, intensity
    if screen > 0 and hasattr(model, "coarse"):
        return _relocate_screened(model, b, u, intensity, offsets, weights, screen)
    c0 = model.unit_images(u)
    r = b - c0 @ intensity
    w = np.ones(len(b)) if weights is None else np.asarray(weights, dtype=np.float64)
    wc0 = c0 if weights is None else (sparse.diags(w) @ c0).tocsc()
    wr = w * r
    n0 = np.asarray(c0.multiply(wc0).sum(axis=0)).ravel()
    own = np.asarray(c0.T @ wr).ravel() + intensity * n0  # each particle's image . what the others leave
    best = np.where(n0 > 0, np.maximum(own, 0.0) ** 2 / np.where(n0 > 0, n0, 1.0), 0.0)
    best_u, best_i = u.copy(), intensity.copy()
    n = len(u)
    # the moves' images traced a batch of moves at a time (one launch, one product each: every particle's
    # image, and so its column's products, its own whatever is traced beside it), not memoised (used once)
    trace = getattr(model, "traced", model.unit_images)
    per = max(1, RELOCATE_POINTS // n)
    for first in range(0, len(offsets), per):
        moves = offsets[first:first + per]
        k = len(moves)
        ck = trace(np.vstack([u + off for off in moves]))  # (pixels, k n): move m's particles in m n .. (m + 1) n
        nks = np.asarray(ck.multiply(ck if weights is None else sparse.diags(w) @ ck).sum(axis=0)).ravel()
        tiled = wc0 if k == 1 else sparse.hstack([wc0] * k).tocsc()
        cross = np.asarray(ck.multiply(tiled).sum(axis=0)).ravel()  # each move's image . its particle's own
        dots = np.asarray(ck.T @ wr).ravel() + np.tile(intensity, k) * cross
        for m, off in enumerate(moves):  # in order: a later move must beat the earlier ones' best
            nk, dot = nks[m * n:(m + 1) * n], dots[m * n:(m + 1) * n]
            gain = np.where((nk > 0) & (dot > 0), dot**2 / np.where(nk > 0, nk, 1.0), 0.0)
            better = gain > best * (1.0 + RELOCATE_MARGIN)
            best[better] = gain[better]
            best_u[better] = u[better] + off
            best_i[better] = dot[better] / nk[better]
    return best_u, best_i


def _relocate_screened(model, b: np.ndarray, u: np.ndarray, intensity: np.ndarray, offsets: np.ndarray,
                       weights: np.ndarray | None, screen: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_relocate` of the moves that pass :func:`_screened_moves` (``model.coarse(screen)``'s
    images): those traced by ``model`` and compared in ``offsets``' order, a later move beating the
    earlier ones' best by :data:`RELOCATE_MARGIN`, as every move is without the screen."""
    top = _screened_moves(model.coarse(screen), b, u, intensity, offsets, weights)
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    wc0, wr, best = _stay_gains(model.unit_images(u), b, intensity, w)
    best_u, best_i = u.copy(), intensity.copy()
    p, r = np.nonzero(top >= 0)  # particle by particle, its moves in offsets' order
    if len(p) == 0:
        return best_u, best_i
    mv = top[p, r]
    moves = np.column_stack([p, u[p] + offsets[mv]])
    nk, dot = _move_gains(getattr(model, "traced", model.unit_images), moves, wc0, wr, intensity, w)
    gain = _gain(nk, dot)
    for rank in range(top.shape[1]):
        sel = r == rank
        q = p[sel]
        better = gain[sel] > best[q] * (1.0 + RELOCATE_MARGIN)
        q = q[better]
        best[q] = gain[sel][better]
        best_u[q] = u[q] + offsets[mv[sel][better]]
        best_i[q] = dot[sel][better] / nk[sel][better]
    return best_u, best_i


def _relocations(projector: Projector, depth: int) -> np.ndarray:
    """The moves :func:`_relocate` tries, (k, 3) voxels (z, y, x): for each camera, up to ``depth``
    steps either side along its viewing direction (a step one voxel along the grid axis nearest
    it), each with the moves of one voxel either side along the two other grid axes (a light-field
    camera's ambiguities near focus: depth, and where in a lenslet)."""
    if depth <= 0:
        return np.zeros((0, 3))
    voxel = np.asarray(projector.grid.voxel_mm, dtype=np.float64)
    moves = set()
    for cam in projector.cameras:
        axis = (np.asarray(cam.rotation, dtype=np.float64)[:, 2] / voxel)[::-1]  # (z, y, x) voxels
        main = int(np.argmax(np.abs(axis)))
        axis = axis / axis[main]
        others = [a for a in range(3) if a != main]
        for k in range(-depth, depth + 1):
            for s in (-1, 0, 1):
                for t in (-1, 0, 1):
                    m = k * axis
                    m[others[0]] += s
                    m[others[1]] += t
                    moves.add(tuple(np.round(m, 6)))
    moves.discard((0.0, 0.0, 0.0))
    return np.array(sorted(moves), dtype=np.float64).reshape(-1, 3)


def _position_std(model, b: np.ndarray, u: np.ndarray, intensity: np.ndarray, *,
                  seen: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) each particle's position uncertainty (z, y, x), voxels: the standard deviation of its
    fitted position from its own image's Jacobian (the others held) and the residual's variance over
    the pixels the particles light. Large where the images hardly change as the particle moves:
    a light-field camera's particle near its focal plane, whose light falls in one lenslet.
    ``seen``: 1 on the pixels measured, 0 on masked ones (None: every pixel)."""
    j = model.jacobian(u, intensity)
    if seen is not None:  # a masked pixel says nothing of where the particle is
        j = (sparse.diags(seen) @ j).tocsc()
    r = b - model.image(u, intensity)
    lit = np.asarray(abs(j).sum(axis=1)).ravel() > 0
    var = float(np.mean(r[lit] ** 2)) if lit.any() else 0.0
    g = (j.T @ j).tocsr()
    n = len(u)
    idx = 4 * np.arange(n)[:, None, None] + np.zeros((1, 4, 4), dtype=np.int64)
    rows = idx + np.arange(4)[None, :, None]
    cols = idx + np.arange(4)[None, None, :]
    blocks = np.asarray(g[rows.ravel(), cols.ravel()]).reshape(n, 4, 4)
    blocks = blocks + 1e-12 * np.trace(blocks, axis1=1, axis2=2)[:, None, None] * np.eye(4)[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = np.linalg.pinv(blocks) * var
    return np.sqrt(np.abs(np.diagonal(cov, axis1=1, axis2=2)[:, 1:]))


def local_median(coordinate: np.ndarray, values: np.ndarray, *, share: float,
                 least: int = LOCAL_MEDIAN_PARTICLES) -> np.ndarray:
    """Each point's running median along one axis: the median of ``values`` over the ``share`` of
    the points (at least ``least``, at most all) nearest it in ``coordinate``, itself included (a
    window of consecutive points in the coordinate's order, centred on the point where the ends
    allow).

    Parameters
    ----------
    coordinate
        (n,) each point's coordinate along the axis.
    values
        (n,) each point's value (a particle's intensity).
    share
        The window's share of the points, above 0 and at most 1.
    least
        The fewest points in a window.

    Returns
    -------
    numpy.ndarray
        (n,) float64 medians.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    n = len(v)
    if n == 0:
        return np.zeros(0)
    m = min(n, max(int(least), int(np.ceil(share * n))))
    order = np.argsort(np.asarray(coordinate, dtype=np.float64).ravel(), kind="stable")
    med = np.median(np.lib.stride_tricks.sliding_window_view(v[order], m), axis=1)  # (n - m + 1,)
    out = np.empty(n)
    out[order] = med[np.clip(np.arange(n) - m // 2, 0, n - m)]
    return out


def _split(u: np.ndarray, intensity: np.ndarray, factor: float, *,
           median: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Particles brighter than ``factor`` times the ``median`` (None: that of ``intensity``) as two of
    half the intensity, :data:`SPLIT_VOXELS` either side along x."""
    if factor <= 0 or len(intensity) == 0:
        return u, intensity
    big = intensity > factor * (np.median(intensity) if median is None else median)
    d = np.array([0.0, 0.0, SPLIT_VOXELS])  # (z, y, x)
    return (np.vstack([u[~big], u[big] + d, u[big] - d]),
            np.concatenate([intensity[~big], 0.5 * intensity[big], 0.5 * intensity[big]]))


def _merge(u: np.ndarray, intensity: np.ndarray, within: float) -> tuple[np.ndarray, np.ndarray]:
    """Particles closer than ``within`` voxels to a brighter one merged into it: intensities
    added, the position weighted by intensity."""
    if len(u) < 2 or within <= 0:
        return u, intensity
    order = np.argsort(-intensity)
    u, intensity = u[order], intensity[order]
    tree = cKDTree(u)
    keep = np.ones(len(u), bool)
    pos, inten = u.copy(), intensity.copy()
    for i in range(len(u)):  # brightest first
        if not keep[i]:
            continue
        near = [k for k in tree.query_ball_point(u[i], within) if k > i and keep[k]]
        if near:
            group = [i, *near]
            wsum = intensity[group].sum()
            if wsum > 0:
                pos[i] = (intensity[group, None] * u[group]).sum(axis=0) / wsum
            inten[i] = wsum
            keep[near] = False
    return pos[keep], inten[keep]


class ParticleReconstructor:
    """Reconstruct frame after frame's particles with one projector (see the module docstring).

    Parameters
    ----------
    projector
        Cameras and grid on a device (:func:`lfcore.plan.projector_for`).
    settings
        How to find, fit and prune the particles.
    recon
        The quick reconstruction's settings (thresholds, sub-apertures, ...); its ``method`` and
        ``iterations`` are replaced by ``settings``'; None: those of the protocol
        :attr:`IprSettings.candidate_protocol` for the projector's cameras.
    """

    def __init__(self, projector: Projector, *, settings: IprSettings | None = None,
                 recon: ReconSettings | None = None) -> None:
        from dataclasses import replace

        from lfcore.plan import default_method  # the planner (it imports the projectors)

        self.projector = projector
        self.settings = settings or IprSettings()
        self.method = self.settings.method or default_method(projector.cameras)
        its = self.settings.candidate_iterations
        if recon is None:  # the protocol as lfpiv reconstruct resolves it for these cameras
            base = protocol_settings(self.settings.candidate_protocol, n_cameras=len(projector.cameras),
                                     method=self.method, iterations=its)
        else:
            base = replace(recon, method=self.method, iterations=its)
        if self.settings.candidate_weights == "line-of-sight" and base.method in ("drt-mart", "mlos-mart"):
            # MLOS-MART on the same grids: no DRT weights traced (the line-of-sight first iterations and
            # MLOS-MART's hand-over are DRT's)
            base = replace(base, method="mlos-mart", los_iterations=0, handover_share=0.0)
        self.recon_settings = replace(base, warm_start=False)
        self.frames = FrameReconstructor(projector, self.recon_settings)
        #: True where particles are modelled as points (:attr:`IprSettings.model`)
        self.point_model = self.settings.model == "point"
        self._offsets = _relocations(projector, self.settings.relocate_depth)
        self._backgrounds: list[float] | None = None  # the frame's, for the ray candidates

    def _candidates(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """Peaks of a quick reconstruction of ``images``, or where their rays bundle
        (:attr:`IprSettings.candidate_source`): (n, 3) voxel index coordinates (z, y, x)."""
        if self.settings.candidate_source == "rays":
            from lfcore.raybundle import ray_candidates

            pos, _ = ray_candidates(self.projector.grid, self.projector.cameras, images,
                                    threshold_sigma=self.recon_settings.threshold_sigma,
                                    backgrounds=self._backgrounds, keep_bins=self.settings.ray_keep_bins,
                                    min_score=self.settings.ray_min_score)
            return pos
        vol = self.frames.reconstruct(images).volume
        smooth = self.settings.candidate_smoothing
        if smooth > 0:  # (z, y, x): a particle's light gathered into one peak
            from scipy.ndimage import gaussian_filter

            vol = gaussian_filter(vol, (smooth / 3.0, smooth, smooth))
        pos, _, _ = detect_particles(vol, self.projector.grid, threshold=self.settings.candidate_threshold)
        return to_index(self.projector.grid, pos)

    def reconstruct(self, images: Sequence[np.ndarray], *, predicted_mm: np.ndarray | None = None) -> ParticleResult:
        """The particles of one frame.

        Parameters
        ----------
        images
            One raw (rows, columns) image per camera, in the projector's camera order, counts; NaN
            on a flat field's masked pixels (:func:`lfcore.flatfield.correct`), which measured
            nothing: they weigh nothing in the fit and are masked in the residual rounds.
        predicted_mm
            (m, 3) world points (x, y, z) mm where particles are expected (Shake-the-Box's
            prediction from the tracks so far): first-round candidates beside the quick
            reconstruction's peaks (a peak within :attr:`IprSettings.merge_voxels` of one is left
            out), fitted and pruned like them, so that a prediction where no particle is fades away.

        Returns
        -------
        ParticleResult

        Raises
        ------
        ValueError
            The wrong number of images, or one of another size than its camera's sensor.
        """
        p, s = self.projector, self.settings
        if len(images) != len(p.cameras):
            raise ValueError(f"got {len(images)} images for {len(p.cameras)} cameras")
        backgrounds, sigma0 = [], []
        for img, cam in zip(images, p.cameras, strict=True):
            if img.shape != (cam.sensor_px[1], cam.sensor_px[0]):
                raise ValueError(f"camera '{cam.name}' images are {cam.sensor_px[1]} x {cam.sensor_px[0]}, "
                                 f"got {img.shape[0]} x {img.shape[1]}")
            level, noise = estimate_background(img)
            backgrounds.append(self.recon_settings.background if self.recon_settings.background is not None
                               else level)
            sigma0.append(noise)
        # the signal the particles must explain: background-subtracted counts of all cameras' pixels
        b = np.concatenate([np.asarray(img, np.float64).ravel() - bg for img, bg in zip(images, backgrounds,
                                                                                        strict=True)])
        # a flat field's masked pixels (NaN: lfcore.flatfield.correct) measured nothing: no weight in the fit
        seen = np.isfinite(b)
        measured = None if seen.all() else seen.astype(np.float64)
        if measured is not None:
            b = np.where(seen, b, 0.0)
        seconds = {"candidates": 0.0, "operator": 0.0, "fit": 0.0}
        self._backgrounds = backgrounds
        sizes = [img.size for img in images]
        weights = measured  # each pixel's (noise_model "shot"), from the residual of the fit before

        def weigh(model, u: np.ndarray, intensity: np.ndarray, fixed: np.ndarray | float = 0.0) -> np.ndarray | None:
            if s.noise_model != "shot":
                return measured
            if measured is None:
                return noise_weights(b, fixed + model.image(u, intensity), np.asarray(sigma0), sizes,
                                     floor=s.noise_floor)
            return np.where(seen, noise_weights(b, np.where(seen, fixed + model.image(u, intensity), 0.0),
                                                np.asarray(sigma0), sizes, floor=s.noise_floor), 0.0)

        u = np.zeros((0, 3))
        intensity = np.zeros(0)
        residual_images = list(images)
        n_cand = 0
        model = None
        rounds = 0
        for rnd in range(s.rounds):
            t0 = time.perf_counter()
            cand = self._candidates(residual_images)
            if rnd == 0 and predicted_mm is not None and len(predicted_mm):
                pred = to_index(p.grid, predicted_mm)
                if len(cand):
                    d, _ = cKDTree(pred).query(cand, k=1)
                    cand = cand[d > max(s.merge_voxels, 1.0)]
                cand = np.vstack([pred, cand])
            if len(u) and len(cand):  # where a particle is near already, the residual's peak is its rest
                d, _ = cKDTree(u).query(cand, k=1)
                cand = cand[d > max(s.merge_voxels, 1.0)]
            seconds["candidates"] += time.perf_counter() - t0
            rounds = rnd + 1
            if len(cand) == 0:
                break
            n_cand += len(cand)
            # few new candidates (a residual round): only they and the particles their images touch are fitted
            local = rnd > 0 and len(cand) <= s.local_refit_share * len(intensity)
            u = np.vstack([u, cand])
            t0 = time.perf_counter()
            model = self._model(u, model)
            seconds["operator"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            # a new particle's first intensity: its image's best fit to what is left unexplained
            c = model.unit_images(u[len(intensity):])
            rest = b - (model.image(u[:len(intensity)], intensity) if len(intensity) else 0.0)
            cs = c if measured is None else (sparse.diags(measured) @ c).tocsc()  # on the pixels seen
            norm = np.asarray(cs.multiply(cs).sum(axis=0)).ravel()
            start = np.where(norm > 0, (cs.T @ rest) / np.where(norm > 0, norm, 1.0), 0.0)
            if local:
                old = len(intensity)
                c_old = model.unit_images(u[:old])
                near = np.asarray(abs(c_old).T @ np.asarray(abs(c).sum(axis=1)).ravel()).ravel() > 0
                held = (u[:old][~near], intensity[~near])
                fixed = c_old[:, ~near] @ held[1]  # the held particles' image, taken off the recorded one
                g_u, g_i, weights = self._shake(model, b - fixed, np.vstack([u[:old][near], cand]),
                                                np.concatenate([intensity[near], np.maximum(start, 0.0)]),
                                                weights, partial(weigh, fixed=fixed), held)
                u, intensity = np.vstack([held[0], g_u]), np.concatenate([held[1], g_i])
                found = fixed + model.image(g_u, g_i)
            else:
                intensity = np.concatenate([intensity, np.maximum(start, 0.0)])
                u, intensity, weights = self._shake(model, b, u, intensity, weights, weigh)
                found = None
            seconds["fit"] += time.perf_counter() - t0
            if rnd + 1 < s.rounds:
                found = model.image(u, intensity) if found is None else found
                left = b - found if measured is None else np.where(seen, b - found, np.nan)
                offs = np.concatenate([[0], np.cumsum([img.size for img in images])])
                if s.residual_mask > 0:  # no elimination by pixels that the found particles' noise fills
                    noise = np.repeat(np.asarray(sigma0, dtype=np.float64), sizes)
                    left = np.where(found > s.residual_mask * noise, np.nan, left)
                residual_images = [(left[offs[k]:offs[k + 1]].reshape(img.shape) + backgrounds[k]).astype(np.float32)
                                   for k, img in enumerate(images)]
        unsure = 0
        if s.max_position_std > 0 and model is not None and len(u):
            sure = _position_std(model, b, u, intensity, seen=measured).max(axis=1) <= s.max_position_std
            u, intensity, unsure = u[sure], intensity[sure], int(np.count_nonzero(~sure))
        res, rms = self._residuals(model, b, u, intensity, seen=measured)
        return ParticleResult(positions_mm=to_mm(p.grid, u), intensity=intensity, residual=res, candidates=n_cand,
                              rounds=rounds, rms_residual=rms, seconds=seconds, unsure=unsure)

    def _shake(self, model: _Model | _PointModel, b: np.ndarray, u: np.ndarray, intensity: np.ndarray,
               weights: np.ndarray | None, weigh: Callable[..., np.ndarray | None],
               held: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """A round's fit of the particles ``u``, ``intensity`` to the images ``b``: fit, prune, split,
        fit, prune, relocate, fit and prune; the fitted particles and the pixels' new ``weights``
        (``weigh(model, u, intensity)``). ``held``: the particles held (not fitted, their image off
        ``b`` already), which the pruning's and the split's median intensity counts."""
        s = self.settings
        u, intensity = _fit(model, b, u, intensity, shakes=s.shakes, max_step=s.max_step_voxels, weights=weights,
                            jacobian_reuse=s.jacobian_reuse)
        weights = weigh(model, u, intensity)
        u, intensity = self._prune(u, intensity, held)
        if s.split_intensity > 0:
            median = None  # that of intensity; with particles held, theirs counted too (none left: no split)
            if held is not None and len(intensity):
                median = float(np.median(np.concatenate([held[1], intensity])))
            u, intensity = _split(u, intensity, s.split_intensity, median=median)
            u, intensity = _fit(model, b, u, intensity, shakes=s.shakes, max_step=s.max_step_voxels,
                                weights=weights, jacobian_reuse=s.jacobian_reuse)
            u, intensity = self._prune(u, intensity, held)
        if self.point_model and s.relocate_depth > 0:
            u, intensity = _relocate(model, b, u, intensity, self._offsets, weights, screen=s.relocate_screen)
        u, intensity = _fit(model, b, u, intensity, shakes=max(s.shakes // 2, 1), max_step=s.max_step_voxels,
                            weights=weights, jacobian_reuse=s.jacobian_reuse)
        weights = weigh(model, u, intensity)
        u, intensity = self._prune(u, intensity, held)
        return u, intensity, weights

    def _model(self, u: np.ndarray, previous: _Model | _PointModel | None) -> _Model | _PointModel:
        """The particles' forward model: the point model (one for all rounds: light-field cameras'
        traced points, pinhole cameras' Gaussian spots) where :attr:`IprSettings.model` asks for it,
        else the blend of the voxels' operator rows around ``u``."""
        if self.point_model:
            if previous is None:
                s = self.settings
                previous = _PointModel(self.projector, sub_apertures=s.point_sub_apertures or None,
                                       wavelength_nm=s.wavelength_nm, particle_image_px=s.particle_image_px)
            return previous
        return _Model(self.projector, self.method, u)

    def _prune(self, u: np.ndarray, intensity: np.ndarray, held: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """Leave out the particles outside the box (by more than :attr:`IprSettings.box_margin_voxels`
        with the point model), merge the close ones and drop the faint ones. ``held``: particles
        not pruned here whose intensities the median counts too."""
        s = self.settings
        shape = np.asarray(self.projector.grid.shape)
        margin = s.box_margin_voxels if self.point_model else 0.0
        inside = np.all((u >= -0.5 - margin) & (u <= shape - 0.5 + margin), axis=1) & (intensity > 0)
        u, intensity = _merge(u[inside], intensity[inside], s.merge_voxels)
        if len(intensity):
            all_u, all_i = (u, intensity) if held is None else (np.vstack([held[0], u]),
                                                                np.concatenate([held[1], intensity]))
            if s.intensity_axis is None:
                light = np.median(all_i)
            else:  # the light where each particle is: u is (z, y, x)
                light = local_median(all_u[:, 2 - "xyz".index(s.intensity_axis)], all_i,
                                     share=s.intensity_share)[len(all_i) - len(intensity):]
            bright = intensity >= s.min_intensity * light
            u, intensity = u[bright], intensity[bright]
        return u, intensity

    @staticmethod
    def _residuals(model: _Model | None, b: np.ndarray, u: np.ndarray, intensity: np.ndarray, *,
                   seen: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """Each particle's residual (that over its pixels against its own image) and the RMS residual
        over the pixels the particles light; ``seen``: 1 on the pixels measured, 0 on masked ones
        (None: every pixel)."""
        if model is None or len(u) == 0:
            return np.zeros(len(u)), float("nan")
        c = model.unit_images(u)  # (pixels, n) per unit intensity
        if seen is not None:
            c = (sparse.diags(seen) @ c).tocsc()
        r = b - c @ intensity
        lit = (abs(c) > 0).astype(np.float64)
        r2 = lit.T @ (r * r)
        own = np.asarray(c.multiply(c).sum(axis=0)).ravel() * intensity**2
        res = np.sqrt(r2 / np.where(own > 0, own, np.inf))
        touched = np.asarray(lit.sum(axis=1)).ravel() > 0
        rms = float(np.sqrt(np.mean(r[touched] ** 2))) if touched.any() else float("nan")
        return res, rms
