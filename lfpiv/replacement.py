"""Replacing a run's derived data (``volumes/``, ``vectors/``) made with other settings, safely.

The new set is made beside the old one, in ``<name>.pending/``, and put in place only once it
holds every pair asked of it (:meth:`lfcore.runstore.RunStore.finish`): a Ctrl-C, a kill or a
failing worker leaves the old set whole, and the same settings with ``--skip-done`` go on.
These functions choose where a command writes and tell the user, one note each, what happens
to the old set.
"""

from __future__ import annotations

import shutil
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from lfcore.runstore import RunStore, RunStoreError

__all__ = ["begin", "end", "kept_aside", "noting_interrupt"]

#: The command that makes each kind of derived data.
_COMMAND = {"volumes": "reconstruct", "vectors": "correlate", "particles": "particles"}


def _note(text: str, level: str = "note") -> None:
    print(f"lfpiv: {level}: {text}", file=sys.stderr)


def _pairs(store: RunStore, group: Any, name: str, *, strict: bool = False) -> list[int]:
    """The pairs ``group`` lists as done, checked; for a note (not ``strict``), [] where the list
    is damaged (the command's own checks say so)."""
    try:
        return store.done_pairs(name, group)
    except RunStoreError:
        if strict:
            raise
        return []


def _some(pairs: list[int]) -> str:
    shown = ", ".join(str(p) for p in pairs[:6])
    return f"{len(pairs)} pair(s) ({shown}{' ...' if len(pairs) > 6 else ''})"


def begin(store: RunStore, name: str, pairs: list[int], *, matches: Callable[[Any], bool],
          differences: Callable[[Any], list[str]], create: Callable[[], None]) -> None:
    """Choose where ``name`` (``volumes`` or ``vectors``) of this command's ``pairs`` is written.

    Into the current set when ``matches`` it (same settings); into its pending replacement
    when that matches (an interrupted replacement goes on); else into a new set that
    ``create`` makes (beside the current one when that holds pairs). ``differences(group)``
    names the settings in which a group differs, for the note.
    """
    current = store.group[name] if name in store.group else None
    pending = store.pending(name)
    if matches(pending):
        store.check_replaceable(name)  # before anything is computed for a replacement that could not be put in place
        store.resume(name)
        left = store.unfinished(name)
        _note(f"going on with the interrupted replacement of {name}/ made with these settings "
              f"({len(_pairs(store, pending, name))} pair(s) done{f', {len(left)} more asked' if left else ''}); "
              f"{name}/ keeps the old ones until it is complete")
    elif not matches(current):
        if pending is not None:
            _note(f"an interrupted replacement of {name}/ made with other settings "
                  f"({', '.join(differences(pending)[:4]) or 'grid'} differ) is dropped, with its "
                  f"{len(_pairs(store, pending, name))} pair(s)")
        done = _pairs(store, current, name, strict=True)
        if done:
            store.check_replaceable(name)
            changed = differences(current) or ["grid"]
            _note(f"the {name} of {len(done)} pair(s) made with other settings ({', '.join(changed[:4])}"
                  f"{' ...' if len(changed) > 4 else ''} differ) are replaced once the new ones are complete"
                  + ("; vectors correlated from them will no longer match them" if name == "volumes" else ""))
            _warn_room(store, name)
        create()
    store.plan(name, pairs)


def _warn_room(store: RunStore, name: str) -> None:
    # both sets are on disk until the new one is complete
    held = sum(f.stat().st_size for f in (Path(store.path) / name).rglob("*") if f.is_file())
    free = shutil.disk_usage(store.path).free
    if free < held:
        _note(f"the new {name} are made beside the old ones, which take {held / 2**30:.2f} GiB, and only "
              f"{free / 2**30:.2f} GiB is free; free some space, or delete {store.path}/{name} first if the old "
              "ones may go", "warning")


def end(store: RunStore, name: str) -> None:
    """Put a complete replacement in place, or say what it still lacks (after a command that
    wrote every pair it was asked)."""
    try:
        replaced = store.finish(name)
    except KeyboardInterrupt:
        if store.writing(name).basename == name:  # in place: only the old set's deletion was cut short
            _note(f"the new {name} are in place; the folder of the old ones, {name}.replaced/, is partly deleted, "
                  f"and the next 'lfpiv {_COMMAND[name]}' of this run deletes the rest")
        raise
    left = store.unfinished(name)
    if left:
        _note(f"the replacement of {name}/ still lacks {_some(left)} asked of it before; {name}/ keeps the old "
              "ones until the same settings have done them (with --skip-done)")
    elif replaced:
        _note(f"{name}/ now holds the new {name} ({len(_pairs(store, store.group[name], name))} pair(s))")
    if replaced and store.replaced_left(name):
        _note(f"the old {name} could not all be deleted: what stays is in {store.path}/{name}.replaced/; delete it "
              f"(chmod -R u+w first if it is read-only) before the next replacement of {name}/", "warning")


def kept_aside(store: RunStore, name: str) -> str:
    """How an unfinished replacement is left, for a message ending an interrupted or failed
    command; "" when ``name`` itself was being written."""
    g = store.writing(name)
    if g.basename == name:
        return ""
    return (f"; the {len(_pairs(store, g, name))} pair(s) of new {name} are kept aside and the {name} made before with "
            f"other settings are unchanged; the same command with --skip-done goes on with the new ones")


@contextmanager
def noting_interrupt(store: RunStore, name: str) -> Iterator[None]:
    """Inside, a Ctrl-C that stops an unfinished replacement says how it is left (see
    :func:`kept_aside`) before it ends the command."""
    try:
        yield
    except KeyboardInterrupt:
        aside = kept_aside(store, name)
        if aside:
            _note(f"interrupted{aside}")
        raise
