"""Step ``master check``: a production motor on a station with a master gate is refused, before
anything is touched, while the master check is due or the last one failed (:mod:`eol_cal.msa.gate`);
else the master run that admitted it goes into the record."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from eol_cal.errors import EolCalError
from eol_cal.station.context import CycleContext

NAME = "master check"


def gate_steps(ctx: CycleContext) -> tuple[tuple[str, Callable[[CycleContext], Any]], ...]:
    """The master gate of a production or master run: the station's rules in force (the records
    database's, :func:`eol_cal.msa.gate.gate_in_force`), found before any step; this step when
    there are rules (or they cannot be read: it refuses). The master serial runs as kind
    ``master``, judged against the rules (:mod:`eol_cal.station.steps.measure_ripple`)."""
    if ctx.cfg.kind not in ("production", "master") or (ctx.cfg.master is None and not ctx.station.id):
        return ()
    from eol_cal.msa.gate import gate_in_force  # the records database's library (SQLAlchemy): on a gated station

    try:
        ctx.gate = gate_in_force(ctx.cfg.db, ctx.station.id, ctx.cfg.master, timeout_s=ctx.cfg.db_timeout_s)
    except EolCalError as exc:
        failure = exc

        def refuse(_ctx: CycleContext) -> None:
            raise failure

        return ((NAME, refuse),)
    if ctx.gate is None:
        return ()
    is_master = ctx.cfg.serial == ctx.gate.master.serial
    ctx.cfg = dataclasses.replace(ctx.cfg, master=ctx.gate.master, kind="master" if is_master else "production")
    ctx.gate_info = ctx.gate.info()  # a refusal records the rules it was refused under
    return () if is_master else ((NAME, run),)


def run(ctx: CycleContext) -> None:
    from eol_cal.msa.gate import admitted_info, check_gate

    assert ctx.gate is not None  # gate_steps runs this step only on a station with rules
    last = check_gate(ctx.cfg.db, ctx.gate, ctx.station.id, timeout_s=ctx.cfg.db_timeout_s)
    assert last is not None  # an open gate has its master run
    ctx.gate_info = admitted_info(ctx.gate, last)
