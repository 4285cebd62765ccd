"""Reconstructing a run store's pairs into ``particles/`` (``lfpiv particles``): iterative particle
reconstruction (:mod:`lfcore.ipr`), pair by pair, resumable with ``--skip-done``."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lfcore.device import MemoryBudgetError
from lfcore.flatfield import FlatField, correct
from lfcore.ipr import IprSettings, ParticleReconstructor, ParticleResult
from lfcore.plan import projector_for, unsupported_method
from lfcore.rig import Rig, is_pinhole
from lfcore.runstore import RunStore, is_time_resolved
from lfcore.track import SeriesSettings, TrackSettings, link_series, predict_series
from lfcore.volume import VolumeGrid
from lfpiv.errors import UsageError
from lfpiv.pair_runner import AlongChoice, along_option_error, along_pairs_choice, recorded_pairs, run_pairs

log = logging.getLogger(__name__)

__all__ = ["INTENSITY_REFERENCES", "LIGHT_FIELD_FIT", "NOISE_MODEL_CHOICES", "PINHOLE_FIT", "AlongPairs",
           "IprSettings", "PairParticles", "ParticlesDone", "ParticlesJob", "check_along_workers", "fit_defaults",
           "intensity_axis", "ipr_settings", "particles_pair_task", "particles_run", "same_settings", "used_cameras"]


#: Settings added to :class:`lfcore.ipr.IprSettings` after ``particles/`` was first written, at the
#: value that reproduces what the code did before each existed: no splitting (before
#: ``split_intensity``), the trilinear blend of voxels' rows (before ``model``), no whole-voxel moves
#: (before ``relocate_depth``), every particle kept (before ``max_position_std``), candidates from
#: plain DRT-MART of a fixed count (before ``candidate_protocol``), candidates from a reconstruction's
#: peaks (before ``candidate_source``), every particle judged against the frame's median intensity
#: (before ``intensity_axis``), every pixel weighed alike in the fit (before ``noise_model``), no floor
#: on the weights (before ``noise_floor``), no masked pixels in the residual rounds (before
#: ``residual_mask``), only the box's particles (before ``box_margin_voxels``), every particle refitted in
#: every residual round (before ``local_refit_share``), every relocation move traced in full (before
#: ``relocate_screen``), the candidates' quick reconstruction on its protocol's weights, its volume
#: unsmoothed (before ``candidate_weights`` and ``candidate_smoothing``), every particle's Jacobian
#: traced every shake (before ``jacobian_reuse``).
OLD_DEFAULTS: dict[str, Any] = {"split_intensity": 0.0, "model": "voxels", "relocate_depth": 0,
                                "max_position_std": 0.0, "candidate_protocol": "fixed",
                                "candidate_source": "reconstruction", "intensity_axis": None,
                                "intensity_share": 0.1, "noise_model": "flat",
                                "noise_floor": 0.0, "residual_mask": 0.0, "box_margin_voxels": 0.0,
                                "local_refit_share": 0.0, "relocate_screen": 0.0, "candidate_weights": "protocol",
                                "candidate_smoothing": 0.0, "jacobian_reuse": 0.0}

#: What ``lfpiv particles --min-intensity-of`` judges a particle's intensity against
#: (:func:`intensity_axis`).
INTENSITY_REFERENCES = ("auto", "frame", "sheet")

#: What ``lfpiv particles --noise-model`` takes: :data:`lfcore.ipr.NOISE_MODELS` or ``"auto"``
#: (:func:`fit_defaults`).
NOISE_MODEL_CHOICES = ("auto", "shot", "flat")

#: The fit's weights and residual mask that ``"auto"`` gives where the cameras used include a
#: light-field camera (:func:`fit_defaults`), and those it gives to pinhole cameras alone.
LIGHT_FIELD_FIT: dict[str, Any] = {"noise_model": "shot", "residual_mask": 3.0}
PINHOLE_FIT: dict[str, Any] = {"noise_model": "flat", "residual_mask": 0.0}


def fit_defaults(cameras: Sequence[Any], *, noise_model: str = "auto",
                 residual_mask: float | str = "auto") -> dict[str, Any]:
    """:attr:`lfcore.ipr.IprSettings.noise_model` and :attr:`~lfcore.ipr.IprSettings.residual_mask`
    for ``lfpiv particles --noise-model`` and ``--residual-mask``: each given value as it is, each
    ``"auto"`` chosen from the cameras used (after ``--cameras``).

    Where a light-field camera is among them, ``"auto"`` is :data:`LIGHT_FIELD_FIT` (the shot-noise
    weights and the residual rounds' mask at 3 background sigmas); pinhole cameras alone get
    :data:`PINHOLE_FIT` (every pixel alike, no mask). Measured end to end (``benchmarks/RESULTS.md``,
    twelfth session, issue 48): with a light-field camera, shot + 3 found more and fewer ghosts on
    every rig (issue 48's 512 x 512 rig's A1 pair recall 0.938 and 4.0% ghosts; the mixed rig of
    one light-field and two pinhole cameras 0.852 and 10.7% ghosts to 0.890 and 2.4%); four pinhole
    cameras lost (recall 0.904 to 0.871, ghosts 1.8% to 3.0%).

    Parameters
    ----------
    cameras
        The cameras used (:class:`lfcore.rig.Camera` or any object with a ``kind``:
        :func:`lfcore.rig.is_pinhole`).
    noise_model
        ``"auto"``, ``"shot"`` or ``"flat"`` (:data:`NOISE_MODEL_CHOICES`).
    residual_mask
        ``"auto"`` or a number of background sigmas, 0 or more.

    Returns
    -------
    dict
        ``{"noise_model": str, "residual_mask": float}``: what ``particles/`` records.

    Raises
    ------
    UsageError
        No cameras (where one of them is ``"auto"``), or a value neither ``"auto"`` nor one of
        those above.
    """
    if noise_model not in NOISE_MODEL_CHOICES:
        raise UsageError(f"--noise-model is one of {', '.join(NOISE_MODEL_CHOICES)}, got '{noise_model}'")
    if isinstance(residual_mask, str) and residual_mask != "auto":
        raise UsageError(f"--residual-mask is auto or a number of background sigmas, got '{residual_mask}'")
    auto = "auto" in (noise_model, residual_mask)
    if auto and not cameras:
        raise UsageError("--noise-model and --residual-mask auto choose from the cameras used, and none is given")
    chosen = PINHOLE_FIT if all(is_pinhole(c) for c in cameras) else LIGHT_FIELD_FIT
    return {"noise_model": chosen["noise_model"] if noise_model == "auto" else noise_model,
            "residual_mask": chosen["residual_mask"] if residual_mask == "auto" else float(residual_mask)}


def used_cameras(rig: Rig, names: Sequence[str] | None) -> list[Any]:
    """The cameras of ``rig`` named in ``names`` (``--cameras``; all of them where None or empty),
    in the rig's order.

    Raises
    ------
    UsageError
        A name the rig does not have (as :func:`lfpiv.pair_runner.recorded_pairs` says it).
    """
    have = [c.name for c in rig.camera]
    unknown = [n for n in names or () if n not in have]
    if unknown:
        raise UsageError(f"--cameras: no camera '{unknown[0]}' in this run (it has {', '.join(have)})")
    return [c for c in rig.camera if not names or c.name in names]


#: Settings of ray bundling only: the reconstruction's candidates do not depend on them.
RAYS_ONLY = ("ray_keep_bins", "ray_min_score")

#: Settings of the quick reconstruction's candidates only, with the command's option for each: ray
#: bundling makes no reconstruction, so giving one of them with ``candidate_source="rays"`` is refused.
QUICK_ONLY = {"candidate_iterations": "--candidate-iterations", "candidate_protocol": "--candidate-protocol",
              "candidate_threshold": "--threshold", "candidate_weights": "--candidate-weights",
              "candidate_smoothing": "--candidate-smoothing"}

#: Settings of the point model only: the ``"voxels"`` model's particles do not depend on them
#: (groups written before they existed hold none of them).
POINT_ONLY = ("point_sub_apertures", "particle_image_px", "wavelength_nm", "relocate_depth", "box_margin_voxels",
              "relocate_screen", "jacobian_reuse")


def _recorded(settings: dict[str, Any]) -> dict[str, Any]:
    """A ``particles/`` group's recorded settings with those added since at :data:`OLD_DEFAULTS`."""
    return {**OLD_DEFAULTS, **settings}


def _matching(settings: dict[str, Any]) -> dict[str, Any]:
    """The settings that make a different set of particles (the point model's own ones only for it, ray
    bundling's only for it)."""
    out = dict(settings)
    if out.get("intensity_axis") is None:  # the frame's median: the running median's window is not used
        out.pop("intensity_share", None)
    if out.get("candidate_source", "reconstruction") != "rays":
        out = {k: v for k, v in out.items() if k not in RAYS_ONLY}
    if out.get("model") == "voxels":
        return {k: v for k, v in out.items() if k not in POINT_ONLY}
    return out


def same_settings(recorded: dict[str, Any], meta: dict[str, Any]) -> bool:
    """True when particles recorded with the settings ``recorded`` (a ``particles/`` group's
    ``settings`` attribute, perhaps written before some of today's settings existed) are those
    ``meta`` (today's :meth:`lfcore.ipr.IprSettings.as_dict` with ``method`` and ``cameras``) makes:
    what ``--skip-done`` keeps and adds to."""
    return _matching(_recorded(recorded)) == _matching(meta)


def intensity_axis(rig: Rig, reference: str = "auto") -> str | None:
    """:attr:`lfcore.ipr.IprSettings.intensity_axis` for ``lfpiv particles --min-intensity-of``
    (:data:`INTENSITY_REFERENCES`): ``"frame"``, None (the frame's median); ``"sheet"``, the rig's
    laser sheet axis (``[laser] sheet_axis``: each particle against the particles nearest it along
    it); ``"auto"``, the sheet's axis where the rig's sheet lights the box unevenly (``sheet_profile``
    other than ``"uniform"``), else None."""
    if reference not in INTENSITY_REFERENCES:
        raise UsageError(f"--min-intensity-of is one of {', '.join(INTENSITY_REFERENCES)}, got '{reference}'")
    if reference == "frame" or (reference == "auto" and rig.laser.sheet_profile == "uniform"):
        return None
    return rig.laser.sheet_axis


def ipr_settings(**options: Any) -> IprSettings:
    """:class:`lfcore.ipr.IprSettings` of the given options, or a one-line :class:`UsageError`
    (also where a quick reconstruction's option is given with ray-bundling candidates, which ignore it)."""
    given = [k for k in QUICK_ONLY if options.get(k) is not None]
    if options.get("candidate_source") == "rays" and given:
        raise UsageError(f"{', '.join(QUICK_ONLY[k] for k in given)}: the quick reconstruction's candidates, which "
                         "--candidates rays does not make; leave them out, or choose --candidates reconstruction")
    if options.get("noise_floor") and options.get("noise_model", "flat") != "shot":
        raise UsageError("--noise-floor weighs the pixels of --noise-model shot, and the flat model weighs them all "
                         "alike (the default for pinhole cameras alone): add --noise-model shot, or leave "
                         "--noise-floor out")
    try:
        return IprSettings(**options)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


@dataclass(frozen=True)
class AlongPairs:
    """``lfpiv particles --along-pairs``: a time-resolved run's frames reconstructed in time order,
    each frame's first candidates predicted by the tracks through the frames before it
    (Shake-the-Box's prediction, :func:`lfcore.track.predict_series`).

    Attributes
    ----------
    search_voxels
        The pair tracking's first search (x, y, z), voxels, that starts the tracks
        (:attr:`lfcore.track.TrackSettings.search_voxels`, ``lfpiv track --search-voxels``).
    link_voxels
        The search around where a track's own velocity puts it in the next frame
        (:attr:`lfcore.track.SeriesSettings.link_voxels`, ``lfpiv track --link-voxels``).
    """

    search_voxels: tuple[float, float, float] = TrackSettings().search_voxels
    link_voxels: tuple[float, float, float] = SeriesSettings().link_voxels

    def __post_init__(self) -> None:
        try:  # the tracking's own checks
            TrackSettings(search_voxels=self.search_voxels)
            SeriesSettings(link_voxels=self.link_voxels)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        except TypeError:  # not numbers (the Python API's dict)
            raise UsageError(f"search_voxels and link_voxels need three positive values (x, y, z), got "
                             f"{self.search_voxels} and {self.link_voxels}") from None

    def as_dict(self) -> dict[str, Any]:
        """The settings as JSON-compatible values (recorded in ``particles/``' settings)."""
        return {"search_voxels": [float(v) for v in self.search_voxels],
                "link_voxels": [float(v) for v in self.link_voxels]}

    @property
    def frames_read(self) -> int:
        """The frames before the next one that its prediction reads (the rest may be let go)."""
        return SeriesSettings().fit_frames + 2

    def predict(self, frames: list[np.ndarray], grid: VolumeGrid) -> np.ndarray:
        """The (m, 3) positions (x, y, z), mm, the tracks through ``frames`` (each frame's (n, 3)
        particles, mm, in time order) predict in the frame after the last; none before two frames.

        Only the last frames a prediction reads are linked (the polynomial's ``fit_frames``, a
        frame missed and the one before), so a long series costs the same a frame throughout."""
        if len(frames) < 2:
            return np.zeros((0, 3))
        frames = frames[-self.frames_read:]
        tracks = link_series(frames, grid, settings=TrackSettings(search_voxels=self.search_voxels),
                             series=SeriesSettings(link_voxels=self.link_voxels))
        return predict_series(tracks, len(frames) - 1)


@dataclass
class ParticlesDone:
    """What :func:`particles_run` did.

    Attributes
    ----------
    pairs
        The pairs reconstructed now (without those skipped).
    counts
        Particles per frame reconstructed, in order (A, B of each pair).
    candidates
        Candidates per frame.
    seconds
        Wall time of each frame.
    unsure
        Particles per frame left out as unsure (:attr:`lfcore.ipr.IprSettings.max_position_std`).
    predicted
        Positions per frame the tracks so far predicted (``--along-pairs``; empty otherwise).
    device
        The Warp device.
    along
        Whether the frames were followed along the pairs, and why
        (:func:`lfpiv.pair_runner.along_pairs_choice`).
    """

    pairs: list[int] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)
    candidates: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    unsure: list[int] = field(default_factory=list)
    predicted: list[int] = field(default_factory=list)
    device: str = "cpu"
    along: AlongChoice = AlongChoice(False, "not asked")


@dataclass(frozen=True)
class ParticlesJob:
    """What a Dask worker needs to reconstruct a run's particles (:mod:`lfpiv.batch`): picklable, small."""

    path: str
    rig: Rig
    cameras: tuple[str, ...]
    grid: VolumeGrid
    settings: IprSettings
    device: str | None
    token: str
    #: per camera, the flat field its raw frames are corrected by (:func:`lfcore.flatfield.correct`)
    flats: dict[str, FlatField] | None = None


@dataclass(frozen=True)
class PairParticles:
    """A worker's result: both frames' (n, 5) particle rows and their figures (the coordinator writes them)."""

    tables: list[np.ndarray]
    candidates: list[int]
    seconds: list[float]
    unsure: list[int] = field(default_factory=lambda: [0, 0])


def _frame(ipr: ParticleReconstructor, store: RunStore, names: Sequence[str], pair: int, frame: int,
           predicted_mm: np.ndarray | None = None, flats: dict[str, FlatField] | None = None
           ) -> tuple[ParticleResult, float]:
    import time

    images = [store.read_frame(n, pair, frame) for n in names]  # a damaged frame is an error
    if flats:  # the response divided out; the masked pixels NaN, which the fit weighs not at all
        images = [correct(img, flats[n]) if n in flats else img for img, n in zip(images, names, strict=True)]
    t0 = time.perf_counter()
    try:
        res = ipr.reconstruct(images, predicted_mm=predicted_mm)
    except MemoryBudgetError as exc:
        raise UsageError(str(exc)) from None
    return res, time.perf_counter() - t0


def particles_pair_task(job: ParticlesJob, pair: int) -> PairParticles:
    """Worker task: the particles of both frames of ``pair``, returned to the coordinator, which
    appends them to ``particles/`` (the table is one array that one process writes)."""
    from lfpiv.batch import this_worker_device, worker_state

    def build() -> tuple[RunStore, ParticleReconstructor]:
        cams = [job.rig.camera_named(n) for n in job.cameras]
        proj = projector_for(cams, job.grid, device=this_worker_device(job.device))
        return RunStore.open(job.path), ParticleReconstructor(proj, settings=job.settings)  # it reads frames only

    store, ipr = worker_state(job.token, build)
    made = [_frame(ipr, store, job.cameras, pair, f, flats=job.flats) for f in (0, 1)]
    return PairParticles(tables=[r.table() for r, _ in made], candidates=[r.candidates for r, _ in made],
                         seconds=[t for _, t in made], unsure=[r.unsure for r, _ in made])


def check_along_workers(workers: Any, scheduler: Any) -> None:
    """The one-line error of ``--along-pairs`` with ``--workers`` or ``--scheduler`` (``workers``,
    ``scheduler``: the options as given; None or 0 where not), called where
    ``--along-pairs`` is asked, before any worker starts.

    Raises
    ------
    UsageError
        Workers or a scheduler: the frames are done in time order, in this process.
    """
    if workers or scheduler:
        raise UsageError("--along-pairs reconstructs the frames in time order, each predicted from the ones before: "
                         "leave out --workers and --scheduler")


def _check_along(store: RunStore, chosen: list[int], client: Any) -> None:
    """A one-line error, before anything is written, where ``--along-pairs`` cannot follow the
    particles through the chosen pairs' frames."""
    if not is_time_resolved(store.timing):
        raise UsageError(f"--along-pairs predicts each frame's particles from the frames before it, but "
                         f"{store.path} is not a time-resolved series (every frame dt after the one before); leave out "
                         "--along-pairs, or record or synthesize a time-resolved run (lfpiv synth --time-resolved)")
    check_along_workers(client is not None, None)
    if chosen != list(range(chosen[0], chosen[-1] + 1)):
        raise UsageError("--along-pairs follows particles through consecutive pairs: choose them with --pair-range "
                         "A:B (no step)")


def particles_run(store: RunStore, settings: IprSettings, pairs: slice | None = None, *,
                  cameras: Sequence[str] | None = None, device: str | None = None, progress: bool = True,
                  skip_done: bool = False, option: str = "--pair-range", client: Any = None,
                  along_pairs: AlongPairs | None = None, along_mode: str = "on",
                  along_options: Sequence[str] = (), announce: Callable[[str], None] | None = None,
                  flats: dict[str, FlatField] | None = None, flat_field: dict[str, Any] | None = None
                  ) -> ParticlesDone:
    """Reconstruct the particles of both frames of ``pairs`` (None: every recorded pair) into
    ``particles/``.

    Particles of the same grid, cameras and settings already stored are kept and added to; other
    settings make a new set beside them, which replaces them once complete (as ``reconstruct``
    does with ``volumes/``). With a Dask ``client`` (:func:`lfpiv.batch.dask_client`) the pairs are
    done on its workers, and this process appends each pair's particles to the store as it comes back.

    With ``along_pairs`` (a time-resolved run, :func:`lfcore.runstore.is_time_resolved`) the frames
    are done in time order in this process, each frame's first candidates the positions the tracks
    through the chosen pairs' frames before it predict (:meth:`AlongPairs.predict`); with
    ``skip_done`` the particles kept are those tracks' frames. ``along_mode`` says how
    ``along_pairs`` applies (:func:`lfpiv.pair_runner.along_pairs_choice`): ``"on"`` always (refused
    where it cannot), ``"auto"`` where the run is time-resolved, the pairs consecutive (two or more)
    and no ``client`` given, else frame by frame; ``"off"`` never. What ran is recorded
    (``particles/``' settings hold ``along_pairs`` where on) and said in the result's ``along``.
    ``along_options``: the options given that only apply along the pairs (as spelt), refused where
    ``"auto"`` goes frame by frame. ``announce`` (the command's ``print``) is handed the line saying
    which ran and why (:meth:`lfpiv.pair_runner.AlongChoice.line`) once, before the frames are done.
    ``flats`` (per camera, :func:`lfpiv.jobs.calibrate.flat_fields`) corrects every raw frame by its
    camera's flat field before its particles are fitted, as ``reconstruct`` and the live route do (its
    masked pixels weigh nothing); ``flat_field`` says which calibration that is and is recorded in
    ``particles/``' settings, so particles of other frames' corrections are not kept by ``skip_done``.

    Raises
    ------
    UsageError
        No recorded pairs, a pair never recorded, an unknown camera, or a box too big for memory;
        ``along_pairs`` with ``along_mode`` ``"on"`` on a run that is not time-resolved, on pairs
        that are not consecutive or on Dask workers; ``along_options`` where it goes frame by frame.
    """
    rig = store.rig
    chosen, names = recorded_pairs(store, pairs, cameras, option=option)
    cams = [rig.camera_named(n) for n in names]
    if settings.method is not None and unsupported_method(cams, settings.method) is not None:
        raise UsageError(f"camera '{unsupported_method(cams, settings.method)}' is a pinhole camera: --method "
                         f"{settings.method} needs light-field cameras; use --method mlos-smart")
    mode = along_mode if along_pairs is not None else "off"
    choice = along_pairs_choice(mode, time_resolved=is_time_resolved(store.timing), pairs=chosen,
                                workers=client is not None)
    if not choice.on:
        if along_options:
            raise UsageError(along_option_error(along_options, choice))
        along_pairs = None
    if along_pairs is not None:
        _check_along(store, chosen, client)
    log.info("%s: particles %s", store.path, choice.line())
    if announce is not None:  # before the long work, not after it
        announce(choice.line())
    grid = VolumeGrid.from_rig(rig)
    proj = projector_for(cams, grid, device=device)
    try:
        ipr = ParticleReconstructor(proj, settings=settings)
    except MemoryBudgetError as exc:
        raise UsageError(str(exc)) from None
    meta = {**settings.as_dict(), "method": ipr.method, "cameras": names}
    if along_pairs is not None:  # only where on: groups written before it, or without it, read as without
        meta["along_pairs"] = along_pairs.as_dict()
    if flats:  # likewise: groups of raw frames hold no flat_field
        meta["flat_field"] = flat_field or {}
    done = ParticlesDone(device=proj.device, along=choice)

    def matches(g: Any) -> bool:
        return (g is not None and same_settings(dict(g.attrs.get("settings", {})), meta)
                and list(g.attrs.get("origin_mm", [])) == list(grid.origin_mm)
                and list(g.attrs.get("voxel_mm", [])) == list(grid.voxel_mm))

    def differences(g: Any) -> list[str]:
        old = _matching(_recorded(dict(g.attrs.get("settings", {})))) if g is not None else {}
        now = _matching(meta)
        # a key on one side only differs too (along_pairs: followed along the pairs before, or now)
        return [k for k in {**now, **old} if old.get(k) != now.get(k)]

    def here(todo: list[int]) -> None:
        history: list[np.ndarray] = []  # --along-pairs: the chosen pairs' frames so far, in time order
        with tqdm(total=2 * len(todo), unit="frame", disable=not progress, desc="particles", leave=False) as bar:
            for p in (chosen if along_pairs is not None else todo):
                if p not in todo:  # kept by --skip-done: its particles (in the set being written) carry the tracks on
                    history.extend(store.read_particles(p, f, writing=True)[:, :3] for f in (0, 1))
                    del history[:-along_pairs.frames_read]  # type: ignore[union-attr]
                    continue
                frames: list[ParticleResult] = []
                for f in (0, 1):
                    predicted = along_pairs.predict(history, grid) if along_pairs is not None else None
                    res, seconds = _frame(ipr, store, names, p, f, predicted, flats=flats)
                    if along_pairs is not None:
                        history.append(res.positions_mm)
                        del history[:-along_pairs.frames_read]  # a long series' particles are in the store
                        done.predicted.append(len(predicted))  # type: ignore[arg-type]
                    done.seconds.append(seconds)
                    done.counts.append(res.n)
                    done.candidates.append(res.candidates)
                    done.unsure.append(res.unsure)
                    frames.append(res)
                    bar.update(1)
                    bar.set_postfix_str(f"pair {p} {'AB'[f]}: {res.n} particles")
                store.write_particles(p, [r.table() for r in frames])
                done.pairs.append(p)

    def remote(into: str) -> tuple[Any, ParticlesJob]:
        from lfpiv.batch import new_token

        return particles_pair_task, ParticlesJob(path=str(Path(store.path).resolve()), rig=rig, cameras=tuple(names),
                                                 grid=grid, settings=settings, device=device, token=new_token(),
                                                 flats=flats)

    def written(p: int, r: PairParticles) -> None:
        store.write_particles(p, r.tables)
        done.pairs.append(p)
        done.counts.extend(len(t) for t in r.tables)
        done.candidates.extend(r.candidates)
        done.seconds.extend(r.seconds)
        done.unsure.extend(r.unsure)

    run_pairs(store, "particles", chosen, matches=matches, differences=differences,
              create=lambda: store.create_particles(grid, method=ipr.method, settings=meta), skip_done=skip_done,
              here=here, remote=remote, client=client, on_done=written, desc="particles", progress=progress,
              postfix=lambda p, r: {"pair": p, "particles": "/".join(str(len(t)) for t in r.tables)},
              kept=lambda: f"the particles of {len(done.pairs)} pair(s) written before are kept" if done.pairs else "")
    return done
