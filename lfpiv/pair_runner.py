"""The one per-pair runner behind ``reconstruct`` and ``correlate``.

Both make derived data (``volumes/`` or ``vectors/``) pair by pair in the same sequence:

1. **begin**: choose where the pairs are written (:func:`lfpiv.replacement.begin`): into the
   current set when it was made with the same settings, into an interrupted replacement made with
   them, or into a new set made beside the old one;
2. **skip done**: with ``--skip-done``, leave out the pairs that set already holds;
3. **map**: do each pair, in this process or on Dask workers (:func:`lfpiv.batch.map_pairs`),
   recording each as it finishes (only this process records which pairs are done);
4. **finish**: put a complete replacement in place (:func:`lfpiv.replacement.end`); an
   interrupted or failed one says how it is left.

The job supplies what differs: how to compare and create the set, how to do pairs here, and
the worker task with its (picklable) job description.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from lfcore.plan import SLAB_SHARE, PlanError, asked_slabs
from lfcore.runstore import RunStore, RunStoreError
from lfpiv import replacement
from lfpiv.errors import UsageError, naming

__all__ = ["ALONG_PAIRS_MODES", "SLAB_SHARE", "WORKERS_GIVEN", "AlongChoice", "along_option_error",
           "along_pairs_choice", "particle_pairs", "recorded_pairs", "run_pairs", "select_pairs", "slabs_asked"]

T = TypeVar("T")
log = logging.getLogger(__name__)

#: What ``lfpiv particles`` and ``lfpiv track`` take for following a time-resolved run's particles
#: along its pairs (:func:`along_pairs_choice`): ``"auto"`` (the default, no option), ``"on"``
#: (``--along-pairs``), ``"off"`` (``--pair-by-pair``).
ALONG_PAIRS_MODES = ("auto", "on", "off")

#: Why ``"auto"`` goes pair by pair with workers (:func:`along_pairs_choice`).
WORKERS_GIVEN = "--workers or --scheduler given (along the pairs runs frame after frame, in this process)"


@dataclass(frozen=True)
class AlongChoice:
    """Whether a command follows the particles along the pairs (:func:`along_pairs_choice`).

    Attributes
    ----------
    on
        Along the pairs (True) or pair by pair.
    why
        Why, for the command's one line: e.g. ``"a time-resolved run, pairs 0 to 4"``.
    """

    on: bool
    why: str

    def line(self) -> str:
        """The command's line saying which and why."""
        return f"{'along the pairs' if self.on else 'pair by pair'}: {self.why}"


def along_pairs_choice(mode: str, *, time_resolved: bool, pairs: Sequence[int], workers: bool = False,
                       min_frames: int = 3, previous: bool = False) -> AlongChoice:
    """Whether ``lfpiv particles`` or ``lfpiv track`` follows the particles along the pairs.

    ``"on"`` (``--along-pairs``) is along the pairs (the job refuses what cannot be, with one line);
    ``"off"`` (``--pair-by-pair``) pair by pair; ``"auto"`` (no option) along the pairs where the run
    is time-resolved (:func:`lfcore.runstore.is_time_resolved`), the chosen pairs are consecutive and
    hold ``min_frames`` frames or more, no workers are asked and no ``--predictor previous``, else
    pair by pair, never an error. The same inputs give the same choice, so what ran is recorded and
    ``--skip-done`` finds it again.

    Parameters
    ----------
    mode
        One of :data:`ALONG_PAIRS_MODES`.
    time_resolved
        The run is a time-resolved series (every frame ``dt`` after the one before).
    pairs
        The chosen pairs, in order.
    workers
        ``--workers`` or ``--scheduler`` given (the frames are done in time order, in one process).
    min_frames
        Fewest frames along which following pays: 3 for ``particles`` (a prediction needs two frames
        before), the tracks' ``--min-frames`` for ``track``.
    previous
        ``track --predictor previous`` (each pair predicted by the one before: pair by pair).

    Returns
    -------
    AlongChoice

    Raises
    ------
    UsageError
        A mode not in :data:`ALONG_PAIRS_MODES`.
    """
    if mode not in ALONG_PAIRS_MODES:
        raise UsageError(f"along the pairs is one of {', '.join(ALONG_PAIRS_MODES)}, got '{mode}'")
    chosen = list(pairs)
    span = f"pairs {chosen[0]} to {chosen[-1]}" if chosen else "no pairs"
    if mode == "on":
        return AlongChoice(True, f"asked (--along-pairs), {span}")
    if mode == "off":
        return AlongChoice(False, "asked (--pair-by-pair)")
    if not time_resolved:
        return AlongChoice(False, "not a time-resolved run (every frame dt after the one before)")
    if workers:
        return AlongChoice(False, WORKERS_GIVEN)
    if previous:
        return AlongChoice(False, "--predictor previous predicts each pair from the one before")
    if not chosen or chosen != list(range(chosen[0], chosen[-1] + 1)):
        return AlongChoice(False, "the chosen pairs are not consecutive")
    if 2 * len(chosen) < min_frames:
        return AlongChoice(False, f"{2 * len(chosen)} frame(s) chosen, fewer than the {min_frames} that tracks "
                           "along the pairs need")
    return AlongChoice(True, f"a time-resolved run, {span} (--pair-by-pair to track each pair on its own)")


def slabs_asked(slabs: int | str | None, nz: int) -> int | None:
    """The depth slabs ``--slabs`` asks for over a box ``nz`` voxels deep: 1 for None (not given),
    None for ``"auto"`` (the job chooses from the memory free), else the number, checked
    (:func:`lfcore.plan.asked_slabs`).

    Raises
    ------
    UsageError
        Not a whole number, or not from 1 to ``nz``.
    """
    try:
        return asked_slabs(slabs, nz)
    except PlanError as exc:
        raise UsageError(str(exc)) from None


def run_pairs(store: RunStore, name: str, pairs: list[int], *, matches: Callable[[Any], bool],
              differences: Callable[[Any], list[str]], create: Callable[[], None], skip_done: bool,
              here: Callable[[list[int]], None],
              remote: Callable[[str], tuple[Callable[..., T], Any]] | None, client: Any,
              on_done: Callable[[int, T], None], desc: str, progress: bool,
              kept: Callable[[], str] = lambda: "",
              postfix: Callable[[int, T], dict[str, Any]] | None = None) -> list[int]:
    """Make ``name`` (``volumes`` or ``vectors``) of ``pairs``; returns the pairs done now.

    Parameters
    ----------
    store
        The run, open for writing.
    name
        ``"volumes"`` or ``"vectors"``.
    pairs
        The pairs asked for.
    matches, differences, create
        As :func:`lfpiv.replacement.begin`: whether a group holds data of these settings, the
        settings in which it differs, and how to create a new set.
    skip_done
        Leave out the pairs the set being written already holds.
    here
        ``here(pairs)`` does the pairs in this process and records each as it is written.
    remote
        ``remote(into)`` gives the worker task and its job for the group ``into`` (``name`` or its
        pending replacement), when ``client`` is a Dask client.
    client
        A Dask client (:func:`lfpiv.batch.dask_client`), or None for this process.
    on_done
        ``on_done(pair, result)`` records a pair a worker finished (called in this process, in the
        order the pairs finish).
    desc, progress
        The progress bar of the workers' pairs.
    kept
        What a failure leaves of the pairs done before (e.g. "the 2 volume(s) written before are
        kept"), or "" for nothing to say.
    postfix
        ``postfix(pair, result)``: what the workers' progress bar shows of a pair just finished
        (its fields, as :meth:`tqdm.tqdm.set_postfix` takes them), or None for nothing.

    Raises
    ------
    UsageError
        A pair's error, with how an unfinished replacement, or what was done before, is left.
    """
    with naming(f"{store.path}/{name}"):
        replacement.begin(store, name, pairs, matches=matches, differences=differences, create=create)
    if skip_done:
        done = set(store.done_pairs(name, store.writing(name)))
        pairs = [p for p in pairs if p not in done]
    log.info("%s: %s of %d pair(s) into %s/%s", store.path, desc, len(pairs), store.path,
             store.writing(name).basename)
    if pairs:
        try:
            with replacement.noting_interrupt(store, name):
                if client is not None:
                    from lfpiv.batch import map_pairs

                    task, job = remote(store.writing(name).basename)  # type: ignore[misc]
                    map_pairs(client, task, job, pairs, on_done=on_done, desc=desc, progress=progress,
                              postfix=postfix)
                else:
                    here(pairs)
        except (UsageError, RunStoreError) as exc:  # RunStoreError: damaged input, named
            aside = replacement.kept_aside(store, name)
            before = "" if aside else kept()
            if aside or before:
                raise type(exc)(f"{exc}{aside or '; ' + before}") from None
            raise
        except OSError as exc:
            if exc.filename is None:  # a full disk under zarr's writes: say where it was writing
                raise OSError(exc.errno, exc.strerror or str(exc),
                              f"{store.path}/{store.writing(name).basename}") from None
            raise
    with naming(f"{store.path}/{store.writing(name).basename}"):
        replacement.end(store, name)
    return pairs


def recorded_pairs(store: RunStore, pairs: slice | None, cameras: Any, *, rig: Any = None,
                   option: str = "--pair-range") -> tuple[list[int], list[str]]:
    """The recorded pairs ``pairs`` selects (every committed pair where None: a run cut short has fewer
    than it planned) and the cameras (``cameras``, or all of ``rig``'s: the run's rig where None), for a
    command that processes a run's frames (``reconstruct``, ``particles``).

    Raises
    ------
    UsageError
        No committed pairs, a selected pair never recorded, or a camera the run does not have.
    """
    if store.committed_pairs == 0:
        raise UsageError(f"{store.path} has no recorded pairs (committed_pairs = 0); nothing to reconstruct")
    chosen = (select_pairs(pairs, store.n_pairs, option=option) if pairs is not None
              else list(range(store.committed_pairs)))
    late = [p for p in chosen if p >= store.committed_pairs]
    if late:
        raise UsageError(f"pair {late[0]} was never recorded (the run has {store.committed_pairs} committed "
                         f"pair(s)); choose {option} within 0:{store.committed_pairs}")
    names = list(cameras) if cameras else [c.name for c in (store.rig if rig is None else rig).camera]
    unknown = [n for n in names if n not in store.cameras]
    if unknown:
        raise UsageError(f"--cameras: no camera '{unknown[0]}' in this run (it has {', '.join(store.cameras)})")
    return chosen, names


def particle_pairs(store: RunStore, pairs: slice | None, *, option: str = "--pair-range"
                   ) -> tuple[dict[str, Any], list[int]]:
    """The ``particles/`` attributes and the pairs with particles that ``pairs`` selects (``evaluate``,
    ``track``).

    Raises
    ------
    UsageError
        A run without particles (or with damaged attributes), or none of the selected pairs with them.
    """
    try:
        attrs = store.particle_attrs()
    except RunStoreError as exc:
        raise UsageError(str(exc)) from None
    done = store.particle_pairs()
    chosen = [p for p in select_pairs(pairs, store.n_pairs, option=option) if p in done]
    if not chosen:
        raise UsageError(f"none of the selected pairs has particles (with particles: {done or 'none'}); "
                         f"run 'lfpiv particles {store.path}' first")
    return attrs, chosen


def select_pairs(pairs: slice | None, n_pairs: int, *, option: str = "--pair-range") -> list[int]:
    """The pair indices ``pairs`` (the ``--pair-range``, ``option`` in messages) selects of a run
    of ``n_pairs``.

    Raises
    ------
    UsageError
        A range that selects no pair.
    """
    if pairs is None:
        return list(range(n_pairs))
    chosen = list(range(n_pairs))[pairs]
    if not chosen:
        raise UsageError(f"{option} selects no pair of this run (it has pairs 0 to {n_pairs - 1}); give START:STOP "
                         "with START below STOP, e.g. 0:10")
    return chosen


def along_option_error(options: Sequence[str], choice: AlongChoice) -> str:
    """The one-line refusal of options that only apply along the pairs (``options``, as spelt) where
    ``choice`` (:func:`along_pairs_choice` of ``"auto"``) is pair by pair."""
    return (f"{', '.join(options)} only apply along the pairs of a time-resolved series, and this command goes pair "
            f"by pair ({choice.why}); leave them out, or give --along-pairs where the run allows it")
