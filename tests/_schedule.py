"""The order the two workers take the suite's files in: the costliest first.

``--dist loadfile`` hands a file (a *unit*: its module fixtures are computed once) to whichever
worker is free, in collection order, which is alphabetical. A heavy file late in the alphabet then
ran on one worker at the end while the other sat idle, and the 10 000 power-ups
(tests/test_mech_identify.py, ~250 CPU s, a fifth of the suite) were one unit on one worker. On a
loaded machine the suite's wall time is its busiest worker's CPU seconds times the load's share, so
this module:

- orders the units by their measured CPU seconds (``tests/schedule_cpu.txt``, written by
  ``python tests/_cpu_report.py DIR --table``), the costliest first and the rest in collection
  order after them (a classic longest-first list schedule: the last units handed out are small);
- makes each test of :data:`SPLIT` a unit of its own, so both workers run its parts (tests that
  share no module fixture, each minutes at load).

A file missing from the table (new, or cheap) only runs later; nothing is left out. The order does
not change what a test checks: every file still runs whole on one worker.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

#: tests (``path::function``) whose parametrized items are units of their own
SPLIT = ("tests/test_mech_identify.py::test_ten_thousand_powerups_identify_the_right_frame",)

TABLE = Path(__file__).with_name("schedule_cpu.txt")


def unit(nodeid: str) -> str:
    """The scheduling unit of a test: its file, or the test itself for one of :data:`SPLIT`."""
    if nodeid.split("[", 1)[0] in SPLIT:
        return nodeid
    return nodeid.split("::", 1)[0]


def costs(path: Path | None = None) -> dict[str, float]:
    """The table's CPU seconds per unit (``seconds unit`` a line, ``#`` a comment; default :data:`TABLE`)."""
    path = TABLE if path is None else path
    out: dict[str, float] = {}
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            seconds, name = line.split(None, 1)
            out[name] = float(seconds)
    return out


def costliest_first(items: list[pytest.Item]) -> None:
    """Reorder ``items`` in place: by their unit's cost, the costliest first (stable: a file's tests
    keep their order, and units of equal or unknown cost their collection order)."""
    table = costs()
    if table:
        items.sort(key=lambda item: -table.get(unit(item.nodeid), 0.0))


def make_scheduler(config: pytest.Config, log: Any) -> Any:
    """pytest-xdist's file scheduler with :data:`SPLIT`'s items as units of their own."""
    from xdist.scheduler import LoadFileScheduling

    class _Scheduler(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return unit(nodeid)

    return _Scheduler(config, log)
