"""python-can, imported without its MF4 log format.

Importing python-can imports asammdf for its MF4 logger, and with it pandas: 0.6-0.7 CPU s (several
wall seconds under load) that every process paid before it could open the bus (``eol-cal flash``,
``eol-cal ecu-sim``, ``eol-cal run``'s pre-flight). eol-cal never logs CAN traffic to MF4; its
captures use asammdf directly (:mod:`eol_cal.capture.mdf4_io`), which the station cycle imports on
its helper thread while the dyno turns.

Only the first import of python-can in a process decides. ``import eol_cal`` puts
:class:`CanWithoutMf4` first on the import path (:func:`install`), so that first import, from
whichever module, runs with asammdf masked; a process that imported asammdf before keeps
python-can's MF4 format (it costs nothing more there).
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
from collections.abc import Sequence
from types import ModuleType


class _Masked(importlib.abc.Loader):
    """python-can's own loader, its package executed while ``import asammdf`` fails."""

    def __init__(self, loader: importlib.abc.Loader) -> None:
        self.loader = loader

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType | None:
        return self.loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        module.__loader__ = module.__spec__.loader = self.loader  # type: ignore[union-attr]  # as if never wrapped
        masked = "asammdf" not in sys.modules
        if masked:
            sys.modules["asammdf"] = None  # type: ignore[assignment]  # "import asammdf" fails: python-can skips MF4
        try:
            self.loader.exec_module(module)
        finally:
            if masked and sys.modules.get("asammdf", "") is None:
                del sys.modules["asammdf"]


class CanWithoutMf4(importlib.abc.MetaPathFinder):
    """Finds python-can as the other finders do; its package runs without asammdf. Leaves the
    import path after the first look-up of ``can``."""

    def find_spec(self, fullname: str, path: Sequence[str] | None,
                  target: ModuleType | None = None) -> importlib.machinery.ModuleSpec | None:
        if fullname != "can":
            return None
        if self in sys.meta_path:
            sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is not None and spec.loader is not None:
            spec.loader = _Masked(spec.loader)
        return spec


def install() -> None:
    """Put :class:`CanWithoutMf4` first on the import path unless python-can is imported already
    (or the finder is there)."""
    if "can" not in sys.modules and not any(isinstance(f, CanWithoutMf4) for f in sys.meta_path):
        sys.meta_path.insert(0, CanWithoutMf4())
