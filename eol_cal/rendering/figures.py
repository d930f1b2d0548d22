"""matplotlib for every figure of the tool: pyplot on the Agg backend without LaTeX, imported on
first use (it costs a second, and the commands that draw nothing never pay it), and PNG files
written atomically, every text drawn literally where it does not parse as math text.

The pyplot getter and the text rules are :mod:`eol_cal.rendering.renderer`'s (one place for what reaches a
renderer); this module writes the files.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from eol_cal.infra.atomic import atomic_path
from eol_cal.errors import InputError
from eol_cal.rendering.renderer import literal_texts, pyplot

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["pyplot", "save_png", "write_png"]


def write_png(fig: Figure, path: str | Path) -> None:
    """Write ``fig`` as PNG at ``path``, atomically; the figure stays open. A text of the figure
    that does not parse as math text is drawn as written (:func:`eol_cal.rendering.renderer.literal_texts`)."""
    literal_texts(fig)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=110)
    except OSError as exc:
        raise InputError(str(path), None, f"cannot write the plot: {exc.strerror or exc}") from None


def save_png(fig: Figure, path: str | Path) -> None:
    """Write ``fig`` as PNG at ``path`` (:func:`write_png`) and close it."""
    try:
        write_png(fig, path)
    finally:
        pyplot().close(fig)
