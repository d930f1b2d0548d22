"""Takt time of the end-of-line station: what the station adds to the motor's time on the dyno.

The critical path as users feel it: from the operator's scan (station loop) or the `run` start
(single `eol-cal run` process) to the verdict on screen, minus the profile's physical time (the
shaft turning: ramps, captures and stops, :func:`eol_cal.dyno.setpoints.physical_seconds`, for the
calibration profile and the compensated verification the run chose, each with the lead-in its
record says the shaft turned for the ECU's settling after the flash before it).

The simulators run in this process on 127.0.0.1, at fixed addresses for many motors, as a line's
dyno and ECU are other machines (:func:`eol_cal.sim.loopback.loopback_line`): the dyno simulator in
real time (a capture takes its physical time, the buffer fills as the shaft turns) with the
built-in plant, and the ECU simulator with its bus paced to the CAN bit rate. Each motor gets a
fresh, erased ECU and the next plant draw.

- station loop: one `eol-cal station --station FILE` process (warm) fed serials on stdin, one
  at a time when it asks; the first motor is its warm-up and is not counted;
- single run: one `eol-cal run` process per motor (process start included).

Each setup (register map, bit rate) runs the code to compare with (``--base DIR``, a worktree
of that commit; given more than once, each is a column named by its commit) and this checkout,
alternated, in the same run; ``--read-back both`` adds this checkout with the station setting
``flash.read_back = "off"`` as a further column.

An error run (a cycle that stopped early: a refused pre-flight takes 0.05 s) is printed with what
its record says stopped it and left out of the figures; the bench then exits 1. Twice in twenty runs
on 2026-12-02 the later motors of a station stopped at pre-flight in 0.05 s, and their medians were
printed as the loop's critical path (the one run seen whole: its first motor had stopped with an
error while the simulated plant ran 1.8 s behind real time; the reasons were not kept then).

    python bench/bench_station.py [--base ../takt-base [--base DIR2]] [--motors 3] [--runs 3] \\
        [--setups default@500000,default@1000000,vendor-b@500000] [--profile eol-default] \\
        [--read-back on|off|both]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMITS = ROOT / "fixtures" / "limits.toml"
#: the cycle's steps up to the verdict, in order (what the record's ``steps`` names them)
CRITICAL_STEPS = ("pre-flight", "prepare ECU", "acquire", "fit", "table", "flash", "acquire compensated", "metrics")


#: seconds between two readings of the station process's CPU time (the steps' CPU figures)
SAMPLE_S = 0.02


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


class Screen:
    """A child process's stdout, read as it comes, with the time each piece arrived."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.text = ""
        self.events: list[tuple[float, int]] = []  # (monotonic time, length of text then)
        self.cpu: list[float] = []  # the child's CPU seconds at each event (user + system, all its threads)
        self._cond = threading.Condition()
        self._proc = proc
        self.samples: list[tuple[float, float]] = []  # (wall time, the child's CPU seconds), every SAMPLE_S
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self) -> None:
        while self._proc.poll() is None:
            cpu = self.cpu_now()
            self.samples.append((time.time(), cpu))
            time.sleep(SAMPLE_S)

    def cpu_over(self, t0: float, t1: float) -> float:
        """The child's CPU seconds between wall times ``t0`` and ``t1`` (interpolated between samples)."""
        import numpy as np

        t, c = np.array(self.samples).T
        return float(np.interp(t1, t, c) - np.interp(t0, t, c))

    def _read(self) -> None:
        fd = self._proc.stdout.fileno()
        while True:
            chunk = os.read(fd, 65536)
            now, cpu = time.monotonic(), self.cpu_now()
            with self._cond:
                self.cpu.append(cpu)
                if not chunk:
                    self.events.append((now, -1))
                    self._cond.notify_all()
                    return
                self.text += chunk.decode("utf-8", "replace")
                self.events.append((now, len(self.text)))
                self._cond.notify_all()

    def cpu_now(self) -> float:
        """The child's CPU seconds so far (/proc; its last figure once it has ended)."""
        try:
            fields = Path(f"/proc/{self._proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return self.cpu[-1] if self.cpu else float("nan")
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def cpu_at(self, t: float) -> float:
        """The child's CPU seconds when the output of monotonic time ``t`` came."""
        with self._cond:
            return next(c for (te, _n), c in zip(self.events, self.cpu, strict=True) if te >= t)

    def wait_for(self, pattern: re.Pattern, start: int = 0, timeout: float = 300.0) -> tuple[float, re.Match]:
        """When ``pattern`` first appeared after text position ``start`` (monotonic s), and the match."""
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                m = pattern.search(self.text, start)
                if m is not None:
                    t = next(t for t, n in self.events if n == -1 or n >= m.end())
                    return t, m
                if self.events and self.events[-1][1] == -1:
                    raise RuntimeError(f"process ended before {pattern.pattern!r}; output:\n{self.text[-3000:]}")
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no {pattern.pattern!r} within {timeout} s; output:\n{self.text[-3000:]}")
                self._cond.wait(left)


@dataclass
class Motor:
    """One motor's figures (s)."""

    serial: str
    verdict: str
    wall: float  # scan or process start -> verdict on screen
    physical: float
    steps: dict[str, float]
    before_cycle: float  # scan / process start -> the cycle's start (record started_at)
    tail: float  # verdict on screen -> next serial asked / process exit
    plant_late: float
    load: str
    extra: dict[str, float] = field(default_factory=dict)
    lead_in: float = 0.0  # of ``physical``: the shaft turned for the ECU's settling after each reset
    why: str = ""  # an error run's reasons and error, as its record gives them

    def said(self) -> str:
        """The line printed under an error run's figures: what stopped its cycle."""
        return f"      {self.serial} is an error run, left out of the figures: {self.why}" if self.verdict == "error" else ""

    @property
    def critical(self) -> float:
        return self.wall - self.physical


def eol_cal(code: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "cli.main", *args]


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="160", **(extra or {}))
    env.pop("PYTHONPATH", None)  # each checkout imports its own eol_cal (the working directory comes first)
    return env


def run_dir(reports: Path, serial: str) -> Path:
    (found,) = sorted(reports.glob(f"{serial}_*"))
    return found


def written(path: Path, timeout: float = 300.0) -> Path:
    """``path`` once it exists: the loop writes a run's report and ``report.json`` on its report
    thread after it asked for the next serial (the record itself is in the spool by then)."""
    end = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > end:
            raise TimeoutError(f"{path} not written within {timeout} s")
        time.sleep(0.05)
    return path


def leads_in(rec: dict) -> dict[str, tuple[float, object]]:
    """Each of the run's captures' lead-in for the ECU's settling after a reset: (s at its first
    point, the point turned at first as a ``DynoSetpoint`` or None); (0, None) in records from
    before the lead-in."""
    from eol_cal.dyno.setpoints import DynoSetpoint

    out: dict[str, tuple[float, object]] = {}
    for k, c in (rec.get("captures") or {}).items():
        point = c.get("lead_in_point")
        out[k] = (float(c.get("lead_in_s") or 0.0),
                  None if not point else DynoSetpoint(point["speed_rpm"], point["seconds"]))
    return out


def _ramped(point: object, segs: list) -> object:
    """The lead-in point at the first segment's ramp rate, as the cycle commands it."""
    import dataclasses

    return None if point is None or not segs else dataclasses.replace(point, ramp_rpm_s=segs[0].ramp_rpm_s)


def physical_of(rec: dict, rate_hz: int) -> tuple[float, float, float]:
    """The physical seconds of the run's two acquisitions (0 for one that did not run), and of
    them the lead-ins' (the shaft's time with the lead-in less without it)."""
    from eol_cal.analysis.point_metrics import verify_segments
    from eol_cal.dyno.setpoints import physical_seconds, setpoints_from_profile
    from eol_cal.plant.profile import load_profile

    ran = {s["step"] for s in rec["steps"] if s["seconds"] is not None}
    segs = setpoints_from_profile(load_profile(rec["station"]["profile"]))
    lead = leads_in(rec)
    before = after = lead_s = 0.0
    if "acquire" in ran:
        at_point, point = lead.get("before", (0.0, None))
        before = physical_seconds(segs, rate_hz, at_point, _ramped(point, segs))
        lead_s += before - physical_seconds(segs, rate_hz)
    if "acquire compensated" in ran:
        op = rec["fit"]["operating_point"]
        after_segs = segs if rec["station"]["verify"] == "full" else verify_segments(segs, op["speed_rpm"], op["i_qo_a"])
        at_point, point = lead.get("after", (0.0, None))
        after = physical_seconds(after_segs, rate_hz, at_point, _ramped(point, after_segs))
        lead_s += after - physical_seconds(after_segs, rate_hz)
    return before, after, lead_s


def motor_figures(rec: dict, serial: str, t_start_wall: float, t_verdict_wall: float, tail: float,
                  plant_late: float, load_text: str, rate_hz: int) -> Motor:
    before, after, lead_s = physical_of(rec, rate_hz)
    steps = {s["step"]: s["seconds"] for s in rec["steps"] if s["seconds"] is not None}
    started = dt.datetime.fromisoformat(rec["started_at"]).timestamp()
    crit = {k: v for k, v in steps.items() if k in CRITICAL_STEPS}
    crit["acquire"] = crit.get("acquire", 0.0) - before
    crit["acquire compensated"] = crit.get("acquire compensated", 0.0) - after
    error = rec.get("error") or {}
    why = "; ".join([*(str(r) for r in rec.get("reasons") or []),
                     *([f"error in {error.get('step')}: {error.get('message')}"] if error else [])]) or "no reason recorded"
    return Motor(serial, rec["verdict"], t_verdict_wall - t_start_wall, before + after, crit, started - t_start_wall,
                 tail, plant_late, load_text, {"report": steps.get("report", 0.0), "record": steps.get("record", 0.0)},
                 lead_s, why=why if rec["verdict"] == "error" else "")


def step_cpu(rec: dict, screen: Screen) -> dict[str, float]:
    """Each step's CPU seconds (the station process, all its threads), over the step's wall span:
    the steps run one after the other from the record's start."""
    t = dt.datetime.fromisoformat(rec["started_at"]).timestamp()
    out: dict[str, float] = {}
    for s in rec["steps"]:
        if s["seconds"] is None:
            continue
        out[f"cpu {s['step']}"] = screen.cpu_over(t, t + s["seconds"])
        t += s["seconds"]
    return out


def settings_file(work: Path, line, map_name: str, key: Path, profile: str) -> Path:
    path = work / "station.toml"
    path.write_text("\n".join([
        'station_id = "BENCH"',
        f'limits = "{LIMITS}"',
        f'db = "{work / "results.sqlite"}"',
        f'report_dir = "{work / "reports"}"',
        f'spool_dir = "{work / "spool"}"',
        f'key_file = "{key}"',
        f'profile = "{profile}"',
        "[dyno]",
        f'address = "{line.dyno_address}"',
        f'register_map = "{map_name}"',
        "[can]",
        'interface = "remote"',
        f'channel = "{line.can_channel}"',
        "",
    ]))
    return path


def plant_late(line) -> float:
    return sum(c.source_late_s for c in list(line.dyno.sim.captures))


def station_loop(code: Path, line, work: Path, map_name: str, key: Path, profile: str, motors: int,
                 rate_hz: int, first_seed: int, env: dict[str, str] | None = None) -> list[Motor]:
    """``motors`` + 1 motors through one `eol-cal station` process; the first one is not counted."""
    settings = settings_file(work, line, map_name, key, profile)
    err = open(work / "station.stderr", "w")  # noqa: SIM115 - the child's stderr; closed after its run
    proc = subprocess.Popen(eol_cal(code, "station", "--station", str(settings), "--operator", "bench"),
                            cwd=code, env=child_env(env), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err)
    screen = Screen(proc)
    prompt = re.compile(r"Scan serial")
    out: list[Motor] = []
    pos = 0
    try:
        t_prompt, m = screen.wait_for(prompt, pos, timeout=120)
        pos = m.end()
        for k in range(motors + 1):
            serial = f"L{first_seed + k:04d}"
            line.load(serial, first_seed + k)
            load_text = load()
            t_scan, t_scan_wall, cpu_scan = time.monotonic(), time.time(), screen.cpu_now()
            proc.stdin.write(f"{serial}\n".encode())
            proc.stdin.flush()
            t_verdict, m = screen.wait_for(re.compile(rf"{serial}: (PASS|FAIL|ERROR)"), pos)
            pos = m.end()
            t_next, m = screen.wait_for(prompt, pos)
            pos = m.end()
            rec = json.loads(written(run_dir(work / "reports", serial) / "report.json").read_text())
            fig = motor_figures(rec, serial, t_scan_wall, t_scan_wall + (t_verdict - t_scan), t_next - t_verdict,
                                plant_late(line), load_text, rate_hz)
            fig.extra.update(cpu_cycle=screen.cpu_at(t_verdict) - cpu_scan,
                             cpu_tail=screen.cpu_at(t_next) - screen.cpu_at(t_verdict), **step_cpu(rec, screen))
            print(f"    loop {serial}{' (warm-up)' if k == 0 else ''}: {fig.verdict}, scan->verdict {fig.wall:.2f} s "
                  f"(CPU {fig.extra['cpu_cycle']:.2f} s), verdict->next scan CPU {fig.extra['cpu_tail']:.2f} s, "
                  f"physical {fig.physical:.2f}, critical {fig.critical:.2f}, verdict->next scan {fig.tail:.2f}, "
                  f"plant late {fig.plant_late:.2f}, load {load_text}", flush=True)
            if fig.said():
                print(fig.said(), flush=True)
            if k:
                out.append(fig)
        proc.stdin.write(b"q\n")
        proc.stdin.flush()
        proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
        err.close()
    return out


def single_runs(code: Path, line, work: Path, map_name: str, key: Path, profile: str, runs: int,
                rate_hz: int, first_seed: int, env: dict[str, str] | None = None) -> list[Motor]:
    out: list[Motor] = []
    work.mkdir(parents=True, exist_ok=True)
    for k in range(runs):
        serial = f"S{first_seed + k:04d}"
        line.load(serial, first_seed + k)
        cmd = eol_cal(code, "run", "--dyno", line.dyno_address, "--interface", "remote", "--channel", line.can_channel,
                      "--limits", str(LIMITS), "--db", str(work / "results.sqlite"), "--serial", serial,
                      "--profile", profile, "--key-file", str(key), "--report-dir", str(work / "reports"),
                      "--spool-dir", str(work / "spool"), "--register-map", map_name)
        load_text = load()
        t0, t0_wall = time.monotonic(), time.time()
        with open(work / f"{serial}.stderr", "w") as err:
            proc = subprocess.Popen(cmd, cwd=code, env=child_env(env), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                    stderr=err)
            screen = Screen(proc)
            try:
                t_verdict, _m = screen.wait_for(re.compile(rf"{serial}(?::\s+|\s+)(pass|fail|error)\b", re.I))
                rc = proc.wait(300)
            finally:
                if proc.poll() is None:
                    proc.kill()
        t_exit = time.monotonic()
        if rc not in (0, 1):
            raise RuntimeError(f"eol-cal run exit {rc}: {(work / f'{serial}.stderr').read_text()[-2000:]}")
        rec = json.loads((run_dir(work / "reports", serial) / "report.json").read_text())
        fig = motor_figures(rec, serial, t0_wall, t0_wall + (t_verdict - t0), t_exit - t_verdict, plant_late(line),
                            load_text, rate_hz)
        fig.extra.update(cpu_cycle=screen.cpu_at(t_verdict), cpu_tail=screen.cpu[-1] - screen.cpu_at(t_verdict),
                         **step_cpu(rec, screen))
        print(f"    run {serial}: {fig.verdict}, start->verdict {fig.wall:.2f} s (CPU {fig.extra['cpu_cycle']:.2f} s), "
              f"verdict->exit CPU {fig.extra['cpu_tail']:.2f} s, physical {fig.physical:.2f}, "
              f"critical {fig.critical:.2f}, verdict->exit {fig.tail:.2f}, plant late {fig.plant_late:.2f}, "
              f"load {load_text}", flush=True)
        if fig.said():
            print(fig.said(), flush=True)
        out.append(fig)
    return out


def med(values: list[float]) -> str:
    return f"{statistics.median(values):6.2f} ({min(values):.2f}-{max(values):.2f})" if values else "-"


def measured(motors: list[Motor]) -> list[Motor]:
    """The motors whose cycle ran to a pass or fail: an error run stops early (a refused pre-flight
    takes 0.05 s), so its critical path is no figure of the loop."""
    return [m for m in motors if m.verdict != "error"]


def report(results: dict[tuple[str, str, str], list[Motor]], codes: list[str]) -> int:
    """Print the figures; returns the number of error runs left out of them."""
    setups = sorted({s for s, _c, _m in results}, key=lambda s: list(dict.fromkeys(s for s, _c, _m in results)).index(s))
    print("\n## Critical path beyond the physical time, median (min-max) s per motor")
    print(f"{'setup':<22}{'mode':<14}" + "".join(f"{c:>26}" for c in codes))
    for setup in setups:
        for mode in ("station loop", "eol-cal run"):
            cells = [med([m.critical for m in measured(results.get((setup, c, mode), []))]) for c in codes]
            print(f"{setup:<22}{mode:<14}" + "".join(f"{x:>26}" for x in cells))
    errors = 0
    for (setup, code, mode), every in results.items():
        motors = measured(every)
        errors += len(every) - len(motors)
        if not every:
            continue
        print(f"\n### {setup}, {mode}, {code}: {len(every)} motors, verdicts "
              f"{','.join(m.verdict for m in every)}, load {every[0].load} .. {every[-1].load}")
        for m in every:
            if m.said():
                print(m.said())
        if not motors:
            print("no motor's cycle ran to a pass or fail: no figures")
            continue
        rows = [("scan/start -> verdict on screen", [m.wall for m in motors]),
                ("physical time (shaft turning)", [m.physical for m in motors]),
                ("  of which lead-in (ECU settling)", [m.lead_in for m in motors]),
                ("critical path beyond physical", [m.critical for m in motors]),
                ("  start -> cycle start", [m.before_cycle for m in motors])]
        for step in CRITICAL_STEPS:
            label = f"  {step}" + (" beyond physical" if step.startswith("acquire") else "")
            rows.append((label, [m.steps.get(step, 0.0) for m in motors]))
        rows.append(("  metrics end -> verdict on screen",
                     [m.critical - m.before_cycle - sum(m.steps.get(s, 0.0) for s in CRITICAL_STEPS) for m in motors]))
        rows.append(("  (plant later than real time)", [m.plant_late for m in motors]))
        rows.append(("verdict -> next scan / exit", [m.tail for m in motors]))
        rows.append(("  report step (record)", [m.extra["report"] for m in motors]))
        if all("cpu_cycle" in m.extra for m in motors):
            rows.append(("CPU s, scan -> verdict (all threads)", [m.extra["cpu_cycle"] for m in motors]))
            rows.append(("CPU s, verdict -> next scan", [m.extra["cpu_tail"] for m in motors]))
            for step in (*CRITICAL_STEPS, "report"):
                rows.append((f"  CPU s, {step}", [m.extra.get(f"cpu {step}", 0.0) for m in motors]))
        for label, values in rows:
            print(f"{label:<40}{med(values)}")
    return errors


def short_rev(path: Path) -> str:
    """The checkout's commit, short."""
    return subprocess.run(["git", "-C", str(path), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", type=Path, action="append", default=[],
                    help="checkout of the code to compare with (a git worktree); again for another column")
    ap.add_argument("--motors", type=int, default=3, help="counted motors per station loop (after one warm-up)")
    ap.add_argument("--runs", type=int, default=3, help="single `eol-cal run` processes per setup")
    ap.add_argument("--setups", default="default@500000,default@1000000,vendor-b@500000",
                    help="register map @ CAN bit rate, comma-separated")
    ap.add_argument("--modes", default="loop,run", help="loop, run or both")
    ap.add_argument("--profile", default="eol-default")
    ap.add_argument("--read-back", choices=("on", "off", "both"), default="on",
                    help="this checkout's station setting flash.read_back: before-crc (on, the default), off, or "
                         "both as two columns")
    args = ap.parse_args()

    import logging

    from cli.fit import enable_jax_cache
    from eol_cal.dyno.mapfile import load_register_map
    from eol_cal.ecu import protocol as P
    from eol_cal.sim.loopback import loopback_line
    from eol_cal.records.limits import load_limits

    for name in ("pymodbus", "isotp", "UdsClient", "Connection", "can", "can_remote"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    from eol_cal.numerics.xla import configure_xla

    configure_xla()  # the simulators' plant in this process, as `eol-cal dyno-sim` runs it
    enable_jax_cache()  # the simulators' plant in this process
    # each column: a checkout and the environment its processes get (the settings' variables)
    codes: dict[str, tuple[Path, dict[str, str]]] = {}
    for base in args.base:  # one base: "today", as before; several: each named by its commit
        codes["today" if len(args.base) == 1 else f"base {short_rev(base)}"] = (base.resolve(), {})
    if args.read_back in ("on", "both"):
        codes["ours"] = (ROOT, {})
    if args.read_back in ("off", "both"):
        codes["ours, no read-back"] = (ROOT, {"EOL_CAL_FLASH_READ_BACK": "off"})
    rev = {name: short_rev(path) for name, (path, _env) in codes.items()}
    print(f"# {platform.node()} {platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
          f"profile {args.profile}, real-time dyno, load {load()}; code: "
          + ", ".join(f"{n} {rev[n]} ({p})" for n, (p, _env) in codes.items()), flush=True)
    modes = [m for m in args.modes.split(",") if m]
    results: dict[tuple[str, str, str], list[Motor]] = {}
    warmed: set[Path] = set()
    with tempfile.TemporaryDirectory(prefix="bench-station-") as tmp:
        tmp = Path(tmp)
        key = tmp / "key.hex"
        key.write_text(P.DEV_SECRET.hex())
        for i, setup in enumerate(args.setups.split(",")):
            map_name, _, bitrate = setup.partition("@")
            regmap = load_register_map(map_name)
            # the plant's programs ready before the dyno simulator serves, as the demo's are (a real dyno's
            # data is never late): its first motor's capture then holds no compile
            with loopback_line(tmp / f"sim-{map_name}-{bitrate}", register_map=regmap, realtime=True,
                               bitrate=int(bitrate), prepare=load_limits(LIMITS).estimator_options) as line:
                print(f"\n# setup {setup}: dyno {line.dyno_address} ({regmap.name}), ECU {line.can_channel} "
                      f"paced to {int(bitrate)} bit/s", flush=True)
                for j, mode in enumerate(modes):
                    seed = 1 + 100 * (len(modes) * i + j)  # the same motors for both checkouts
                    for name, (code, env) in codes.items():  # today, then ours: alternated within each mode
                        work = tmp / f"{setup.replace('@', '-')}-{mode}-{name.replace(', ', '-').replace(' ', '_')}"
                        work.mkdir()
                        label = "station loop" if mode == "loop" else "eol-cal run"
                        if mode == "run" and code not in warmed:  # JAX's and the OS's caches, not counted
                            print(f"  warm-up run, {name}:", flush=True)
                            single_runs(code, line, work / "warm-up", map_name, key, args.profile, 1, 10000, 9000, env)
                            warmed.add(code)
                        print(f"  {label}, {name}:", flush=True)
                        if mode == "loop":
                            got = station_loop(code, line, work, map_name, key, args.profile, args.motors, 10000, seed,
                                               env)
                        else:
                            got = single_runs(code, line, work, map_name, key, args.profile, args.runs, 10000, seed, env)
                        results[(setup, name, label)] = got
    errors = report(results, list(codes))
    print(f"\n# load at the end {load()}")
    if errors:
        print(f"# {errors} error run(s) left out of the figures (their reasons above): the run is not a measurement "
              "of the loop as it should be", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
