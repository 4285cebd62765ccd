"""lfpiv: instrument software for light-field particle image velocimetry.

``import lfpiv`` gives the notebook-sized API of :mod:`lfpiv.api`: :func:`load_rig`,
:func:`open_run`, :func:`import_files`, :func:`reconstruct`, :func:`correlate`, :func:`evaluate`,
:func:`export`, :func:`views`, :func:`check_camera`, :func:`particles` and :func:`track`, the jobs
the ``lfpiv`` commands run. They are imported on first use, so ``import lfpiv`` stays cheap.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version
from typing import Any

try:
    __version__ = version("lfpiv")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__", "check_camera", "correlate", "evaluate", "export", "import_files", "load_rig", "open_run",
           "particles", "reconstruct", "track", "views"]

_API = {"check_camera", "correlate", "evaluate", "export", "import_files", "load_rig", "open_run", "particles",
        "reconstruct", "track", "views", "Evaluation"}


def __getattr__(name: str) -> Any:
    if name in _API:
        from lfpiv import api

        return getattr(api, name)
    raise AttributeError(f"module 'lfpiv' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_API})
