"""Running hostile inputs through the real CLI in a child process and judging how it ended
(see :mod:`eol_cal.sim.fuzz`)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from eol_cal.sim import ROOT  # the checkout whose ``cli`` the children run (another one: the code before a change)
from eol_cal.sim.fuzz.mutate import CHILD_MEMORY_BYTES, KINDS, Case, cases

@dataclass
class Outcome:
    """How the CLI ended on one case."""

    case: Case
    command: str
    rc: int | None
    seconds: float
    stderr: str
    traceback: bool
    hang: bool
    crash: bool
    modified: bool
    named: bool
    maxrss_kb: int = 0
    accepted: bool = False

    @property
    def clean(self) -> bool:
        """Ended as the tool promises: 0/1/2, one-line error naming the file, in time, input intact."""
        return not (self.traceback or self.hang or self.crash or self.modified) and (self.accepted or self.named)



# --------------------------------------------------------------------------------------------
# running the CLI


#: eol-cal's parent: a small interpreter that starts it under the address-space limit, passes on
#: the signals sent to it, ends as it ended and reports its peak resident set (KiB) on a pipe.
#: Linux counts in a child's ``ru_maxrss`` the image it was forked from (the high-water mark of the
#: memory it had before exec), so eol-cal forked straight from a test worker of 2 GB reported 2 GB;
#: forked from this ~10 MB process it reports its own.
_LAUNCHER = """\
import os, resource, signal, subprocess, sys
limit, report = int(sys.argv[1]), int(sys.argv[2])
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
state = {"child": None, "pending": [], "reaped": False}
def forward(signum, _frame):
    if state["child"] is None:
        state["pending"].append(signum)
    elif not state["reaped"]:
        try:
            os.kill(state["child"].pid, signum)
        except ProcessLookupError:  # reaped a moment ago
            pass
for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGABRT", "SIGUSR1", "SIGUSR2", "SIGALRM"):
    signal.signal(getattr(signal, name), forward)
try:
    state["child"] = subprocess.Popen(sys.argv[3:])
except OSError as e:
    sys.stderr.write(f"could not start {sys.argv[3]}: {e}\\n")
    os._exit(127)
for signum in state["pending"]:
    os.kill(state["child"].pid, signum)
_, status, usage = os.wait4(state["child"].pid, 0)
state["reaped"] = True  # a late signal must not reach a reused pid
os.write(report, str(usage.ru_maxrss).encode())
if os.WIFSIGNALED(status):
    signum = os.WTERMSIG(status)
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # eol-cal's end already dumped what it dumps
    if signum not in (signal.SIGKILL, signal.SIGSTOP):
        signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)
    os._exit(128 + signum)
os._exit(os.WEXITSTATUS(status))
"""


#: a signalled child: says "go" once Python is up, then runs the program as ``eol-cal`` does
_GO_FIRST = ("import os, runpy, sys; os.write(1, b'go\\n'); sys.argv = ['eol-cal', *sys.argv[1:]]; "
             "runpy.run_module('cli.main', run_name='__main__', alter_sys=True)")

def run_cli(args: list[str], cwd: Path, timeout_s: float, memory_bytes: int = CHILD_MEMORY_BYTES,
            root: Path = ROOT, stdin: str = "", env: dict[str, str] | None = None,
            signal_at: tuple[int, float] | None = None) -> tuple[int | None, str, str, float, int]:
    """Run ``eol-cal ARGS`` (the ``cli`` of checkout ``root``) in a child under an address-space limit,
    with ``stdin`` as its input and ``env`` added to (the station's ``EOL_CAL_*`` variables removed from)
    this process's environment; with ``signal_at = (SIGNUM, S)`` the signal is sent ``S`` seconds
    after the start unless the child ended before.

    Returns (exit code or None when it was killed for running past ``timeout_s``; a negative
    code is the signal that ended it), stdout, stderr, seconds, peak resident memory (KiB).
    """
    child_env = {k: v for k, v in os.environ.items() if not k.startswith("EOL_CAL_") or k == "EOL_CAL_JAX_CACHE"}
    child_env["PYTHONPATH"] = str(root)
    child_env.setdefault("EOL_CAL_JAX_CACHE", "off")
    child_env.update(env or {})
    t0 = time.perf_counter()
    # signalled: the moment counts from Python's start, just before the program's first instruction
    # (no code of the tool's runs before it; the interpreter's own start takes 0.05 to 0.3 s with load)
    program = ["-c", _GO_FIRST] if signal_at is not None else ["-m", "cli.main"]
    report_r, report_w = os.pipe()
    with open(report_r, "rb") as report:
        try:
            proc = subprocess.Popen([sys.executable, "-I", "-S", "-c", _LAUNCHER, str(memory_bytes), str(report_w),
                                     sys.executable, *program, *args], cwd=cwd, stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=child_env,
                                    pass_fds=(report_w,), start_new_session=True)
        finally:
            os.close(report_w)
        rc, out, err, seconds = _ended(proc, stdin, timeout_s, env, signal_at, t0)
        # eol-cal's own peak resident set; 0 where it was killed before its launcher could say
        rss = int(report.read() or 0)
    return rc, out.decode(errors="replace"), err.decode(errors="replace"), seconds, rss


def _ended(proc: subprocess.Popen, stdin: str, timeout_s: float, env: dict[str, str] | None,
           signal_at: tuple[int, float] | None, t0: float) -> tuple[int | None, bytes, bytes, float]:
    ended_at_moment = False
    try:
        if signal_at is not None:
            assert proc.stdout is not None
            go = proc.stdout.readline()  # the interpreter is up: eol-cal's first instruction comes next
            t0 = time.perf_counter()  # the seconds of a signalled run count from here, as its moment does
            try:  # the input goes in at once; the signal comes at its moment if the child still runs
                out, err = proc.communicate(stdin.encode(), timeout=signal_at[1])
            except subprocess.TimeoutExpired:
                if proc.poll() is None:  # still running (not a zombie that ended a moment ago)
                    proc.send_signal(signal_at[0])
                else:  # it ended at its moment: no signal, and its seconds say so (below)
                    ended_at_moment = True
                out, err = proc.communicate(timeout=timeout_s)
            out = go.removeprefix(b"go\n") + out
        else:
            out, err = proc.communicate(stdin.encode(), timeout=timeout_s)
        rc: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        # a hang: where it hangs, from the child's faulthandler (PYTHONFAULTHANDLER in env) on SIGABRT
        with contextlib.suppress(ProcessLookupError, subprocess.TimeoutExpired):
            if (env or {}).get("PYTHONFAULTHANDLER"):
                proc.send_signal(6)
                proc.wait(5)
        with contextlib.suppress(ProcessLookupError):  # the abort above may have ended the group
            os.killpg(proc.pid, 9)
        out, err = proc.communicate()
        rc = None
    seconds = time.perf_counter() - t0
    if ended_at_moment:
        seconds = min(seconds, signal_at[1] if signal_at is not None else seconds)
    return rc, out, err, seconds


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.exists() else "-"


def _commands(kind: str, name: str) -> list[list[str]]:
    if kind in ("csv", "mdf4"):
        return [["analyze", "--json", name]]
    if kind in ("block", "block2"):
        return [["block", "check", name], ["block", "show", "--json", name]]
    return [["table", name, "-o", name + ".out.bin"]]


def judge(case: Case, command: list[str], rc: int | None, stdout: str, stderr: str, seconds: float,
          rss_kb: int, modified: bool) -> Outcome:
    """An :class:`Outcome` from how one command ended."""
    # a MemoryError under RLIMIT_AS is a decoder that believed a size, not a clean refusal
    crash = rc is not None and (rc not in (0, 1, 2) or "MemoryError" in stderr)
    accepted = rc == 0
    return Outcome(case=case, command=" ".join(command), rc=rc, seconds=seconds, stderr=stderr[-2000:],
                   traceback="Traceback" in stderr, hang=rc is None, crash=crash, modified=modified,
                   named=case.name in stderr or case.name in stdout, maxrss_kb=rss_kb, accepted=accepted)


def run_case(case: Case, workdir: Path, timeout_s: float = 20.0,
             memory_bytes: int = CHILD_MEMORY_BYTES, root: Path = ROOT) -> list[Outcome]:
    """Write ``case`` into ``workdir``, run each of its commands, judge each."""
    path = workdir / case.name
    path.write_bytes(case.data)
    before = _digest(path)
    outcomes = []
    for command in _commands(case.kind, case.name):
        rc, out, err, seconds, rss = run_cli(command, workdir, timeout_s, memory_bytes, root)
        after = _digest(path)
        outcomes.append(judge(case, command, rc, out, err, seconds, rss, after != before))
    return outcomes


def run_batch(batch: list[Case], workdir: Path, timeout_s: float = 60.0,
              memory_bytes: int = CHILD_MEMORY_BYTES, root: Path = ROOT) -> list[Outcome]:
    """Captures of one batch in one ``analyze --json`` (one bad file must not cost the others);
    a batch that does not end cleanly is run again file by file to find the culprit."""
    digests = {}
    for case in batch:
        (workdir / case.name).write_bytes(case.data)
        digests[case.name] = _digest(workdir / case.name)
    command = ["analyze", "--json", *(c.name for c in batch)]
    rc, out, err, seconds, rss = run_cli(command, workdir, timeout_s, memory_bytes, root)
    try:
        doc = json.loads(out)
        accepted = {c["file"] for c in doc["captures"]} | {c["file"].split("#")[0] for c in doc["captures"]}
        refused = {e["file"].split("#")[0] for e in doc["errors"]}
    except (ValueError, KeyError, TypeError):
        doc = None
    if doc is None or rc not in (0, 2) or "Traceback" in err or "MemoryError" in out + err:
        return [o for case in batch for o in run_case(case, workdir, timeout_s / len(batch), memory_bytes, root)]
    outcomes = []
    for case in batch:
        modified = _digest(workdir / case.name) != digests[case.name]
        ok = case.name in accepted and case.name not in refused
        outcomes.append(Outcome(case=case, command="analyze --json (batch)", rc=0 if ok else 2, seconds=seconds,
                                stderr="", traceback=False, hang=False, crash=False, modified=modified,
                                named=case.name in refused or ok, maxrss_kb=rss, accepted=ok))
    return outcomes


@dataclass
class Counts:
    """What every fault count has: tried, the must-be-zero counts, the slowest run, the bad outcomes."""

    tried: int = 0
    tracebacks: int = 0
    hangs: int = 0
    crashes: int = 0
    modified: int = 0
    max_seconds: float = 0.0
    bad: list = field(default_factory=list)


@dataclass
class Tally(Counts):
    """Counts over a campaign (the figures ``bench/bench_faults.py`` prints)."""

    accepted: int = 0
    refused_cleanly: int = 0
    unnamed: int = 0
    max_rss_kb: int = 0

    def add(self, outcomes: list[Outcome]) -> None:
        """Count one input (all its commands)."""
        self.tried += 1
        worst = [o for o in outcomes if not o.clean]
        self.tracebacks += any(o.traceback for o in outcomes)
        self.hangs += any(o.hang for o in outcomes)
        self.crashes += any(o.crash for o in outcomes)
        self.modified += any(o.modified for o in outcomes)
        self.unnamed += any(not (o.accepted or o.named) and not (o.traceback or o.hang or o.crash) for o in outcomes)
        if not worst:
            if all(o.accepted for o in outcomes):
                self.accepted += 1
            else:
                self.refused_cleanly += 1
        self.bad.extend(worst)
        self.max_seconds = max([self.max_seconds, *(o.seconds for o in outcomes)])
        self.max_rss_kb = max([self.max_rss_kb, *(o.maxrss_kb for o in outcomes)])


def campaign(seed: int, per_kind: int, workdir: Path, bases: Mapping[str, bytes], kinds: tuple[str, ...] = KINDS,
             batch: int = 10, timeout_s: float = 20.0, memory_bytes: int = CHILD_MEMORY_BYTES,
             root: Path = ROOT) -> dict[str, Tally]:
    """Run a seeded campaign; a :class:`Tally` per kind."""
    tallies = {kind: Tally() for kind in kinds}
    all_cases = cases(seed, per_kind, bases, kinds)
    for kind in kinds:
        mine = [c for c in all_cases if c.kind == kind]
        if kind in ("csv", "mdf4"):
            for i in range(0, len(mine), batch):
                chunk = mine[i:i + batch]
                outcomes = run_batch(chunk, workdir, timeout_s * len(chunk), memory_bytes, root)
                for case in chunk:
                    tallies[kind].add([o for o in outcomes if o.case is case])
        else:
            for case in mine:
                tallies[kind].add(run_case(case, workdir, timeout_s, memory_bytes, root))
    return tallies
