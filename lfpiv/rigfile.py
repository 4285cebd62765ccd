"""Reading rig files (TOML) into validated :class:`lfcore.rig.Rig` objects."""

from __future__ import annotations

import tomllib
from pathlib import Path

from lfcore.rig import Rig, RigError

__all__ = ["load_rig"]


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig file.

    Raises
    ------
    lfcore.rig.RigError
        One line naming the file and the problem: a missing file, a TOML syntax error with its
        line, an unknown key or an impossible value with its key.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Windows editors) is not TOML
    except UnicodeDecodeError as exc:
        raise RigError(f"rig file {path} is not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except FileNotFoundError:
        raise RigError(f"rig file {path} not found; pass the path of a rig TOML file (see examples/)") from None
    except OSError as exc:
        raise RigError(f"rig file {path} cannot be read: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RigError(f"{path}: invalid TOML: {exc}") from None
    return Rig.from_dict(data, source=str(path))
