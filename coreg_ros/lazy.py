"""Lazy re-exports of a package (PEP 562): a name's module is imported on first use."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from importlib import import_module


def lazy_exports(package: str, homes: Mapping, namespace: dict) -> tuple[Callable, Callable]:
    """
    Return the ``__getattr__`` and ``__dir__`` of a package that re-exports names lazily.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    homes : mapping
        Public name -> its module: a submodule name (``'keys'``, relative to ``package``), a full
        module path (``'coreg_ros.api'``), or ``(module, attribute)`` for a name exported under
        another one.
    namespace : dict
        The package's ``globals()``: a name, once imported, is kept there.

    """
    def getattr_(name: str):
        home = homes.get(name)
        if home is None:
            raise AttributeError(f'module {package!r} has no attribute {name!r}')
        module, attr = home if isinstance(home, tuple) else (home, name)
        value = getattr(import_module(module if '.' in module else f'{package}.{module}'), attr)
        namespace[name] = value
        return value

    def dir_():
        return sorted(set(namespace) | set(homes))

    return getattr_, dir_
