"""Replacing derived data whole: ``volumes.pending/`` and ``vectors.pending/``, made beside the
current ``volumes/`` or ``vectors/`` and put in their place only once complete."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import zarr

from lfcore.runstore._common import Part, RunStoreError
from lfcore.runstore._schema import validated


class Replacement(Part):
    """Where ``volumes/`` and ``vectors/`` are written, and how a new set replaces the old.

    A new set of volumes or vectors made while the run holds some is written into
    ``<name>.pending/``; readers see the old ``<name>/`` whole until :meth:`finish` renames the
    new one into place, and :meth:`recover` settles a replacement killed half-way through that.
    """

    #: Suffix of the group where a replacement of ``volumes/`` or ``vectors/`` is made.
    PENDING = ".pending"

    #: The attribute of ``volumes/`` and ``vectors/`` that lists the pairs written so far.
    DONE = {"volumes": "reconstructed_pairs", "vectors": "correlated_pairs", "particles": "particle_pairs"}

    def _begin(self, name: str, *, staged: bool) -> zarr.Group:
        """A new, empty group where ``name`` (``volumes`` or ``vectors``) is made from now on:
        ``name`` itself, or with ``staged`` its pending replacement, which leaves ``name`` whole
        until :meth:`finish`."""
        pending = name + self.PENDING
        if pending in self.group:  # an earlier replacement, interrupted, and now superseded
            del self.group[pending]
        key = pending if staged else name
        if key in self.group:
            del self.group[key]
        self._target[name] = key
        return self.group.create_group(key)

    def pending(self, name: str) -> zarr.Group | None:
        """The unfinished replacement of ``name`` (``volumes`` or ``vectors``) that an interrupted
        run left, or None."""
        key = name + self.PENDING
        return self.group[key] if key in self.group else None

    def resume(self, name: str) -> zarr.Group:
        """Write ``name`` into its pending replacement again (a replacement resumed), and return it."""
        g = self.pending(name)
        if g is None:
            raise RunStoreError(f"{self.path} has no {name}{self.PENDING}/ to resume")
        self._target[name] = g.basename
        return g

    def writing(self, name: str) -> zarr.Group:
        """The group that writes of ``name`` (``volumes`` or ``vectors``) go to: ``name`` itself,
        or the pending replacement that :meth:`create_volumes`, :meth:`create_vectors` or
        :meth:`resume` chose."""
        key = self._target[name]
        if key not in self.group:
            raise RunStoreError(f"{self.path} has no {key}/ group; create it first")
        return self.group[key]

    def plan(self, name: str, pairs: list[int]) -> None:
        """Add ``pairs`` to those the pending replacement of ``name`` being written must hold
        before :meth:`finish` puts it in place (nothing to do when ``name`` itself is written):
        a replacement resumed for a few pairs does not drop the old set's others unasked."""
        g = self.writing(name)
        if g.basename != name:
            planned = validated(self.path, g.basename, g.attrs, "planned_pairs")
            g.attrs["planned_pairs"] = sorted(set(planned) | {int(p) for p in pairs})

    def unfinished(self, name: str) -> list[int]:
        """The planned pairs (:meth:`plan`) that the pending replacement of ``name`` being
        written still lacks; [] when it is complete or ``name`` itself is written."""
        g = self.writing(name)
        if g.basename == name:
            return []
        return sorted(set(validated(self.path, g.basename, g.attrs, "planned_pairs")) - set(self.done_pairs(name, g)))

    def done_pairs(self, name: str, group: zarr.Group | None) -> list[int]:
        """The pairs ``group`` (``name``, ``volumes`` or ``vectors``, or its pending replacement;
        None: none) lists as done, checked (:mod:`lfcore.runstore._schema`); [] for a group that
        lists none yet (made, no pair written).

        Raises
        ------
        RunStoreError
            If the list is not a list of pair numbers, one line naming it.
        """
        if group is None or self.DONE[name] not in group.attrs:
            return []
        return list(validated(self.path, group.basename, group.attrs, self.DONE[name]))

    def finish(self, name: str) -> bool:
        """Put the pending replacement of ``name`` being written in place of ``name`` once it
        holds every planned pair (:meth:`plan`): two directory renames, then the old set is
        deleted. Returns True when it replaced ``name``.

        Until then readers see the old ``name`` whole. A kill between the renames, or while the
        old set is deleted, leaves ``<name>.replaced/``, which :meth:`recover` settles.
        """
        key = self._target[name]
        if key == name or self.unfinished(name):
            return False
        root = Path(self.path)
        old = root / f"{name}.replaced"
        self._clear_replaced(name)
        if (root / name).exists():
            os.replace(root / name, old)
        os.replace(root / key, root / name)
        self._target[name] = name
        shutil.rmtree(old, ignore_errors=True)  # what stays (read-only folders) the next replacement names
        return True

    def _clear_replaced(self, name: str) -> None:
        """Delete ``<name>.replaced/``, the old set an earlier replacement put aside and could not
        delete (read-only folders, a kill); a one-line error naming what stays if it cannot be."""
        old = Path(self.path) / f"{name}.replaced"
        if not os.path.lexists(old):
            return
        why: list[str] = []
        if old.is_dir() and not old.is_symlink():
            def note(_func: object, path: str, info: tuple) -> None:
                why.append(f"{getattr(info[1], 'strerror', None) or info[1]}: {path}")

            kw = {"onexc": lambda f, p, e: note(f, p, (type(e), e, None))} if sys.version_info >= (3, 12) else \
                {"onerror": note}
            shutil.rmtree(old, **kw)
        else:
            try:
                old.unlink()
            except OSError as exc:
                why.append(f"{exc.strerror or exc}: {old}")
        if os.path.lexists(old):
            raise RunStoreError(f"{old}, the old {name} an earlier replacement put aside, cannot be deleted "
                                f"({why[0] if why else 'it came back'}); delete it (chmod -R u+w first if it is "
                                "read-only), then run the command again")

    def check_replaceable(self, name: str) -> None:
        """Before a replacement of ``name`` (``volumes`` or ``vectors``) is computed: settle the old
        set an earlier one left (``<name>.replaced/``) and check that the current ``name/`` can be
        moved aside and deleted once the new set is complete, so that nothing is computed for a
        replacement that cannot be put in place.

        Raises
        ------
        RunStoreError
            ``<name>.replaced/`` cannot be deleted, or ``name/`` or a folder in it is read-only
            (one line, naming it and the fix).
        """
        self._clear_replaced(name)
        cur = Path(self.path) / name
        if not cur.is_dir():
            return
        for folder, _dirs, _files in os.walk(cur):
            if not os.access(folder, os.W_OK | os.X_OK):
                raise RunStoreError(f"{cur} cannot be replaced: {folder} is read-only, so the old {name} could not "
                                    f"be deleted once the new ones are made; make it writable (chmod -R u+w {cur}), "
                                    f"or delete {cur} if the old {name} may go")

    def replaced_left(self, name: str) -> bool:
        """Whether ``<name>.replaced/`` is left by a replacement killed in :meth:`finish`."""
        return (Path(self.path) / f"{name}.replaced").exists()

    def recover(self) -> list[str]:
        """Settle replacements killed in :meth:`finish`: one killed between its renames is
        completed (its pending set was complete), and the old set's folder left by one killed
        while deleting it is deleted. Returns what was done, one line each."""
        root, done = Path(self.path), []
        for name in self._target:
            cur, pending, old = root / name, root / (name + self.PENDING), root / f"{name}.replaced"
            if not old.exists():
                continue
            if not cur.exists():
                os.replace(pending if pending.exists() else old, cur)
                done.append(f"completed the replacement of {name}/ that was interrupted as it was put in place")
            shutil.rmtree(old, ignore_errors=True)
        return done
