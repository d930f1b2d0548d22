"""What reaches a renderer: matplotlib on Agg with text taken literally, and links that are files.

A station id, serial, file or database name, variant or failure cause comes from a record or an
input and ends up in a figure's title, legend or tick labels, and on the HTML pages. matplotlib
reads ``$...$`` in any text as math text (a serial ``$\\foo{$`` raised ParseFatalException when
the figure was drawn: ``lot report``, ``analyze --plot`` and ``simulate --plot`` ended in a
traceback), and with ``text.usetex`` (a matplotlibrc may set it) hands every text to LaTeX.
The rules, one place each:

- :func:`pyplot` is the one way the tool gets matplotlib: Agg, ``text.usetex`` off;
- :func:`plain` is applied to every text from a record or an input before matplotlib sees it:
  it escapes ``$`` so that the text is drawn as written (the tool's own labels may use math
  text; tick labels of log axes do);
- :func:`literal_texts` is the net under both, at every figure's save: a text that still does
  not parse as math text is drawn literally instead of failing;
- :func:`file_link` is the one rule for links on the pages: a relative file path, each segment
  percent-encoded, so that no record's ``report_dir`` (``javascript:alert(1)``) becomes a URL
  with a scheme; Jinja's autoescape does the HTML escaping.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure


def pyplot() -> ModuleType:
    """matplotlib's pyplot on the Agg backend, without LaTeX (imported on first use: a second)."""
    import matplotlib

    matplotlib.use("Agg")
    matplotlib.rcParams["text.usetex"] = False
    import matplotlib.pyplot as plt

    return plt


def plain(text: Any) -> str:
    """``text`` (from a record or an input) as matplotlib draws it literally: ``$`` escaped.

    matplotlib takes a text as math when it holds an even number of unescaped ``$``, and drops
    the backslash of each ``\\$`` otherwise; escaping every ``$`` leaves none unescaped, so the
    text is drawn exactly as given (a backslash before a ``$`` included).
    """
    return str(text).replace("$", r"\$")


def literal_texts(fig: Figure) -> None:
    """Every text of ``fig`` that holds math text that does not parse is drawn literally.

    The net under :func:`plain`: a text missed there ends as written on the figure, not as a
    ParseFatalException when the figure is saved. Tick labels get their text at drawing time
    (their formatters are the tool's own).
    """
    from matplotlib.mathtext import MathTextParser
    from matplotlib.text import Text

    parser = MathTextParser("path")
    for text in fig.findobj(Text):
        content = text.get_text()
        if "$" not in content or not text.get_parse_math():
            continue
        dollars = content.count("$") - content.count(r"\$")  # matplotlib's rule: an even number is math
        if dollars <= 0 or dollars % 2:
            continue
        try:
            parser.parse(content)
        except ValueError:
            text.set_parse_math(False)


def file_link(target: str | os.PathLike[str], page_dir: str | os.PathLike[str]) -> str | None:
    """A link from a page in ``page_dir`` to the file ``target``: its relative path, every segment
    percent-encoded (``:`` included, so no segment reads as a URL scheme); None when ``target``
    is not an existing regular file."""
    path = Path(target)
    try:
        if not path.is_file():
            return None
        rel = Path(os.path.relpath(path.resolve(), Path(page_dir).resolve())).as_posix()
    except (OSError, ValueError):  # another drive, a name the file system refuses
        return None
    return "/".join(quote(part, safe="") for part in rel.split("/"))
