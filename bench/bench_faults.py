"""Fault benchmark (issue 16): how the real CLI ends on hostile inputs, side by side with the
code before this work.

Section ``inputs``: a seeded campaign of bad inputs (:mod:`eol_cal.sim.fuzz`: CSV and MDF4 captures,
parameter blocks, fit results), each run through the real CLI in a child process under an
address-space limit. Per kind and in all it prints: bad inputs tried / accepted / refused
cleanly (exit 1 or 2, one line naming the file) / refusals that do not name the file /
tracebacks / hangs / crashes (a signal or another exit code) / inputs modified, the slowest run
and the largest resident set. Tracebacks, hangs, crashes and modified inputs must all be 0.

Side by side (``--before COMMIT``): the same inputs through the CLI of an older commit (checked
out with ``git worktree`` into a temporary directory), the code a user has without this work.

Section ``ecu``: the ECU-kill and signal trials of ``bench/bench_faults_ecu.py`` (the ECU
simulator killed at each flashing step, SIGINT/SIGTERM during each, ``eol-cal run`` with the ECU
killed in either flash): ECU-kill trials / ended within the bound / records kept.

Section ``scenarios`` (issue 23): the targeted scenarios of :mod:`eol_cal.sim.fuzz.scenarios`, every
member of each class the probe found: hostile TOML of every kind (numbers of thousands of
digits, nesting thousands deep, oversized, a FIFO), JSON (fit results, refit rows, spool files,
stored records with NaN), CSV header cells and MDF4 record counts, flags and header comments,
an output over an input through every writing option and setting, values that must be refused,
refit's exit codes. Per kind: tried / refused / accepted / accepted-should-refuse / tracebacks /
hangs / crashes / inputs modified.

Section ``uds`` (issue 23): flashes against an ECU simulator that sends a late duplicate of its
previous answer before every answer (``Faults.stale_answers``), with the response matcher and
without it (udsoncan's first-message rule, the code before): flashes completed and verified.

Section ``signals`` (issue 23): ``bench/bench_faults_signals.py``, SIGINT/SIGTERM at random
moments of ``eol-cal run``'s fit and writes: exit 2, signals ignored, records lost, dyno unsafe.

Sections are functions in :data:`SECTIONS` (name -> function(args) -> bool ok).

Section ``scenarios`` also runs issue 36's hostile scenarios (:mod:`eol_cal.sim.fuzz.scenarios_harden`:
``dbfiles``, ``selections``, ``oemkey``, ``dynoclear``, ``signals``, ``round3``) and those of any
other ``eol_cal.sim.fuzz.scenarios_*`` module present; ``--kinds`` runs some of them (in parts).

Section ``oemkey`` (issue 36): what running an OEM's seed-to-key function in its own child process
costs, beside calling it in this process (the code before): load and one key.

    python bench/bench_faults.py [--seed 1] [--per-kind 125] [--before b46ce43] [--section inputs|ecu|scenarios|...]
    python bench/bench_faults.py --section scenarios --kinds dbfiles selections   # some kinds only
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from eol_cal.sim import fuzz

ROOT = Path(__file__).resolve().parents[1]

COLUMNS = ("tried", "accepted", "refused_cleanly", "unnamed", "tracebacks", "hangs", "crashes", "modified")


@contextlib.contextmanager
def checkout(commit: str) -> Iterator[Path]:
    """A temporary ``git worktree`` of ``commit`` (removed afterwards)."""
    with tempfile.TemporaryDirectory(prefix="bench-faults-before-") as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), commit],
                       check=True, capture_output=True)
        try:
            yield tree
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                           check=False, capture_output=True)


def _row(label: str, tally: fuzz.Tally) -> str:
    cells = "  ".join(f"{getattr(tally, c):>{max(len(c), 5)}d}" for c in COLUMNS)
    return f"{label:<16}{cells}  {tally.max_seconds:8.2f}  {tally.max_rss_kb / 1024:8.0f}"


def _print_tallies(title: str, tallies: dict[str, fuzz.Tally]) -> fuzz.Tally:
    print(f"\n{title}")
    print(f"{'kind':<16}" + "  ".join(f"{c:>{max(len(c), 5)}}" for c in COLUMNS) + "  max s    max RSS MiB")
    total = fuzz.Tally()
    for kind, tally in tallies.items():
        print(_row(kind, tally))
        for name in COLUMNS:
            setattr(total, name, getattr(total, name) + getattr(tally, name))
        total.max_seconds = max(total.max_seconds, tally.max_seconds)
        total.max_rss_kb = max(total.max_rss_kb, tally.max_rss_kb)
        total.bad.extend(tally.bad)
    print(_row("all", total))
    return total


def _show_bad(total: fuzz.Tally, limit: int) -> None:
    for o in total.bad[:limit]:
        what = ("hang" if o.hang else "crash" if o.crash else "traceback" if o.traceback
                else "modified" if o.modified else "unnamed")
        last = (o.stderr.strip().splitlines() or [""])[-1][:160]
        print(f"  {what:<9} {o.case.name} ({o.case.how}) `{o.command}` rc {o.rc}: {last}")


def inputs_section(args: argparse.Namespace) -> bool:
    """Bad inputs through the CLI: ours, and (with --before) the older code's."""
    bases = fuzz.base_files()
    with tempfile.TemporaryDirectory(prefix="bench-faults-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        ours = fuzz.campaign(args.seed, args.per_kind, work, bases, timeout_s=args.timeout)
        took = time.perf_counter() - t0
        total = _print_tallies(f"bad inputs, this tree (seed {args.seed}, {args.per_kind} per kind, "
                               f"{took:.0f} s, bound {args.timeout:g} s per command, RLIMIT_AS "
                               f"{fuzz.CHILD_MEMORY_BYTES / 1024**3:g} GiB)", ours)
        _show_bad(total, args.show)
        if args.before:
            with checkout(args.before) as tree:
                before_work = work / "before"
                before_work.mkdir()
                theirs = fuzz.campaign(args.seed, args.per_kind, before_work, bases, timeout_s=args.timeout, root=tree)
                old = _print_tallies(f"bad inputs, commit {args.before} (the same inputs)", theirs)
                _show_bad(old, args.show)
    print(f"\nbad inputs tried {total.tried} / refused cleanly {total.refused_cleanly} / tracebacks {total.tracebacks} "
          f"/ hangs {total.hangs} / crashes {total.crashes} / inputs modified {total.modified}"
          f" (accepted {total.accepted}, refusals not naming the file {total.unnamed})")
    return not (total.tracebacks or total.hangs or total.crashes or total.modified or total.unnamed)


SCENARIO_COLUMNS = ("tried", "refused", "accepted", "should_refuse", "tracebacks", "hangs", "crashes", "modified")


def _print_scenarios(title: str, tallies: dict) -> object:
    from eol_cal.sim.fuzz.scenarios import ScenarioTally

    print(f"\n{title}")
    print(f"{'kind':<10}" + "  ".join(f"{c:>{max(len(c), 5)}}" for c in SCENARIO_COLUMNS) + "   max s")
    total = ScenarioTally()
    for kind, t in tallies.items():
        print(f"{kind:<10}" + "  ".join(f"{getattr(t, c):>{max(len(c), 5)}d}" for c in SCENARIO_COLUMNS)
              + f"  {t.max_seconds:6.1f}")
        for c in SCENARIO_COLUMNS:
            setattr(total, c, getattr(total, c) + getattr(t, c))
        total.max_seconds = max(total.max_seconds, t.max_seconds)
        total.bad.extend(t.bad)
    print(f"{'all':<10}" + "  ".join(f"{getattr(total, c):>{max(len(c), 5)}d}" for c in SCENARIO_COLUMNS)
          + f"  {total.max_seconds:6.1f}")
    return total


def scenarios_section(args: argparse.Namespace) -> bool:
    """The targeted scenarios (issue 23's, issue 36's, and any other ``eol_cal.sim.fuzz.scenarios_*``
    module's) through the CLI: ours, and (with --before) the older code's."""
    from eol_cal.sim.fuzz.scenarios import all_builders, run_scenarios

    bases = fuzz.base_files()
    builders = all_builders()
    unknown = sorted(set(args.kinds or ()) - set(builders))
    if unknown:
        raise SystemExit(f"--kinds: unknown {', '.join(unknown)}; known: {', '.join(builders)}")
    kinds = tuple(args.kinds or builders)
    with tempfile.TemporaryDirectory(prefix="bench-scenarios-") as tmp:
        t0 = time.perf_counter()
        ours = run_scenarios(kinds, Path(tmp), bases, timeout_s=args.timeout * 3)
        total = _print_scenarios(f"targeted scenarios, this tree ({time.perf_counter() - t0:.0f} s, bound "
                                 f"{args.timeout * 3:g} s per command)", ours)
        for o in total.bad[:args.show]:
            print(f"  {o.what:<22} {o.scenario.kind}: {o.scenario.name} rc {o.rc}: "
                  f"{(o.stderr.strip().splitlines() or [''])[-1][:140]}")
            if o.hang:  # where it hung (the child's faulthandler dump, when the scenario asked for one)
                print("    " + "\n    ".join(o.stderr.strip().splitlines()[-30:]))
        if args.before:
            with checkout(args.before) as tree:
                theirs = run_scenarios(kinds, Path(tmp), bases, timeout_s=args.timeout * 3, root=tree)
            old = _print_scenarios(f"targeted scenarios, commit {args.before} (the same scenarios)", theirs)
            for o in old.bad[:args.show]:
                print(f"  {o.what:<22} {o.scenario.kind}: {o.scenario.name} rc {o.rc}: "
                      f"{(o.stderr.strip().splitlines() or [''])[-1][:140]}")
    print(f"\nscenarios tried {total.tried} / refused {total.refused} / accepted {total.accepted} / "
          f"accepted-should-refuse {total.should_refuse} / tracebacks {total.tracebacks} / hangs {total.hangs} / "
          f"crashes {total.crashes} / inputs modified {total.modified}")
    return not (total.should_refuse or total.tracebacks or total.hangs or total.crashes or total.modified)


def uds_section(args: argparse.Namespace) -> bool:
    """Flashes with a late duplicate answer at every step: with the matcher, and without (before)."""
    import dataclasses

    import eol_cal.ecu.session as session
    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.client import flash_block, hmac_seed_to_key, read_active_block
    from eol_cal.ecu.sim_ecu import Faults
    from eol_cal.ecu.transport import TesterConnection
    from eol_cal.infra.exchange_log import quiet
    from eol_cal.sim.virtual_rig import FAST_CLIENT, example_block, virtual_rig

    quiet(("UdsClient", "isotp", "Connection", "can"))  # udsoncan logs each refused answer; counted below
    timing = dataclasses.replace(FAST_CLIENT, p2_s=0.5)
    key = hmac_seed_to_key(P.DEV_SECRET)
    results = {}
    for label, conn in (("with the matcher", session.MatchingConnection), ("udsoncan's first message (before)",
                                                                           TesterConnection)):
        done = failed = stale = 0
        reasons: dict[str, int] = {}
        saved = session.MatchingConnection
        session.MatchingConnection = conn  # the session builds its connection from this name
        try:
            for k in range(args.uds_flashes):
                block = example_block(seed=100 + k)
                with virtual_rig(faults=Faults(stale_answers=True)) as rig:
                    try:
                        flash_block(rig.tester, block, seed_to_key=key, verify=True, timing=timing)
                        ok = read_active_block(rig.tester, timing=timing) == block
                    except Exception as exc:  # noqa: BLE001 - the outcome counted
                        ok = False
                        reasons[type(exc).__name__] = reasons.get(type(exc).__name__, 0) + 1
                    stale += rig.sim.stale_sent
                done += ok
                failed += not ok
        finally:
            session.MatchingConnection = saved
        results[label] = (done, failed, stale, reasons)
    print(f"\nflashes with a late duplicate answer at every step ({args.uds_flashes} each, P2 {timing.p2_s:g} s)")
    print(f"{'tester':<36}{'flashes':>8}{'completed and verified':>24}{'failed':>8}{'late answers sent':>19}")
    for label, (done, failed, stale, reasons) in results.items():
        why = ", ".join(f"{k} {n}" for k, n in reasons.items())
        print(f"{label:<36}{args.uds_flashes:>8}{done:>24}{failed:>8}{stale:>19}  {why}")
    return results["with the matcher"][1] == 0


def signals_section(args: argparse.Namespace) -> bool:
    """SIGINT/SIGTERM at random moments of eol-cal run's fit and writes (bench/bench_faults_signals.py)."""
    import bench_faults_signals as bs

    counts = bs.print_trials(f"signals during eol-cal run, this tree (seed {args.seed})",
                             bs.signal_trials(args.signal_trials, args.seed))
    if args.before:
        with checkout(args.before) as tree:
            bs.print_trials(f"signals, commit {args.before} (the same moments)",
                            bs.signal_trials(args.signal_trials, args.seed, tree=tree))
    return not any(counts[k] for k in ("ignored", "records lost", "dyno unsafe", "tracebacks", "hangs", "crashes"))


def ecu_section(args: argparse.Namespace) -> bool:
    """ECU-kill and signal trials during ``flash`` and ``run`` (``bench/bench_faults_ecu.py``)."""
    import bench_faults_ecu

    return bench_faults_ecu.ecu_section(args.repeat, args.before or args.ecu_before, args.cap)


def oemkey_rows(key_calls: int) -> list[tuple[str, float, float, float, str]]:
    """(way, load s, median key s, max key s, first key in hex) of the plug-in ``oem_bench_key`` (a module on
    PYTHONPATH, as a station names ``MODULE:FUNC``), in this process and in its own child."""
    import importlib
    import statistics

    from eol_cal.ecu import protocol as P
    from eol_cal.ecu.keychild import ContainedKey

    rows = []
    for label in ("in this process (before)", "in its own child process"):
        t0 = time.perf_counter()
        if label.startswith("in this"):
            sys.modules.pop("oem_bench_key", None)
            fn = importlib.import_module("oem_bench_key").key

            def algo(seed: bytes, fn=fn) -> bytes:
                return fn(seed, P.DEV_SECRET)
        else:
            algo = ContainedKey("oem_bench_key", "key", "oem_bench_key:key", P.DEV_SECRET, "key-algo")
        first = algo(b"\x12\x34\x56\x78").hex()
        load = time.perf_counter() - t0
        calls = []
        for k in range(key_calls):
            t1 = time.perf_counter()
            assert algo(k.to_bytes(4, "big")) == P.security_key(P.DEV_SECRET, k.to_bytes(4, "big"))
            calls.append(time.perf_counter() - t1)
        rows.append((label, load, statistics.median(calls), max(calls), first))
        if hasattr(algo, "close"):
            algo.close()
    return rows


def oemkey_section(args: argparse.Namespace) -> bool:
    """What containing an OEM's seed-to-key function costs (issue 36, class 6): loading it and one
    key, in this process (the code before) and in its own child process (eol_cal.ecu.keychild).
    The plug-in is a module on PYTHONPATH, as a station's: this script measures in a child of its
    own started with it (``--oemkey-rows``)."""
    import json

    with tempfile.TemporaryDirectory(prefix="bench-oemkey-") as tmp:
        Path(tmp, "oem_bench_key.py").write_text("import hashlib, hmac\n\ndef key(seed, secret):\n"
                                                 "    return hmac.new(secret, seed, hashlib.sha256).digest()[:4]\n")
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, (tmp, os.environ.get("PYTHONPATH")))))
        out = subprocess.run([sys.executable, __file__, "--oemkey-rows", "--key-calls", str(args.key_calls)],
                             env=env, capture_output=True, text=True, check=True).stdout
    rows = json.loads(out.splitlines()[-1])
    print(f"\nOEM seed-to-key: load (start, import, first key) and one key ({args.key_calls} keys each)")
    print(f"{'where':<28}{'load ms':>10}{'median key ms':>15}{'max key ms':>12}")
    for label, load, med, worst, _ in rows:
        print(f"{label:<28}{1e3 * load:>10.1f}{1e3 * med:>15.3f}{1e3 * worst:>12.3f}")
    return rows[0][4] == rows[1][4]


#: name -> section; each prints its figures and returns True when its must-be-zero counts are 0
SECTIONS: dict[str, Callable[[argparse.Namespace], bool]] = {
    "inputs": inputs_section, "ecu": ecu_section, "scenarios": scenarios_section, "uds": uds_section,
    "signals": signals_section, "oemkey": oemkey_section,
}


def add_options(ap: argparse.ArgumentParser) -> None:
    """Options of every section (a new section adds its own here)."""
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--per-kind", type=int, default=125, help="bad inputs per kind (csv, mdf4, block, fitjson, block2, fitjson2)")
    ap.add_argument("--timeout", type=float, default=20.0, help="bound per command and input (s): beyond is a hang")
    ap.add_argument("--before", metavar="COMMIT", help="also run the inputs through this older commit's CLI")
    ap.add_argument("--show", type=int, default=20, help="list at most this many bad outcomes")
    ap.add_argument("--repeat", type=int, default=2, help="ECU-kill trials per flashing step")
    ap.add_argument("--cap", type=float, default=20.0, help="ECU trials: seconds after which a trial counts as hung")
    ap.add_argument("--ecu-before", default="b46ce43", metavar="COMMIT",
                    help="ECU trials: the older code's kill -9 reproduction (used when --before is not given)")
    ap.add_argument("--uds-flashes", type=int, default=10, help="flashes per tester in the uds section")
    ap.add_argument("--signal-trials", type=int, default=12, help="signalled runs in the signals section")
    ap.add_argument("--kinds", nargs="+", metavar="KIND",
                    help="scenarios section: only these kinds (issue 23: toml json captures paths refusals exits; "
                         "issue 36: dbfiles selections oemkey dynoclear signals round3; others' modules add theirs)")
    ap.add_argument("--key-calls", type=int, default=200, help="oemkey section: seed-to-key calls timed per way")
    ap.add_argument("--oemkey-rows", action="store_true", help=argparse.SUPPRESS)  # the oemkey section's child


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--section", action="append", choices=sorted(SECTIONS), help="run only these (default all)")
    add_options(ap)
    args = ap.parse_args()
    if args.oemkey_rows:
        import json

        print(json.dumps(oemkey_rows(args.key_calls)))
        return 0
    print(f"# bench_faults: Python {platform.python_version()}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(Path('/proc/loadavg').read_text().split()[:3])}")
    ok = True
    for name in args.section or list(SECTIONS):
        ok &= SECTIONS[name](args)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
