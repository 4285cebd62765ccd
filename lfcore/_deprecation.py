"""The one deprecation helper of lfpiv's Python API: old calls keep working, with a one-line
:class:`DeprecationWarning`, once per function and process.

- :func:`keyword_options`: a function whose options became keyword-only still accepts them
  positionally, in their old order.
- :func:`deprecated_alias`: a function's old name (after a rename or a move) still calls it.
- :func:`moved_names`: a module's ``__getattr__`` for names (classes, functions) that were renamed
  or moved to another module: the old name gives the object itself.
- :func:`deprecated`: a function or method kept for old callers, whose work is now done another
  way (the message says which).

It imports nothing of lfpiv's, so every package may use it (lfcore is pure; the commands, which
may not import lfcore, reach it as :mod:`lfpiv._deprecation`). The command line's old option
spellings have their own helper, :func:`lfpiv.commands.add_old_spelling`.

"""

from __future__ import annotations

import functools
import inspect
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

__all__ = ["deprecated", "deprecated_alias", "keyword_options", "moved_names"]

F = TypeVar("F", bound=Callable[..., Any])

_POSITIONAL = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)


def _warn_once(message: str) -> Callable[[], None]:
    """A function that issues ``message`` as a DeprecationWarning the first time it is called."""
    warned = False

    def warn() -> None:
        nonlocal warned
        if not warned:
            warned = True
            # stacklevel 3: past this function and the wrapper, at the caller's line
            warnings.warn(message, DeprecationWarning, stacklevel=3)

    return warn


def keyword_options(*names: str, since: str) -> Callable[[F], F]:
    """Accept the keyword-only options ``names`` positionally too, in that order, with a warning.

    Decorate the function with its new signature (options after ``*``); a call that passes
    more positional arguments than the function's required ones maps the extra ones onto
    ``names`` and warns once: ``module.function(): pass config=, device= by keyword (positional
    options are deprecated since lfpiv 0.1.0)``. For a class- or static method, put this
    decorator below ``@classmethod``/``@staticmethod``.

    Parameters
    ----------
    *names
        The options that could be passed positionally before, in their old order; each must be
        a keyword-only parameter of the decorated function.
    since
        The lfpiv version whose options became keyword-only (for the message).

    Returns
    -------
    callable
        The decorator. Too many positional arguments, or an option given both positionally and
        by keyword, raise the :class:`TypeError` Python would.
    """
    if not names:
        raise TypeError("keyword_options: name the options that used to be positional")

    def decorate(func: F) -> F:
        params = inspect.signature(func).parameters.values()
        n_positional = sum(p.kind in _POSITIONAL for p in params)
        keyword_only = {p.name for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY}
        if any(p.kind is inspect.Parameter.VAR_POSITIONAL for p in params):
            raise TypeError(f"keyword_options: {func.__qualname__} takes *args, so extra positional arguments "
                            "are not options")
        if not set(names) <= keyword_only:
            raise TypeError(f"keyword_options: {sorted(set(names) - keyword_only)} are not keyword-only "
                            f"parameters of {func.__qualname__}; put them after '*'")
        where = f"{func.__module__}.{func.__qualname__}"
        warn = _warn_once(f"{where}(): pass {', '.join(f'{n}=' for n in names)} by keyword "
                          f"(positional options are deprecated since lfpiv {since})")

        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            extra = args[n_positional:]
            if extra:
                if len(extra) > len(names):
                    raise TypeError(f"{func.__qualname__}() takes {n_positional + len(names)} positional "
                                    f"arguments but {len(args)} were given")
                for name, value in zip(names, extra, strict=False):
                    if name in kwargs:
                        raise TypeError(f"{func.__qualname__}() got multiple values for argument '{name}'")
                    kwargs[name] = value
                warn()
                args = args[:n_positional]
            return func(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return decorate


def deprecated_alias(new: F, old_name: str, *, since: str) -> F:
    """``new`` under its old name: calls it, and warns once that the name changed.

    Parameters
    ----------
    new
        The function as it is called now.
    old_name
        The old dotted name, as users wrote it (``"lfpiv.commands.correlate.evaluate_vectors"``).
    since
        The lfpiv version that renamed or moved it (for the message).

    Returns
    -------
    callable
        A function with ``new``'s signature that warns once per process: ``old_name is now
        module.name (deprecated since lfpiv 0.1.0)``.
    """
    warn = _warn_once(f"{old_name} is now {new.__module__}.{new.__qualname__} (deprecated since lfpiv {since})")

    @functools.wraps(new)
    def alias(*args: Any, **kwargs: Any) -> Any:
        warn()
        return new(*args, **kwargs)

    alias.__doc__ = f"Deprecated: the old name of :func:`{new.__module__}.{new.__qualname__}`."
    return alias  # type: ignore[return-value]


def moved_names(module: str, names: dict[str, Callable[[], Any]], *, since: str) -> Callable[[str], Any]:
    """A module ``__getattr__`` that keeps old names working: each gives its object itself (a class
    stays a class) and warns once, ``module.Old is now package.module.New (deprecated since lfpiv
    0.1.0)``.

    Parameters
    ----------
    module
        The module's ``__name__``.
    names
        Old name -> a function returning the object now (called on first use, so that a name moved
        to a module that imports this one needs no import at load time).
    since
        The lfpiv version that renamed or moved them (for the message).

    Returns
    -------
    callable
        ``__getattr__(name)``; any other name raises :class:`AttributeError` as a module would.
    """
    warned: set[str] = set()

    def __getattr__(name: str) -> Any:
        if name not in names:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        obj = names[name]()
        if name not in warned:
            warned.add(name)
            where = f"{getattr(obj, '__module__', module)}.{getattr(obj, '__qualname__', name)}"
            warnings.warn(f"{module}.{name} is now {where} (deprecated since lfpiv {since})", DeprecationWarning,
                          stacklevel=2)
        return obj

    return __getattr__


def deprecated(instead: str, *, since: str) -> Callable[[F], F]:
    """Keep a function or method for old callers, warning once that ``instead`` is the way now:
    ``module.function() is deprecated since lfpiv 0.1.0: use weights.forward(e, out=out)``.

    Parameters
    ----------
    instead
        What to call instead, as a user would write it.
    since
        The lfpiv version that deprecated it (for the message).
    """
    def decorate(func: F) -> F:
        warn = _warn_once(f"{func.__module__}.{func.__qualname__}() is deprecated since lfpiv {since}: use "
                          f"{instead}")

        @functools.wraps(func)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            warn()
            return func(*args, **kwargs)

        return wrapper  # type: ignore[return-value]

    return decorate
