"""``eol-cal acquire`` (run a test profile on a Modbus TCP dyno) and ``eol-cal dyno-sim``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from cli.common import (CommandExit, console, err_console, exchange_log_options, handle_errors, loop_kernels,
                        print_json)
from cli.ecu import bus_options, open_cli_bus
from cli.paths import io_paths

if TYPE_CHECKING:
    from eol_cal.dyno.sim_dyno import FaultPlan

_SUFFIXES = (".csv", ".mf4")


def register_map_option(func):
    """``--register-map FILE|NAME``: the dyno's register map (a TOML file, or a map shipped with eol-cal)."""
    return click.option("--register-map", "register_map", default="default", show_default=True, metavar="FILE|NAME",
                         help="The dyno's register map: a map file (docs/dyno.md, 'Writing a register map') or a "
                              "shipped map's name (default, vendor-b).")(func)


def realtime_option(func):
    """``--realtime``: the dyno simulator takes a capture's physical time (docs/dyno.md, "The simulator")."""
    return click.option("--realtime", is_flag=True,
                        help="Real-time dyno: a capture takes its physical time and its buffer fills as the shaft "
                             "turns (reads of samples not recorded yet wait), as on a real dyno.")(func)


def load_map(spec: str):
    """The register map a command was given (an :class:`~eol_cal.errors.InputError` names the file and key)."""
    from eol_cal.dyno.mapfile import load_register_map

    return load_register_map(spec)


def _quiet_pymodbus() -> None:
    from eol_cal.infra.exchange_log import quiet

    # pymodbus logs every retried request at ERROR; the command reports failures itself
    quiet(("pymodbus",))


@click.command("acquire")
@click.option("--dyno", "address", required=True, metavar="HOST[:PORT]",
              help="Modbus TCP address of the dyno (port 502 when none is given).")
@click.option("--profile", default="eol-default", show_default=True, help="Built-in test profile name or a TOML profile file.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Capture file (.csv or .mf4), written atomically.")
@click.option("--serial", default=None, help="Motor serial (default: the serial the dyno reports).")
@click.option("--rate", "rate_hz", type=click.IntRange(1, 1_000_000), default=10000, show_default=True,
              help="Capture sample rate (Hz).")
@click.option("--timeout", type=click.FloatRange(0.01, 60.0), default=1.0, show_default=True,
              help="Per-request timeout (s).")
@click.option("--retries", type=click.IntRange(0, 20), default=3, show_default=True,
              help="Retries per request (reconnecting in between).")
@click.option("--connections", type=click.IntRange(1, 16), default=4, show_default=True,
              help="Parallel connections for the capture transfer.")
@click.option("--all-channels", is_flag=True,
              help="Also read temperature and the dq and phase currents (temp, iq, id, ia, ib, ic).")
@click.option("--reset-faults", is_flag=True, help="Clear faults latched on the dyno before the run.")
@click.option("--split-windows", is_flag=True,
              help="Also write each segment's window as its own capture (OUT.wN.mf4): an angle must be reconstructed "
                   "per window.")
@click.option("--json", "as_json", is_flag=True, help="Print a JSON summary instead of text.")
@register_map_option
@bus_options
@handle_errors
@exchange_log_options
@io_paths(inputs=("profile", "can_config"), outputs=("output",))
def acquire_cmd(address, profile, output, serial, rate_hz, timeout, retries, connections, all_channels, reset_faults,
                split_windows, as_json, register_map, interface, channel, bitrate, can_config) -> None:
    """Run a test profile on the dyno and write the capture.

    Segment by segment: set point, wait until at speed, capture, read the buffer. On any error
    the speed goes to 0, the drive is disabled and no capture file is written (exit code 2).
    The segments' windows are joined with gaps in time (metadata segment_starts); they are not
    one continuous recording.

    With the ECU's bus (--interface/--channel or --can-config) the ECU's active block is read
    over UDS before and after the acquisition into the capture (metadata ecu_before.*,
    ecu_after.*); without it the capture has no record of the ECU state, and `eol-cal fit`
    refuses it unless told otherwise.
    """
    import time

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from eol_cal.dyno.client import parse_address
    from eol_cal.dyno.profile_run import DEFAULT_CHANNELS, EXTRA_CHANNELS
    from eol_cal.dyno.setpoints import setpoints_from_profile
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.errors import InputError, naming
    from eol_cal.plant.profile import load_profile
    from eol_cal.station.acquisition import acquire_traced

    if output.suffix.lower() not in _SUFFIXES:
        raise InputError(str(output), None, f"unknown capture format {output.suffix!r}; use .csv or .mf4")
    if not output.parent.is_dir():
        raise InputError(str(output), None, "directory does not exist")
    host, port = parse_address(address)
    regmap = load_map(register_map)
    prof = load_profile(profile)
    with naming(profile if Path(profile).is_file() else None):  # a segment the dyno cannot run: the profile file named
        segments = setpoints_from_profile(prof)
    channels = DEFAULT_CHANNELS + (EXTRA_CHANNELS if all_channels else ())
    config = DynoConfig(host=host, port=port, timeout=timeout, retries=retries, connections=connections,
                        register_map=regmap)
    _quiet_pymodbus()
    t0 = time.perf_counter()
    with Progress(
        TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn(),
        console=err_console, transient=True, disable=as_json,
    ) as bar:
        seg_task = bar.add_task("profile", total=len(segments))
        xfer_task = bar.add_task("transfer", total=1)

        def progress(what: str, done: float, total: float) -> None:
            if what == "transfer":
                bar.update(xfer_task, completed=done, total=total)
            else:
                bar.update(seg_task, description=what, completed=done)

        read_ecu = None
        if interface is not None or can_config is not None:
            from eol_cal.ecu.client import ClientTiming
            from eol_cal.station.acquisition import read_ecu_with

            read_ecu = read_ecu_with(lambda: open_cli_bus(interface, channel, bitrate, can_config), ClientTiming())
        capture, trace = acquire_traced(read_ecu, config, segments, output, serial=serial, rate_hz=rate_hz,
                                        channels=channels, progress=progress, reset_faults=reset_faults,
                                        extra_metadata={"comment": f"eol-cal acquire, profile {prof.name}"})
    windows = []
    if split_windows:
        from eol_cal.capture import write_capture
        from eol_cal.capture.windows import split_windows as windows_of

        for i, window in enumerate(windows_of(capture), start=1):
            path = output.with_name(f"{output.stem}.w{i}{output.suffix}")
            write_capture(window, path)
            windows.append(str(path))
    wall = time.perf_counter() - t0
    summary = {
        "schema": "eol-cal/acquire/1",
        "output": str(output),
        "serial": capture.serial,
        "profile": prof.name,
        "segments": len(segments),
        "samples": int(len(capture.t)),
        "rate_hz": rate_hz,
        "channels": sorted(capture.channels),
        "windows": windows,
        "wall_s": round(wall, 3),
        "ecu": trace.to_dict() if trace.traced else None,
    }
    if as_json:
        print_json(summary)
    else:
        console.print(f"wrote {output}: {summary['samples']} samples, {len(segments)} segments, "
                      f"serial {summary['serial']}, {wall:.2f} s; {trace.describe()}")


def parse_fault_plan(text: str) -> FaultPlan:
    """``--fault KIND[@capture:N|@read:N][/MS]`` -> a dyno :class:`~eol_cal.dyno.sim_dyno.FaultPlan`
    (e.g. ``disconnect@read:5/300``)."""
    from eol_cal.dyno.registers import SimFault
    from eol_cal.dyno.sim_dyno import FaultPlan
    from eol_cal.errors import InputError

    names = {"disconnect": SimFault.DISCONNECT, "over-speed": SimFault.OVER_SPEED, "torque-sensor": SimFault.TORQUE_SENSOR}
    spec, _, ms = text.partition("/")
    kind, _, when = spec.partition("@")
    if kind not in names:
        raise InputError(None, "--fault", f"unknown fault {kind!r}; known: {', '.join(names)}")
    at, index = "capture", 1
    if when:
        at, _, n = when.partition(":")
        if at not in ("capture", "read") or not n.isdigit() or int(n) < 1:
            raise InputError(None, "--fault", f"bad trigger {when!r}; use capture:N or read:N (N >= 1)")
        index = int(n)
    if ms and (not ms.isdigit() or not 0 < int(ms) < 65536):
        raise InputError(None, "--fault", f"bad duration {ms!r}; milliseconds 1..65535")
    return FaultPlan(names[kind], at, index, int(ms) if ms else 500)


@click.command("dyno-sim")
@click.option("--listen", default="127.0.0.1:5020", show_default=True, metavar="HOST:PORT",
              help="Address to serve Modbus TCP on (port 0: any free port).")
@click.option("--ecu-flash", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The ECU simulator's flash file: its active bank sets the motor's compensation.")
@click.option("--seed", type=click.IntRange(0), default=None,
              help="Draw the motor from the plant's production tolerances with this seed (default: the preset motor as is).")
@click.option("--serial", default="M-0001", show_default=True, help="Serial of the simulated motor.")
@click.option("--source", type=click.Choice(["plant", "synthetic"]), default="plant", show_default=True,
              help="plant: the built-in JAX plant with the ECU's mode; synthetic: the analytic model (fast, no ECU).")
@click.option("--fault", "faults", multiple=True, metavar="KIND[@capture:N|@read:N][/MS]",
              help="Inject a fault by itself: disconnect, over-speed or torque-sensor, at the N-th capture or window read "
                   "(repeatable).")
@realtime_option
@register_map_option
@handle_errors
def dyno_sim_cmd(listen, ecu_flash, seed, serial, source, faults, realtime, register_map) -> None:
    """Serve a simulated dyno with the motor on it over Modbus TCP (register map: docs/dyno.md).

    Binds 127.0.0.1 unless told otherwise. Stop with Ctrl-C.
    """
    import asyncio
    import threading
    import time

    from eol_cal.dyno import sim_dyno as ds
    from eol_cal.dyno.sim_capture import CaptureRequest, synthetic_source
    from eol_cal.dyno.registers import DutCmdKind
    from eol_cal.errors import InputError
    from eol_cal.domain.motor_params import load_motor

    from eol_cal.infra.address import parse_host_port

    host, port = parse_host_port(listen, "listen", any_port=True)
    if not serial or len(serial.encode("ascii", "replace")) > 16:
        raise InputError(None, "--serial", "1 to 16 ASCII characters")
    plans = [parse_fault_plan(f) for f in faults]
    regmap = load_map(register_map)
    motor = load_motor("paper")
    if source == "plant":
        from cli.fit import enable_jax_cache

        loop_kernels()  # the plant's tick loop as one kernel, before its first computation

        if seed is not None:
            try:
                import eol_cal.plant.variation  # noqa: F401
            except ImportError:
                raise InputError(None, "--seed",
                                 "motor variation (eol_cal.plant.variation) is not available in this build") from None

        from eol_cal.sim.rig import plant_source

        enable_jax_cache()
        capture_source = plant_source(ecu_flash)
    else:
        capture_source = synthetic_source
    sim = ds.DynoSim(capture_source, serial=serial, motor=motor, seed=seed, faults=plans, register_map=regmap,
                     realtime=realtime)

    def started(bound: int) -> None:
        err_console.print(f"dyno simulator on {host}:{bound} (Modbus TCP, register map {regmap.name!r}), "
                          f"motor {serial}, source {source}"
                          + (", real time" if realtime else "")
                          + (f", ECU flash {ecu_flash}" if ecu_flash else ""))
        if source == "plant":
            threading.Thread(target=warm_up, name="plant-warm-up", daemon=True).start()

    def warm_up() -> None:
        # compile the plant now rather than in the first capture (the client's capture timeout)
        t0 = time.perf_counter()
        try:
            capture_source(CaptureRequest(60.0, DutCmdKind.IQ, 0.0, 100, 10000.0, serial, seed, 0))
        except Exception as exc:  # noqa: BLE001 - the first real capture reports it properly
            err_console.print(f"plant warm-up failed: {exc}")
            return
        from eol_cal.numerics.xla import loop_kernel_on

        how = "its tick loop one XLA kernel" if loop_kernel_on() else "XLA's default loops"
        err_console.print(f"plant ready ({time.perf_counter() - t0:.1f} s; {how})")

    _quiet_pymodbus()
    try:
        asyncio.run(sim.serve(host, port, started))
    except KeyboardInterrupt:  # how a simulator is stopped: exit 0
        from eol_cal.infra import interrupts

        interrupts.handled()
    except (OSError, RuntimeError) as exc:
        raise InputError(None, "--listen", f"cannot listen on {listen}: {exc}") from None


@click.command("dyno-clear")
@click.option("--dyno", "address", required=True, metavar="HOST[:PORT]",
              help="Modbus TCP address of the dyno (port 502 when none is given).")
@click.option("--yes", is_flag=True, help="Confirmed beforehand (no question): clear whatever fault is latched.")
@click.option("--timeout", type=click.FloatRange(0.01, 60.0), default=1.0, show_default=True,
              help="Per-request Modbus timeout (s).")
@register_map_option
@handle_errors
@exchange_log_options
def dyno_clear_cmd(address, yes, timeout, register_map) -> None:
    """Clear a fault latched on the dyno (its watchdog, over-speed, torque sensor) once the operator confirms.

    Reads the faults first; with none latched nothing is written (exit 0). Otherwise it asks
    (type yes; --yes answers beforehand), and only at standstill sets the speed to 0, disables
    the drive and writes the register map's fault_reset (nothing is started). Exit 0 cleared,
    1 a fault latched again (its cause persists: see the dyno), 2 not confirmed, unreachable,
    or the shaft turns.
    """
    import sys

    from eol_cal.dyno.client import parse_address
    from eol_cal.dyno.recover import clear_faults, inspect_faults
    from eol_cal.dyno.transfer import DynoConfig
    from eol_cal.errors import InputError

    host, port = parse_address(address)
    config = DynoConfig(host=host, port=port, timeout=timeout, register_map=load_map(register_map))
    _quiet_pymodbus()
    before = inspect_faults(config)
    if not before.latched:
        _show_faults(address, before, None)
        return
    if not yes:
        err_console.print(f"dyno {address}: {before.describe()}")
        sys.stderr.write("Clear it? The drive stays disabled and nothing is started; check the dyno first. Type yes: ")
        sys.stderr.flush()
        answer = sys.stdin.readline().strip().lower()
        if answer != "yes":
            raise InputError(None, "confirmation", f"{answer!r}, not yes: nothing was written to the dyno")
    before, after = clear_faults(config)
    _show_faults(address, before, after)
    if after.latched:
        raise CommandExit(1)


def _show_faults(address: str, before, after) -> None:
    if after is None:
        console.print(f"dyno {address}: no fault latched ({before.describe()}); nothing was written")
    elif after.latched:
        console.print(f"dyno {address}: still latched after the reset: {after.describe()}; its cause persists")
    else:
        console.print(f"dyno {address}: cleared (was {before.describe()}); the drive is disabled until the next run")


COMMANDS = [acquire_cmd, dyno_sim_cmd, dyno_clear_cmd]
