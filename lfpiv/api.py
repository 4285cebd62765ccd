"""The notebook-sized Python API: what ``import lfpiv`` gives (:mod:`lfpiv` re-exports it).

The same jobs the ``lfpiv`` commands run, with keyword options::

    import lfpiv

    rig = lfpiv.load_rig("examples/one_camera.toml")
    run = lfpiv.import_files(rig, "run.zarr", frames={"cam0": "rec/*.tif"}, dt_us=500, rate_hz=10).store
    lfpiv.reconstruct(run, iterations=50)
    lfpiv.correlate(run)
    print(lfpiv.evaluate(run).vectors.divergence_mean)
    lfpiv.particles(run)                                   # every frame's particles (IPR)
    lfpiv.track(run)                                       # paired A to B, binned into vectors/
    lfpiv.export(run, "netcdf", "field")
    looks = lfpiv.views(run, depths_mm=[-2, 0, 2])        # perspective views, refocused planes
    checks, notes = lfpiv.check_camera(rig)                # seeding, saturation, fill per camera

A run is given as a path or as the store :func:`open_run` returns. Errors are the commands':
:class:`lfpiv.errors.UsageError` for bad input (one line naming the problem and the fix),
:class:`lfcore.errors.DeviceError` for a device fault.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lfcore.rig import Rig
from lfcore.runstore import RunStore
from lfpiv.errors import UsageError
from lfpiv.rigfile import load_rig

__all__ = ["Evaluation", "check_camera", "correlate", "evaluate", "export", "import_files", "load_rig", "open_run",
           "particles", "reconstruct", "track", "views"]

PairsLike = slice | int | str | None


def open_run(path: str | os.PathLike[str] | RunStore, *, mode: str = "r") -> RunStore:
    """The run store at ``path`` (``mode="r+"`` to add volumes or vectors); a store given is
    returned as it is to read, opened again to write."""
    if isinstance(path, RunStore):
        return path if mode == "r" else RunStore.open(path.path, mode=mode)
    return RunStore.open(path, mode=mode)


def _pairs(pairs: PairsLike) -> slice | None:
    """A pair selection: None (all), a pair index, ``"START:STOP"`` or a slice."""
    if pairs is None or isinstance(pairs, slice):
        return pairs
    if isinstance(pairs, int):
        return slice(pairs, pairs + 1)
    from lfpiv.commands import pair_range

    try:
        return pair_range(str(pairs))
    except Exception as exc:  # argparse's ArgumentTypeError: say it as the API's error
        raise UsageError(f"pairs: {exc}") from None


def _rig(rig: Rig | str | os.PathLike[str]) -> Rig:
    return rig if isinstance(rig, Rig) else load_rig(rig)


def import_files(rig: Rig | str | os.PathLike[str], out: str | os.PathLike[str], *, frames: Mapping[str, str],
                 frames_b: Mapping[str, str] | None = None, davis: Mapping[str, str] | None = None,
                 layout: str = "interleaved", dt_us: float | None = None, rate_hz: float | None = None,
                 overwrite: bool = False, skip_done: bool = False, progress: bool = True,
                 checksum: str = "crc32c") -> Any:
    """A run store made from image files recorded elsewhere (``lfpiv import``).

    Parameters are :func:`lfpiv.jobs.import_.import_files`' (``rig`` may be a rig file's path);
    returns its :class:`~lfpiv.jobs.import_.ImportResult` (``.store`` is the run).
    """
    from lfpiv.jobs.import_ import import_files as job

    return job(_rig(rig), out, frames=frames, frames_b=frames_b, davis=davis, layout=layout, dt_us=dt_us,
               rate_hz=rate_hz, overwrite=overwrite, skip_done=skip_done, progress=progress, checksum=checksum)


def reconstruct(run: str | os.PathLike[str] | RunStore, *, method: str | None = None, iterations: int | None = None,
                relaxation: float | None = None, form: str = "simultaneous", pvr: Sequence[float] | None = None,
                margin_mm: Sequence[float] = (0.0, 0.0, 0.0), pairs: PairsLike = None,
                cameras: Sequence[str] | None = None, calibration: str | os.PathLike[str] | None = None,
                device: str | None = None, workers: int | None = None, scheduler: str | None = None,
                skip_done: bool = False, progress: bool = True, slabs: int | str | None = None,
                flat_field: str | os.PathLike[str] | None = None, protocol: str | None = None,
                **options: Any) -> list[Any]:
    """Reconstruct both frames of the selected pairs into the run's ``volumes/`` (``lfpiv reconstruct``).

    Parameters
    ----------
    run
        The run (a path or a store).
    method, iterations, relaxation, form
        DRT-MART, MART, MLOS-MART or MLOS-SMART (None: DRT-MART for light-field cameras, MLOS-MART
        under ``protocol="fast"`` on several light-field cameras (its plan for them,
        :data:`lfcore.reconstruct.SEVERAL_LIGHT_FIELD_CAMERAS`), MLOS-SMART for pinhole ones); MART
        sweeps, a fixed count (None: 50, or the protocol's);
        relaxation (None: 1, or the protocol's: 2 in ``fast``'s plan for several light-field cameras);
        simultaneous or sequential.
    pvr, margin_mm
        Pixel-voxel ratio (x, y, z) of the voxel grid (None: the rig's) and the margin around
        the rig's volume, mm.
    pairs
        None (every recorded pair), a pair index, ``"START:STOP"`` or a slice.
    cameras
        Camera names to reconstruct from (None: all).
    calibration
        A calibration store whose fitted camera models replace the run's rig.
    device, workers, scheduler, skip_done
        As the command's ``--device``, ``--workers``, ``--scheduler``, ``--skip-done``.
    progress
        A progress bar on stderr.
    slabs
        As the command's ``--slabs``: a number of depth slabs, ``"auto"`` (in slabs only where the
        box does not fit the memory) or None (in memory).
    flat_field
        As the command's ``--flat-field``: a calibration store whose dark and white images correct
        every raw frame (None: the raw frames).
    protocol
        As the command's ``--protocol``: a named protocol (:data:`lfcore.reconstruct.PROTOCOLS`:
        ``"fast"``, ``"fixed"``, ``"chapter"``) that the other options change; None: the settings
        as given (:class:`lfcore.reconstruct.ReconSettings`' defaults, 50 iterations).
    **options
        Further :class:`lfcore.reconstruct.ReconSettings` fields (``background``,
        ``threshold_sigma``, ``smooth``, ``sub_apertures``, ``weight_storage``, ...). One given as None
        is that field's None, not the protocol's value (``lit_hysteresis=None``: no hysteresis, where
        ``fast``'s plan for several light-field cameras has 0.5).

    Returns
    -------
    list of lfcore.reconstruct.ReconResult
        One per frame reconstructed (the volumes are in the store).
    """
    from lfpiv.batch import dask_client
    from lfpiv.jobs.calibrate import calibrated_rig, flat_fields
    from lfpiv.jobs.reconstruct import (
        camera_count,
        cameras_kind,
        default_method,
        protocol_run_settings,
        recon_settings,
        reconstruct_run,
        run_method,
    )

    store = open_run(run, mode="r+")
    if protocol is None:
        settings = recon_settings(method=method or default_method(store.rig, cameras),
                                  iterations=50 if iterations is None else iterations,
                                  relaxation=1.0 if relaxation is None else relaxation, form=form, **options)
    else:
        # light-field cameras leave the method to the protocol's plan (fast on several: MLOS-MART)
        settings = protocol_run_settings(protocol, iterations=iterations, method=run_method(store.rig, cameras, method),
                                         relaxation=relaxation, form=form, n_cameras=camera_count(store.rig, cameras),
                                         camera_kind=cameras_kind(store.rig, cameras),
                                         none_given=[k for k, v in options.items() if v is None], **options)
    rig, cal = calibrated_rig(store.rig, calibration, cameras) if calibration is not None else (None, None)
    flats, flat_info = (flat_fields(store.rig, flat_field, cameras)[:2] if flat_field is not None
                        else (None, None))
    with dask_client(workers, scheduler) as client:
        return reconstruct_run(store, settings, pvr=pvr, margin_mm=margin_mm, pairs=_pairs(pairs), cameras=cameras,
                               device=device, progress=progress, rig=rig, calibration=cal, skip_done=skip_done,
                               client=client, option="pairs", slabs=slabs, flats=flats, flat_field=flat_info,
                               protocol=protocol)


def correlate(run: str | os.PathLike[str] | RunStore, *,
              windows: Sequence[Sequence[int]] | None = None, overlap: float | Sequence[float] = 0.75,
              deform_passes: int = 2, pairs: PairsLike = None, device: str | None = None, workers: int | None = None,
              scheduler: str | None = None, skip_done: bool = False, progress: bool = True,
              slabs: int | str | None = None, **options: Any) -> Any:
    """3D multi-grid cross-correlation of the run's volumes into ``vectors/`` (``lfpiv correlate``).

    Parameters
    ----------
    run
        The run, with volumes.
    windows
        (x, y, z) voxels of each pass, largest first (None: two passes that fit the volume,
        :func:`lfpiv.jobs.correlate.fitting_windows`).
    overlap
        Overlap of neighbouring windows, one fraction or (x, y, z).
    deform_passes
        Passes with volume deformation at the final window size.
    pairs
        None (every reconstructed pair), a pair index, ``"START:STOP"`` or a slice.
    device, workers, scheduler, skip_done, progress
        As :func:`reconstruct`.
    slabs
        As the command's ``--slabs``: a number of depth slabs, each read from the store with the
        halo its passes need (the in-memory vectors), ``"auto"`` (in slabs only where the pair does
        not fit in memory) or None (in memory).
    **options
        Further options of :func:`lfpiv.jobs.correlate.correlation_config` (``zero_pad``,
        ``median_filter``, ``epsilon``, ``threshold``, ``interpolation``, ``search_radius``, ...).

    Returns
    -------
    lfpiv.jobs.correlate.CorrelationRun
        The pairs correlated, the vector grid, the outliers, the time taken.
    """
    from lfpiv.batch import dask_client
    from lfpiv.jobs.correlate import correlate_run, correlation_config, fitting_windows, pairs_to_correlate

    store = open_run(run, mode="r+")
    chosen = pairs_to_correlate(store, _pairs(pairs), option="pairs")
    wins = tuple(tuple(int(v) for v in w) for w in windows) if windows is not None else \
        fitting_windows(store.volume_grid().shape)
    ov = (float(overlap),) * 3 if isinstance(overlap, int | float) else tuple(float(v) for v in overlap)
    cfg = correlation_config(windows=wins, overlap=ov, deform_iterations=deform_passes, **options)  # type: ignore[arg-type]
    with dask_client(workers, scheduler) as client:
        return correlate_run(store, cfg, chosen, device=device, progress=progress, skip_done=skip_done, client=client,
                             slabs=slabs)


def particles(run: str | os.PathLike[str] | RunStore, *, pairs: PairsLike = None, cameras: Sequence[str] | None = None,
              device: str | None = None, workers: int | None = None, scheduler: str | None = None,
              skip_done: bool = False, progress: bool = True,
              along_pairs: bool | str | dict[str, Any] | None = "auto",
              flat_field: str | os.PathLike[str] | None = None, **options: Any) -> Any:
    """Reconstruct every frame's particles of the selected pairs into the run's ``particles/`` by
    iterative particle reconstruction (``lfpiv particles``).

    Parameters
    ----------
    run
        The run (a path or a store).
    pairs
        None (every recorded pair), a pair index, ``"START:STOP"`` or a slice.
    cameras
        Camera names to use (None: all).
    device, workers, scheduler, skip_done, progress
        As the command's ``--device``, ``--workers``, ``--scheduler``, ``--skip-done`` and its progress bar.
    along_pairs
        A time-resolved run's frames in time order, each predicted by the tracks through the frames
        before it (``lfpiv particles --along-pairs``): True with the defaults, or a dict of
        :class:`lfpiv.jobs.particles.AlongPairs` fields (``search_voxels``, ``link_voxels``); False
        or None: every frame on its own; ``"auto"`` (the default, as the command's): along the pairs
        where the run is time-resolved, the pairs consecutive (two or more) and no workers given,
        else every frame on its own (:func:`lfpiv.pair_runner.along_pairs_choice`; the result's
        ``along`` says which ran and why).
    flat_field
        As the command's ``--flat-field``: a calibration store whose dark and white images correct
        every raw frame before its particles are fitted (None: the raw frames).
    **options
        :class:`lfcore.ipr.IprSettings` fields (``method``, ``candidate_iterations``, ``shakes``,
        ``min_intensity``, ``merge_voxels``, ``rounds``, ...). ``noise_model`` and ``residual_mask``
        take ``"auto"`` too, their default, as the command does: chosen from the cameras used
        (:func:`lfpiv.jobs.particles.fit_defaults`; ``"shot"`` and 3 where a light-field camera is
        among them, ``"flat"`` and 0 for pinhole cameras alone).

    Returns
    -------
    lfpiv.jobs.particles.ParticlesDone
        The pairs done, particles and candidates per frame, seconds per frame.
    """
    from lfpiv.batch import dask_client
    from lfpiv.jobs.particles import (
        AlongPairs,
        check_along_workers,
        fit_defaults,
        intensity_axis,
        ipr_settings,
        particles_run,
        used_cameras,
    )

    along, mode = None, _along_mode(along_pairs)
    if mode != "off":
        given = along_pairs if isinstance(along_pairs, dict) else {}
        try:
            along = AlongPairs(**{k: tuple(v) for k, v in given.items()})
        except TypeError as exc:
            raise UsageError(f"along_pairs takes search_voxels and link_voxels: {exc}") from None
    if mode == "on":
        check_along_workers(workers, scheduler)  # before any worker starts
    store = open_run(run, mode="r+")
    # as the command: the point model's diffraction blur and spot size, and the axis along which the
    # faint are judged (the laser sheet's, where it lights the box unevenly), are the rig's unless given;
    # the fit's weights and residual mask, unless given (or given as "auto"), the cameras' (fit_defaults)
    fit = fit_defaults(used_cameras(store.rig, cameras), noise_model=options.pop("noise_model", "auto"),
                       residual_mask=options.pop("residual_mask", "auto"))
    options = {"wavelength_nm": store.rig.laser.wavelength_nm,
               "particle_image_px": store.rig.render.particle_image_px,
               "intensity_axis": intensity_axis(store.rig), **fit, **options}
    settings = ipr_settings(**options)
    flats, flat_info = None, None
    if flat_field is not None:
        from lfpiv.jobs.calibrate import flat_fields

        flats, flat_info = flat_fields(store.rig, flat_field, cameras)[:2]
    with dask_client(workers, scheduler) as client:
        return particles_run(store, settings, _pairs(pairs), cameras=cameras, device=device, progress=progress,
                             skip_done=skip_done, option="pairs", client=client, along_pairs=along,
                             along_mode=mode, flats=flats, flat_field=flat_info)


def track(run: str | os.PathLike[str] | RunStore, *, pairs: PairsLike = None, skip_done: bool = False,
          progress: bool = True, predictor: str = "none", device: str | None = None,
          along_pairs: bool | str | dict[str, Any] | None = "auto", **options: Any) -> Any:
    """Pair each selected pair's particles from frame A to frame B and bin the tracks into the run's
    ``vectors/`` (``lfpiv track``); ``predictor`` is the first pass's (``"none"``, ``"volumes"`` or
    ``"previous"``: :mod:`lfpiv.jobs.track`), ``options`` are :class:`lfcore.track.TrackSettings`
    fields (``search_voxels``, ``refine_voxels``, ``passes``, ``bin_voxels``, ``min_tracks``,
    ``field``, ``smooth_voxels``, ...). ``along_pairs`` (a time-resolved run: ``lfpiv track
    --along-pairs``) follows the particles through every frame: True with the defaults, or a dict of
    :class:`lfcore.track.SeriesSettings` fields (``link_voxels``, ``min_frames``, ``fit_frames``,
    ``degree``, ``pool_pairs``, ``bridge_frames``, ``relink``; those not given are the command's
    defaults along the pairs, :data:`lfpiv.jobs.track.ALONG_DEFAULTS`, and the field, where ``field``
    is not given, :data:`lfpiv.jobs.track.ALONG_FIELD`); False or None: pair by pair;
    ``"auto"`` (the default, as the command's): along the pairs where the run allows it
    (:func:`lfpiv.pair_runner.along_pairs_choice`), else pair by pair. Returns the
    :class:`lfpiv.jobs.track.TracksDone` figures (``along``: which ran and why)."""
    from lfpiv.jobs.track import along_defaults, series_settings, track_run, track_settings

    mode = _along_mode(along_pairs)
    settings = track_settings(**options)
    series = None
    if mode != "off":  # what is not given is the command's default along the pairs (along_defaults)
        series = series_settings(**along_defaults(options.get("field"),
                                                  **(along_pairs if isinstance(along_pairs, dict) else {})))
    store = open_run(run, mode="r+")
    return track_run(store, settings, _pairs(pairs), predictor=predictor, progress=progress,
                     skip_done=skip_done, option="pairs", device=device, along_pairs=series, along_mode=mode,
                     field_given="field" in options)


def _along_mode(along_pairs: bool | str | dict[str, Any] | None) -> str:
    """:data:`lfpiv.pair_runner.ALONG_PAIRS_MODES` of the API's ``along_pairs``: ``"auto"`` as it is,
    False and None ``"off"``, True and a dict of settings ``"on"``."""
    if isinstance(along_pairs, str):
        from lfpiv.pair_runner import ALONG_PAIRS_MODES

        if along_pairs not in ALONG_PAIRS_MODES:
            raise UsageError(f"along_pairs is True, False, a dict of settings or one of "
                             f"{', '.join(ALONG_PAIRS_MODES)}, got '{along_pairs}'")
        return along_pairs
    return "off" if along_pairs is False or along_pairs is None else "on"


@dataclass(frozen=True)
class Evaluation:
    """What :func:`evaluate` found.

    Attributes
    ----------
    volumes
        Per reconstructed frame, its quality against the truth
        (:class:`lfpiv.jobs.evaluate.FrameEvaluation`); None without volumes or without truth.
    vectors
        The vectors' figures (:class:`lfpiv.jobs.evaluate.VectorEvaluation`: velocity error
        against the truth where there is one, outliers, divergence error); None without vectors.
    particles
        Per frame with particles, recall, ghosts and position error per axis against the truth
        (:class:`lfpiv.jobs.evaluate.ParticleEvaluation`, matching within ``particle_match_voxels``);
        None without particles or without truth.
    """

    volumes: list[Any] | None
    vectors: Any
    particles: list[Any] | None = None


def evaluate(run: str | os.PathLike[str] | RunStore, *, pairs: PairsLike = None, threshold: float = 0.1,
             match_voxels: float = 2.0, particle_match_voxels: float = 1.0) -> Evaluation:
    """The run's volumes, particles and vectors against its truth (``lfpiv evaluate``); a recorded or
    imported run has no truth, and only the vectors' outliers and divergence error are measured."""
    from lfpiv.jobs.evaluate import evaluate_particles, evaluate_run, evaluate_vector_fields

    store = open_run(run)
    sel = _pairs(pairs)
    vols = None
    if store.has_volumes and store.truth() is not None:
        vols = evaluate_run(store, sel, threshold, match_voxels, option="pairs")
    parts = None
    if store.has_particles and store.truth() is not None:
        parts = evaluate_particles(store, sel, particle_match_voxels, option="pairs")
    vec = evaluate_vector_fields(store, sel, option="pairs")
    return Evaluation(volumes=vols, vectors=None if isinstance(vec, str) else vec, particles=parts)


def export(run: str | os.PathLike[str] | RunStore, fmt: str, out: str | os.PathLike[str], *,
           overwrite: bool = False) -> list[Path]:
    """Write the run's vector fields for other tools (``lfpiv export``): ``fmt`` is ``"netcdf"``,
    ``"vtk"``, ``"tecplot"``, ``"davis"`` or ``"mat"`` (:mod:`lfpiv.jobs.export`); returns the files."""
    from lfpiv.jobs.export import export_run

    return export_run(open_run(run), fmt, out, overwrite=overwrite)


def views(run: str | os.PathLike[str] | RunStore | None = None, *, pair: int = 0, frame: str = "A",
          image: str | os.PathLike[str] | Any = None, calibration: str | os.PathLike[str] | None = None,
          rig: Rig | str | os.PathLike[str] | None = None, camera: str | None = None,
          depths_mm: Sequence[float] | None = None, upsample: int = 1, out: str | os.PathLike[str] | None = None,
          fmt: str = "png", every_view: bool = True) -> Any:
    """The perspective views and refocused planes of a raw light-field frame (``lfpiv views``).

    The frame is a run's (``run``, ``pair``, ``frame`` "A" or "B", ``camera``) or ``image``: a raw
    image file, or a (rows, columns) array, of a camera of the ``calibration`` store's rig (its
    fitted microlens grid is used) or of ``rig`` (its nominal one). ``depths_mm`` are z in the
    rig's frame (default: 5 planes through the volume). With ``out`` the pictures and the figure
    are written there. Returns a :class:`lfpiv.jobs.views.ViewsResult` (``.views.images`` the views,
    ``.planes`` the refocused planes, ``.mosaic``, ``.centre_view``).
    """
    from lfpiv.jobs.views import views as job

    if isinstance(run, RunStore):
        run = run.path
    return job(run=run, pair=pair, frame=frame, image=image, calibration=calibration,
               rig=None if rig is None else _rig(rig), camera=camera, depths_mm=depths_mm, upsample=upsample,
               out=out, fmt=fmt, every_view=every_view)


def check_camera(rig: Rig | str | os.PathLike[str], *, frames: Mapping[str, Any] | None = None,
                 run: str | os.PathLike[str] | RunStore | None = None, pair: int = 0,
                 images: Mapping[str, str | os.PathLike[str]] | None = None,
                 calibration: str | os.PathLike[str] | None = None, cameras: Sequence[str] | None = None,
                 plot: str | os.PathLike[str] | None = None, sim_options: Mapping[str, Any] | None = None
                 ) -> tuple[list[Any], list[str]]:
    """The checks before recording (``lfpiv check-camera``): per camera, the seeding density
    (PPM or PPP), the saturated share, the micro-image fill, the histogram and a refocused plane,
    with :meth:`lfcore.camera_checks.CameraCheck.verdicts` against the chapter's ranges.

    The frames are ``frames`` (camera name -> array), a ``run``'s pair, image files, or (none of
    them) one pair grabbed from the rig now, the laser firing once (the simulated lab with
    ``hardware = "sim"``; ``sim_options`` as :func:`lfpiv.rigging.sim_lab_options` gives them).
    Returns (the checks, notes).
    """
    from lfpiv.jobs.check_camera import check_cameras, check_frames

    the_rig = _rig(rig)
    if frames is not None:
        checks, notes = check_frames(the_rig, frames, calibration=calibration)
        if plot is not None:
            from lfpiv.plots import plot_camera_checks

            plot_camera_checks(checks, plot)
        return checks, notes
    if isinstance(run, RunStore):
        run = run.path
    return check_cameras(the_rig, run=run, pair=pair, images=images, calibration=calibration,
                         sim_options=None if sim_options is None else dict(sim_options),
                         cameras=None if cameras is None else list(cameras), out=plot)
