"""Signals at random moments of ``eol-cal run``: during the fit (JAX tracing and solving) and
during the writes (judging, report, record). Does every one end the run with exit 2, the dyno in
its safe state, the record kept, and nothing flashed after it? (issue 23: the fault benchmark's
``signals`` section, ``bench/bench_faults.py --section signals``.)

Real processes on 127.0.0.1: ``eol-cal ecu-sim`` (python-can-remote) and ``eol-cal run`` each in
their own process, the dyno simulator (synthetic captures) in this one. A trial waits for what
starts its window (the dyno's drive disabled after the calibration acquisition: the fit follows;
the compensated capture's file ``after.mf4``: the writes follow), waits a seeded random time inside
the window, sends SIGINT or SIGTERM, and judges:

- ``ignored``: the run ended 0 or 1 (the signal was swallowed), or flashed the calibrated block
  after it: the ECU boots it although the record says the signal came before the block's CRC went
  out (in the fit, the table, the flash before its CRC, or an acquisition before them);
- ``missed``: the run was over before the signal came: the process had exited (no signal sent),
  or its record was in the database (the database file's last write) before the signal was sent,
  and the process was only exiting: its exit code is the run's. Not a trial of the
  signal: counted apart, so that a window longer than the run does not read as a swallowed signal;
- ``stopped``: the step the record says the signal stopped (``error.step``; the flash's own step
  from the error's message);
- ``lost``: no record in the database, nor in the spool;
- ``unsafe``: the dyno simulator was left enabled or turning;
- ``traceback``, ``hang`` (no exit within ``--cap`` s), ``crash`` (another exit code).

    python bench/bench_faults_signals.py [--trials 12] [--seed 1] [--before COMMIT]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bench_faults_ecu import LIMITS  # the same limits as the ECU trials (beside this script: on its path)
from eol_cal.dyno import sim_dyno as ds
from eol_cal.dyno.sim_capture import synthetic_source
from eol_cal.ecu import protocol as P

ROOT = Path(__file__).resolve().parents[1]

#: (window, what opens it, the longest wait into it, s). The fit starts as the calibration
#: acquisition ends, when the client disables the dyno's drive (``FIRST_STOP``); the capture files
#: are written beside the fit and the flash, so they no longer mark it. The fit is 0.1-0.3 s, then
#: the flash: 0.3 s reaches into both.
FIRST_STOP = "the dyno's drive disabled after the first acquisition"
WINDOWS = (("fit", FIRST_STOP, 0.3), ("writes", "after.mf4", 0.8))


@dataclass
class SignalTrial:
    window: str
    signal_name: str
    delay_s: float
    rc: int | None
    seconds: float
    traceback: bool
    ignored: bool
    lost: bool
    unsafe: bool
    sent: bool = True
    stopped: str = ""
    after_end: bool = False  # sent, but after the record was in the database: the run was over

    @property
    def hang(self) -> bool:
        return self.rc is None

    @property
    def crash(self) -> bool:
        return self.rc is not None and self.rc not in (0, 1, 2)

    @property
    def clean(self) -> bool:
        return not (self.traceback or self.ignored or self.lost or self.unsafe or self.hang or self.crash or self.missed)

    @property
    def missed(self) -> bool:
        return not self.sent or self.after_end


def _cli(tree: Path, *args: str) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if not k.startswith("EOL_CAL_") or k == "EOL_CAL_JAX_CACHE"}
    env["PYTHONPATH"] = str(tree)
    return subprocess.Popen([sys.executable, "-m", "cli.main", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=tree, start_new_session=True)


def one_trial(tree: Path, work: Path, window: str, opens: str, delay_s: float, sig: signal.Signals,
              cap: float) -> SignalTrial:
    from eol_cal.ecu.flash import active_block_from_file
    from eol_cal.firmware import block as B

    (work / "limits.toml").write_text(LIMITS)
    (work / "key.hex").write_text(P.DEV_SECRET.hex())
    sim = ds.DynoSim(synthetic_source, serial="K-1")
    procs = []
    try:
        with ds.DynoSimThread(sim, "127.0.0.1", 0) as dyno:
            ecu = _cli(tree, "ecu-sim", "--flash-file", str(work / "ecu.flash"), "--listen", "127.0.0.1:0",
                       "--serial", "K-1", "--s3-s", "1")
            procs.append(ecu)
            url = ecu.stdout.readline().strip()
            run = _cli(tree, "run", "--dyno", f"127.0.0.1:{dyno.port}", "-i", "remote", "-c", url, "--limits",
                       str(work / "limits.toml"), "--db", str(work / "db.sqlite"), "--serial", "K-1", "--key-file",
                       str(work / "key.hex"), "--report-dir", str(work / "reports"), "--spool-dir", str(work / "spool"),
                       "--json")
            procs.append(run)
            end = time.monotonic() + cap
            was_enabled = False

            def opened() -> bool:
                nonlocal was_enabled
                if opens != FIRST_STOP:
                    return bool(list((work / "reports").rglob(opens)))
                was_enabled = was_enabled or sim.enabled
                return was_enabled and not sim.enabled

            while not opened() and time.monotonic() < end and run.poll() is None:
                time.sleep(0.005)
            time.sleep(delay_s)
            t0 = time.monotonic()
            sent = run.poll() is None
            sent_at = dt.datetime.now(dt.UTC)
            if sent:
                run.send_signal(sig)
            try:
                out, err = run.communicate(timeout=cap)
                rc: int | None = run.returncode
            except subprocess.TimeoutExpired:
                run.kill()
                out, err = run.communicate()
                rc = None
            seconds = time.monotonic() - t0
            unsafe = sim.enabled or sim.speed != 0.0
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)
    raw = active_block_from_file(work / "ecu.flash") if (work / "ecu.flash").exists() else None
    n_records, stopped, message, db_written = _record_outcome(work)
    flashed_after = (raw is not None and bool(B.unpack(raw, "active").flags & B.FLAG_COMP_ENABLE)
                     and not _crc_out_before(stopped, message))
    after_end = sent and db_written is not None and db_written < sent_at.timestamp()
    ignored = sent and not after_end and (rc in (0, 1) or flashed_after)
    flash_step = _flash_step(message)
    return SignalTrial(window, sig.name, delay_s, rc, seconds, "Traceback" in err, ignored, n_records < 1,
                       unsafe, sent, f"flash ({flash_step})" if flash_step else stopped, after_end)


#: the calibrated flash's steps from its CRC on (eol_cal.ecu.sequence): a signal there came after
#: the whole block had gone out, and the ECU may boot it (the record says which)
AFTER_THE_CRC = ("CRC (36)", "transfer exit (37)", "check routine (31 0202)", "reset", "confirm (22 FD01)")
#: the cycle's steps after the calibrated flash ("": no error, the verdict stands)
AFTER_THE_FLASH = ("acquire compensated", "metrics", "report", "")


def _flash_step(message: str) -> str:
    """The flash's own step an ``Interrupted`` message names ("... during flash (reset); ..."),
    "" when none."""
    _, found, rest = message.partition("during flash (")
    text = rest.split(";", 1)[0].strip()
    return text[:-1] if found and text.endswith(")") else ""


def _crc_out_before(stopped: str, message: str) -> bool:
    """Whether the calibrated block's CRC went out before the signal, by the step the record says
    it stopped."""
    if stopped == "flash":
        return _flash_step(message) in AFTER_THE_CRC
    return stopped in AFTER_THE_FLASH


def _record_outcome(work: Path) -> tuple[int, str, str, float | None]:
    """The run's records in the database and the spool, the step the record names as failed (""
    without a record or an error: the database's record, else the spool's) and the error's message,
    and when the database was last written (POSIX s; None without a record in it)."""
    from eol_cal.records.query import query_records

    db = work / "db.sqlite"
    db_writes = [f.stat().st_mtime for f in work.glob("db.sqlite*")]  # before this process reads it
    recs = query_records(db) if db.exists() else []
    spooled = sorted((work / "spool").glob("*.json"))
    stopped = message = ""
    if recs:
        if recs[-1].error is not None:
            stopped, message = recs[-1].error.step, recs[-1].error.message
    elif spooled:
        try:
            error = json.loads(spooled[0].read_text()).get("error")
        except (ValueError, AttributeError):
            error = None
        if isinstance(error, dict):
            stopped, message = str(error.get("step", "")), str(error.get("message", ""))
    return len(recs) + len(spooled), stopped, message, (max(db_writes) if recs and db_writes else None)


def signal_trials(trials: int, seed: int, tree: Path = ROOT, cap: float = 120.0) -> list[SignalTrial]:
    rng = random.Random(seed)
    out = []
    for k in range(trials):
        window, opens, longest = WINDOWS[0] if k % 3 != 2 else WINDOWS[1]
        sig = (signal.SIGINT, signal.SIGTERM)[rng.randrange(2)]
        delay = round(rng.uniform(0.0, longest), 3)
        with tempfile.TemporaryDirectory(prefix="bench-signals-") as tmp:
            out.append(one_trial(tree, Path(tmp), window, opens, delay, sig, cap))
    return out


def print_trials(title: str, trials: list[SignalTrial], show: int = 20) -> dict[str, int]:
    counts = {"trials": len(trials), "missed (the run was over)": sum(t.missed for t in trials),
              "exit 2": sum(t.rc == 2 for t in trials), "ignored": sum(t.ignored for t in trials),
              "records lost": sum(t.lost for t in trials), "dyno unsafe": sum(t.unsafe for t in trials),
              "tracebacks": sum(t.traceback for t in trials), "hangs": sum(t.hang for t in trials),
              "crashes": sum(t.crash for t in trials)}
    worst = max((t.seconds for t in trials if t.rc is not None), default=0.0)
    print(f"\n{title}")
    print("  ".join(f"{k} {v}" for k, v in counts.items()) + f"  worst s {worst:.1f}")
    stopped: dict[str, int] = {}
    for t in trials:
        if not t.missed:
            name = t.stopped or "(none: the verdict stands)"
            stopped[name] = stopped.get(name, 0) + 1
    print("  steps the signals stopped: " + ", ".join(f"{k} {v}" for k, v in sorted(stopped.items())))
    for t in [t for t in trials if not t.clean][:show]:
        print(f"  {t.window} +{t.delay_s:.2f} s {t.signal_name}: sent {t.sent}, after the end {t.after_end}, "
              f"rc {t.rc}, ignored {t.ignored}, "
              f"lost {t.lost}, unsafe {t.unsafe}, traceback {t.traceback}, stopped {t.stopped or '-'}")
    return counts


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=12)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    counts = print_trials("signals", signal_trials(args.trials, args.seed))
    return 0 if not any(counts[k] for k in ("ignored", "records lost", "dyno unsafe", "tracebacks", "hangs", "crashes")) else 1


if __name__ == "__main__":
    sys.exit(main())
