"""matplotlib for every figure of the tool: pyplot on the Agg backend, imported on first use (it
costs a second, and the commands that draw nothing never pay it), and PNG files written atomically."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

from eol_cal.atomic import atomic_path
from eol_cal.errors import InputError

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def pyplot() -> ModuleType:
    """matplotlib's pyplot on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_png(fig: Figure, path: str | Path) -> None:
    """Write ``fig`` as PNG at ``path``, atomically; the figure stays open."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=110)
    except OSError as exc:
        raise InputError(str(path), None, f"cannot write the plot: {exc.strerror or exc}") from None


def save_png(fig: Figure, path: str | Path) -> None:
    """Write ``fig`` as PNG at ``path`` (atomically) and close it."""
    try:
        write_png(fig, path)
    finally:
        pyplot().close(fig)
