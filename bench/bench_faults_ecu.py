"""ECU-kill and signal trials: does every way out of ``eol-cal flash`` / ``eol-cal run`` end in
time, cleanly, with the banks intact and the record kept? (issue 16, the ECU part of the fault
benchmark: ``bench/bench_faults.py --section ecu`` runs it beside the bad inputs.)

Real processes on 127.0.0.1: ``eol-cal ecu-sim --die-at STEP`` kills itself (SIGKILL) when that
request of the flash arrives; ``eol-cal flash`` and ``eol-cal run`` are their own processes; the
dyno simulator (synthetic captures) runs in this process. Per trial it records the time from the
ECU's death (or the signal) to the tester's exit, the exit code, the error line, the old block's
bank and which block the flash image boots.

Side by side: the same ECU-kill trials on the code before this work (``--before COMMIT``, run from
a ``git worktree`` of that commit), where a dead link hung the tester (capped at ``--cap`` s).

    python bench/bench_faults_ecu.py [--repeat 2] [--before b46ce43] [--cap 20]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from eol_cal.ecu import protocol as P
from eol_cal.ecu.client import ClientTiming, flash_block, hmac_seed_to_key
from eol_cal.ecu.flash import NorFlash, select_active
from eol_cal.sim.virtual_rig import FAST_CLIENT, example_block, virtual_rig

ROOT = Path(__file__).resolve().parents[1]

BOUND_S = ClientTiming().dead_link_bound_s
KILL_STEPS = ("session", "security", "read_did", "erase", "download", "transfer", "read_memory",
              "transfer_exit", "check", "reset")
SIGNAL_STEPS = (("session", "sessions"), ("security", "security access"), ("erase", "erase"),
                ("transfer", "download"), ("transfer_exit", "transfer exit (37)"),
                ("check", "check routine (31 0202)"), ("reset", "reset"))


@dataclass
class Trial:
    what: str
    rc: int | None
    seconds: float  # from the ECU's death or the signal to the tester's exit
    error_lines: int
    traceback: bool
    old_bank_intact: bool
    boots: int  # sequence the flash image boots: 1 old, 2 new (complete and checked)
    record: bool | None = None

    @property
    def clean(self) -> bool:
        return self.rc == 2 and self.error_lines == 1 and not self.traceback


def _cli(env: dict, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cli.main", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=env["PYTHONPATH"])


def _env(tree: Path) -> dict:
    """The environment (and working directory) that runs the ``eol-cal`` of ``tree``."""
    return dict(os.environ, PYTHONPATH=str(tree))


def _sim(env, flash: Path, *fault: str) -> tuple[subprocess.Popen, str]:
    proc = _cli(env, "ecu-sim", "--flash-file", str(flash), "--listen", "127.0.0.1:0", "--s3-s", "1", *fault)
    url = proc.stdout.readline().strip()
    if not url.startswith("ws://"):
        raise RuntimeError(proc.stderr.read())
    return proc, url


def _died_at(proc: subprocess.Popen) -> list[float]:
    """A list that gets the time the process ends (filled by a watcher thread)."""
    when: list[float] = []
    threading.Thread(target=lambda: (proc.wait(), when.append(time.monotonic())), daemon=True).start()
    return when


def _outcome(what, rc, seconds, err, path: Path, old_bank: bytes) -> Trial:
    flash = NorFlash(path)
    return Trial(what, rc, seconds, sum(line.startswith("error:") for line in err.splitlines()),
                 "Traceback" in err, flash.bank(0) == old_bank, select_active(flash)[0].sequence)


def kill_flash(env, base: Path, work: Path, step: str, cap: float, old_bank: bytes) -> Trial:
    path = work / "ecu.bin"
    shutil.copy(base / "base.bin", path)
    sim, url = _sim(env, path, "--die-at", step)
    died = _died_at(sim)
    flash = _cli(env, "flash", str(base / "new.bin"), "-i", "remote", "-c", url, "--key-file", str(base / "key.hex"))
    try:
        _, err = flash.communicate(timeout=cap)
        rc = flash.returncode
    except subprocess.TimeoutExpired:
        flash.kill()
        _, err = flash.communicate()
        rc = None  # hung
    end = time.monotonic()
    sim.kill()
    sim.wait()
    return _outcome(f"flash, ECU killed at {step}", rc, end - (died[0] if died else end), err, path, old_bank)


def kill_flash_external(env, base: Path, work: Path, cap: float, old_bank: bytes) -> Trial:
    """The issue's reproduction: ``ecu-sim --erase-s 0.4``, ``kill -9`` when the flash shows the erase."""
    path = work / "ecu.bin"
    shutil.copy(base / "base.bin", path)
    sim, url = _sim(env, path, "--erase-s", "0.4")
    flash = _cli(env, "flash", str(base / "new.bin"), "-i", "remote", "-c", url, "--key-file", str(base / "key.hex"))
    seen = []
    for line in flash.stderr:
        seen.append(line)
        if line.strip() == "erase":
            break
    sim.kill()
    sim.wait()
    died = time.monotonic()
    try:
        _, err = flash.communicate(timeout=cap)
        rc = flash.returncode
    except subprocess.TimeoutExpired:
        flash.kill()
        _, err = flash.communicate()
        rc = None  # hung
    return _outcome("flash, kill -9 at the erase", rc, time.monotonic() - died, "".join(seen) + err, path, old_bank)


def signal_flash(env, base: Path, work: Path, step: str, shown: str, sig: signal.Signals, old_bank: bytes) -> Trial:
    path = work / "ecu.bin"
    shutil.copy(base / "base.bin", path)
    sim, url = _sim(env, path, "--slow", f"{step}:1.0")
    flash = _cli(env, "flash", str(base / "new.bin"), "-i", "remote", "-c", url, "--key-file", str(base / "key.hex"))
    seen = []
    for line in flash.stderr:
        seen.append(line)
        if line.strip() == shown:
            break
    time.sleep(0.3)
    t0 = time.monotonic()
    flash.send_signal(sig)
    _, err = flash.communicate(timeout=BOUND_S + 10)
    seconds = time.monotonic() - t0
    time.sleep(1.5)  # the slowed request ends on the ECU
    sim.terminate()
    sim.wait()
    return _outcome(f"flash, {sig.name} during {step}", flash.returncode, seconds, "".join(seen) + err, path, old_bank)


LIMITS = """default_variant = "B"
[variant.B]
max_k6 = 0.0025
max_pp_before_pct = 25.0
max_pp_after_pct = 2.0
min_improvement_pct = 50.0
min_r2 = 0.3
max_rms_nm = 0.1
max_ci_k6_rel = 0.05
max_ci_phase_k6_deg = 3.0
max_ci_c6_nm = 0.01
max_hall_deviation_deg = 3.0
"""


def kill_run(env, base: Path, work: Path, die_at: str) -> Trial:
    """``eol-cal run`` with the ECU killed at ``die_at`` (erase:1 the prepare flash, transfer:3 the
    calibrated block's flash: the prepare flash sends two TransferData, its body and, last, its
    CRC; transfer:2 killed the prepare flash's CRC write): is the error record in the database
    and the report written?"""
    from eol_cal.dyno import sim_dyno as ds
    from eol_cal.dyno.sim_capture import synthetic_source
    from eol_cal.records.query import query_records

    (work / "limits.toml").write_text(LIMITS)
    flash_file = work / "ecu.flash"
    sim_dyno = ds.DynoSim(synthetic_source, serial="K-1")
    with ds.DynoSimThread(sim_dyno, "127.0.0.1", 0) as dyno:
        ecu = _cli(env, "ecu-sim", "--flash-file", str(flash_file), "--listen", "127.0.0.1:0", "--serial", "K-1",
                   "--die-at", die_at)
        url = ecu.stdout.readline().strip()
        died = _died_at(ecu)
        run = _cli(env, "run", "--dyno", f"127.0.0.1:{dyno.port}", "-i", "remote", "-c", url,
                   "--limits", str(work / "limits.toml"), "--db", str(work / "db.sqlite"), "--serial", "K-1",
                   "--key-file", str(base / "key.hex"), "--report-dir", str(work / "reports"),
                   "--spool-dir", str(work / "spool"), "--json")
        _, err = run.communicate(timeout=300)
        end = time.monotonic()
        ecu.kill()
        ecu.wait()
    recs = query_records(work / "db.sqlite") if (work / "db.sqlite").exists() else []
    kept = (len(recs) == 1 and recs[0].verdict == "error"
            and bool(list((work / "reports").rglob("report.json"))))
    t = Trial(f"run, ECU killed at {die_at}", run.returncode, end - (died[0] if died else end),
              sum(line.startswith("error:") for line in err.splitlines()), "Traceback" in err, True, 0, kept)
    return t


def _base(tmp: Path) -> Path:
    key = hmac_seed_to_key(P.DEV_SECRET)
    base = tmp / "base"
    base.mkdir()
    with virtual_rig(base / "base.bin") as rig:
        flash_block(rig.tester, example_block(seed=1), seed_to_key=key, timing=FAST_CLIENT)
    (base / "key.hex").write_text(P.DEV_SECRET.hex())
    (base / "new.bin").write_bytes(example_block(seed=2))
    return base


def _summary(name: str, trials: list[Trial], bound: float) -> None:
    n = len(trials)
    hung = sum(t.rc is None for t in trials)
    within = sum(t.rc is not None and t.seconds <= bound for t in trials)
    clean = sum(t.clean for t in trials)
    tb = sum(t.traceback for t in trials)
    intact = sum(t.old_bank_intact for t in trials)
    worst = max((t.seconds for t in trials if t.rc is not None), default=float("nan"))
    print(f"{name:<34} trials {n:3d}  ended within {bound:.1f} s {within:3d}  hangs {hung:3d}  "
          f"exit 2 + one line {clean:3d}  tracebacks {tb:3d}  old bank intact {intact:3d}  worst {worst:5.2f} s")


def ecu_section(repeat: int, before: str | None, cap: float) -> bool:
    """Run the trials, print the figures; True when every trial ended within the bound with the
    old bank intact and every run kept its record."""
    print(f"\nECU-kill trials: bound max(P2*, S3 + back-off + P2) + 1 s = {BOUND_S:.2f} s (ClientTiming defaults)")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        base = _base(tmp)
        old_bank = NorFlash(base / "base.bin").bank(0)
        env = _env(ROOT)
        cases = [(s, r) for r in range(repeat) for s in KILL_STEPS]
        kills = [kill_flash(env, base, Path(tempfile.mkdtemp(dir=tmp)), s, cap, old_bank) for s, _ in cases]
        with ThreadPoolExecutor(4) as pool:
            signals = list(pool.map(
                lambda c: signal_flash(env, base, Path(tempfile.mkdtemp(dir=tmp)), c[0], c[1], c[2], old_bank),
                [(s, shown, sig) for sig in (signal.SIGINT, signal.SIGTERM) for s, shown in SIGNAL_STEPS]))
        runs = [kill_run(env, base, Path(tempfile.mkdtemp(dir=tmp)), die) for die in ("erase:1", "transfer:3")]
        external = [kill_flash_external(env, base, Path(tempfile.mkdtemp(dir=tmp)), cap, old_bank)
                    for _ in range(repeat)]
        older = []
        if before:
            tree = tmp / "before"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), before],
                           check=True, capture_output=True)
            try:
                for _ in range(repeat):
                    older.append(kill_flash_external(_env(tree), base, Path(tempfile.mkdtemp(dir=tmp)), cap,
                                                     old_bank))
            finally:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                               capture_output=True)
    print()
    _summary("flash, ECU killed at each step", kills, BOUND_S)
    _summary("flash, kill -9 at the erase (ours)", external, BOUND_S)
    if older:
        _summary(f"same, {before} (before)", older, BOUND_S)
    _summary("flash, SIGINT/SIGTERM at each step", signals, BOUND_S)
    print(f"boots after the ECU was killed: old {sum(t.boots == 1 for t in kills)}, new (complete, checked) "
          f"{sum(t.boots == 2 for t in kills)}, other {sum(t.boots not in (1, 2) for t in kills)}; "
          f"after a signal: old {sum(t.boots == 1 for t in signals)}, new {sum(t.boots == 2 for t in signals)}")
    # a run goes on after its flash step failed: the dyno's safe state, the report and the record,
    # which waits for the fit's pre-warm thread (station/steps/acquire_before.py: JAX imports and a solver trace,
    # seconds under load); it is judged against --cap (a hang), not the link's bound
    for t in runs:
        print(f"{t.what:<34} exit {t.rc}  ended {t.seconds:.2f} s after the ECU died  traceback {t.traceback}  "
              f"record and report kept {t.record}")
    ours = kills + external
    within = sum(t.rc is not None and t.seconds <= BOUND_S for t in ours)
    runs_ended = sum(t.rc == 2 and t.seconds <= cap for t in runs)
    kept = sum(bool(t.record) for t in runs)
    print(f"ECU-kill trials {len(ours)} / ended within the bound {within} / runs ended exit 2 within {cap:g} s "
          f"{runs_ended} of {len(runs)} / records kept {kept} of {len(runs)} runs")
    print("\nper trial (ours):")
    for t in kills + signals:
        print(f"  {t.what:<40} exit {t.rc}  {t.seconds:5.2f} s  boots seq {t.boots}")
    intact = all(t.old_bank_intact for t in kills + external + signals)
    return (within == len(ours) and runs_ended == kept == len(runs) and intact
            and not any(t.traceback for t in ours + runs + signals))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="ECU-kill trials per step.")
    ap.add_argument("--before", default="b46ce43", help="Commit to compare with ('' to skip).")
    ap.add_argument("--cap", type=float, default=20.0, help="Seconds after which a trial counts as hung.")
    args = ap.parse_args()
    print(f"# bench_faults_ecu: {platform.python_version()}, {os.cpu_count()} CPUs")
    return 0 if ecu_section(args.repeat, args.before or None, args.cap) else 1


if __name__ == "__main__":
    sys.exit(main())
