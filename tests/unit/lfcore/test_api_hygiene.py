"""lfcore's public functions and methods take their options by keyword only.

Definitions, as this test applies them:

- A public module is a module of lfcore none of whose dotted name's parts starts with an
  underscore (so :mod:`lfcore._kernels`, the Warp kernels, is not one).
- A public function is a plain Python function defined in lfcore's source (its code object's
  file is under ``lfcore/``) and reachable by a public name of a public module (a name in its
  ``__all__``, or without a leading underscore where it has none). A public class's methods
  count too: those without a leading underscore, plus ``__init__``, ``__new__`` and
  ``__call__`` (how a class is called), its static and class methods included, and those it
  inherits from lfcore's own base classes, public or not. Methods that :mod:`dataclasses` or
  :mod:`typing` generate are not in lfcore's source and are skipped; so are Warp kernels and
  functions, which are not plain functions.
- An option is a parameter with a default value. It must be keyword-only (after ``*``); the
  required arguments (the data: arrays, the rig, a path) may stay positional, and ``*args`` and
  ``**kwargs`` are neither.

A function wrapped by :func:`lfcore._deprecation.keyword_options` (options positional still
accepted, with a DeprecationWarning) is judged by the signature it wraps.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from pathlib import Path

import lfcore

#: Methods of a class that are how it is called, though their names start with an underscore.
CALLED = {"__init__", "__new__", "__call__"}

_POSITIONAL = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)

_ROOT = Path(lfcore.__file__).parent


def public_modules() -> list[str]:
    """lfcore and its submodules whose dotted names have no part with a leading underscore."""
    names = [m.name for m in pkgutil.walk_packages(lfcore.__path__, "lfcore.")]
    return ["lfcore", *sorted(n for n in names if not any(p.startswith("_") for p in n.split(".")))]


def _in_lfcore(func: object) -> bool:
    code = getattr(inspect.unwrap(func), "__code__", None)
    return code is not None and Path(code.co_filename).is_relative_to(_ROOT)


def public_functions() -> dict[str, object]:
    """Every public function and method of lfcore (see the module docstring), by its dotted
    name where it is defined (``module.Class.method``), unwrapped."""
    found: dict[str, object] = {}

    def add(func: object) -> None:
        if isinstance(func, (staticmethod, classmethod)):
            func = func.__func__
        if inspect.isfunction(func) and _in_lfcore(func):
            func = inspect.unwrap(func)
            found.setdefault(f"{func.__module__}.{func.__qualname__}", func)

    for name in public_modules():
        module = importlib.import_module(name)
        public = getattr(module, "__all__", None) or [n for n in vars(module) if not n.startswith("_")]
        for attr in public:
            obj = getattr(module, attr, None)
            if not str(getattr(obj, "__module__", "") or "").startswith("lfcore"):
                continue  # imported from elsewhere (numpy, typing, ...)
            if inspect.isclass(obj):
                for cls in obj.__mro__:
                    if str(cls.__module__).startswith("lfcore"):
                        for method_name, method in vars(cls).items():
                            if not method_name.startswith("_") or method_name in CALLED:
                                add(method)
            else:
                add(obj)
    return found


def positional_options(func: object) -> list[str]:
    """The parameters of ``func`` that have a default but may be passed positionally."""
    return [p.name for p in inspect.signature(func).parameters.values()
            if p.kind in _POSITIONAL and p.default is not p.empty]


def offenders() -> dict[str, list[str]]:
    """Public functions with positional options: dotted name -> those options."""
    return {name: opts for name, func in sorted(public_functions().items()) if (opts := positional_options(func))}


def test_the_walk_finds_lfcore_s_public_api():
    found = public_functions()
    # a function, a method, a class method, a constructor, a call, one from a private module
    # re-exported by a public package, an inherited method of a private base
    for name in ("lfcore.correlate.correlate", "lfcore.flows.Flow.velocity", "lfcore.rig.Rig.from_dict",
                 "lfcore.correlate.Correlator.__init__", "lfcore.correlate.Correlator.__call__",
                 "lfcore.runstore._store.RunStore.open", "lfcore.runstore._frames.Frames.frames"):
        assert name in found, name
    assert not any(".__repr__" in n or ".__eq__" in n for n in found)  # dataclasses' own
    assert not any(n.startswith("lfcore._kernels") for n in found)


def test_options_are_keyword_only():
    bad = offenders()
    assert not bad, "options to make keyword-only (put them after '*'): " + "; ".join(
        f"{name}({', '.join(opts)})" for name, opts in bad.items())
