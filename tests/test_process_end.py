"""How an ``eol-cal`` process ends once its outcome is decided (cli.main): with the decided exit
status, and a signal up to the very end is exit 2.

Python's teardown after the last atexit handler used to run with the signal handlers reset: a
signal there was ignored and the status stayed the verdict (the fault bench's "missed" signals),
or killed the process by the signal. ``cli.main.end_process`` ends the process at the last atexit
handler instead, so the teardown (where a module's finalizer would still run) never comes.

Each case is a real process running ``cli.main.main`` with one extra command.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# an extra command for each case; a module-global finalizer that would speak in the teardown
SCRIPT = textwrap.dedent("""
    import atexit, os, signal, sys, time
    import click
    from cli import main as m
    from cli.common import CommandExit, handle_errors

    class SaysAtTeardown:
        def __del__(self):
            sys.stderr.write("teardown ran\\n")

    kept = SaysAtTeardown()

    @click.command("case")
    @click.argument("what")
    @handle_errors
    def case(what):
        if what == "pass":
            click.echo("verdict: pass")
        elif what == "fail":
            click.echo("verdict: fail")
            raise CommandExit(1)
        elif what == "bug":
            raise ValueError("a bug")
        elif what == "message":
            sys.exit("a message")
        elif what == "late-signal":
            # registered after main's: runs before its last handler, the verdict already said
            def late():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)  # the signal ends the process before this ends
            atexit.register(late)
            click.echo("verdict: fail")
            raise CommandExit(1)

    m.cli.add_command(case)
    sys.argv = ["eol-cal", "case", sys.argv[1]]
    m.main()
""")


def _end(what: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT, what], capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("what, status", [("pass", 0), ("fail", 1)])
def test_the_decided_status_ends_the_process_without_the_teardown(what, status):
    res = _end(what)
    assert res.returncode == status, res.stderr
    assert f"verdict: {what}" in res.stdout  # said before the end, and flushed
    assert "teardown ran" not in res.stderr


@pytest.mark.parametrize("what, words", [("bug", "ValueError: a bug"), ("message", "a message")])
def test_a_bug_or_a_message_is_still_said_with_exit_1(what, words):
    res = _end(what)
    assert res.returncode == 1 and words in res.stderr, res.stderr


def test_a_signal_after_the_verdict_is_said_is_exit_2():
    res = _end("late-signal")
    assert res.returncode == 2, res.stderr
    assert "verdict: fail" in res.stdout and "Traceback" not in res.stderr, res.stderr
