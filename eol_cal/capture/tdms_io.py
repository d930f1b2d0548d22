"""NI TDMS captures (LabVIEW, DAQmx) read with npTDMS (capture format v1, "TDMS").

A TDMS file holds groups of channels. A channel is named in a channel map as ``"Group/Channel"``,
or by its own name alone when no other group has a channel of that name. Units come from each
channel's ``unit_string`` property (or the map), metadata from the file's root properties.

Time: when the map names a ``t`` channel (or the file has one called ``t``), every channel used
shares its rows and must be as long. Otherwise each channel is a waveform on its own time base,
``wf_start_offset + k * wf_increment`` (the map's ``[file] sample_rate`` for a channel without
``wf_increment``), channels that state a ``wf_start_time`` put on one clock by it; then, as for
MDF4, everything goes on the torque channel's time base (:func:`eol_cal.capture.columns.assemble`).

Before any data is read the file's metadata is read and checked: npTDMS reports a truncated or
damaged file only as a logged warning and reads what it can, so any warning is refused here; a
channel that declares more values than the file could hold is refused before its array is made.
Only the channels the capture uses are read.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from nptdms import TdmsFile
from nptdms.log import log_manager

from eol_cal.capture.channel_map import ChannelMap, apply_channel_map, foreign_channel, missing_source
from eol_cal.capture.columns import Column, assemble
from eol_cal.capture.file_options import MAX_SAMPLE_RATE
from eol_cal.capture.metadata import KEY_PATTERN, MetaValue, coerce_value, decode_value, split_truth
from eol_cal.capture.data import CANONICAL_CHANNELS, Capture
from eol_cal.errors import InputError
from eol_cal.infra.inputs import check_regular


#: bytes of a TDMS segment's lead-in (tag, flags, version, two offsets)
_LEAD_IN_BYTES = 28


class _Warnings(logging.Filter):
    """Keeps npTDMS's warnings (and drops them from its console handler)."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            self.messages.append(record.getMessage())
        return False


@contextlib.contextmanager
def _refusing_warnings(file: str) -> Iterator[None]:
    """Turn npTDMS's warnings (truncated segment, incomplete metadata, ...) into a refusal."""
    caught = _Warnings()
    loggers = list(log_manager.loggers.values())
    for logger in loggers:
        logger.addFilter(caught)
    try:
        yield
    finally:
        for logger in loggers:
            logger.removeFilter(caught)
        if caught.messages:
            raise InputError(file, None, f"truncated or damaged TDMS file: {caught.messages[0]}")


def _property_value(key: str, value: object, file: str) -> MetaValue:
    if isinstance(value, str):
        return decode_value(key, value, file)
    if isinstance(value, (bool, np.bool_)):
        return coerce_value(key, int(value), file)
    if isinstance(value, (int, np.integer)):
        return coerce_value(key, int(value), file)
    if isinstance(value, (float, np.floating)):
        return coerce_value(key, float(value), file)
    return coerce_value(key, str(value), file)  # a time stamp: its ISO text


def _root_properties(tdms: Any, file: str) -> dict[str, MetaValue]:
    """The file's root properties as metadata; a property whose name is not a metadata key
    (``NI_ExpStartTimeStamp`` is one, ``my key`` is not) is left out."""
    return {key: _property_value(key, value, file) for key, value in tdms.properties.items()
            if isinstance(key, str) and KEY_PATTERN.match(key)}


def _source_names(channels: list[Any], channel_map: ChannelMap | None, file: str) -> dict[str, Any]:
    """Source name -> npTDMS channel for the channels the capture uses: the map's (``Group/Channel``,
    or the bare name where it is unique) and the canonical names the map does not claim."""
    by_path = {f"{c.group_name}/{c.name}": c for c in channels}
    by_name: dict[str, list[Any]] = {}
    for c in channels:
        by_name.setdefault(c.name, []).append(c)

    def ambiguous(name: str, found: list[Any], where: str, field: str) -> InputError:
        groups = ", ".join(repr(c.group_name) for c in found)
        return InputError(where, field, f"channel {name!r} is in groups {groups} of {file}; name it as "
                                        f"'{found[0].group_name}/{name}'")

    out: dict[str, Any] = {}
    claimed: set[str] = set()
    wanted = [] if channel_map is None else [(canonical, src, channel_map) for canonical, spec in
                                              channel_map.channels.items() for src in spec.sources()]
    for canonical, src, mapping in wanted:
        if src in by_path:
            out[src] = by_path[src]
        elif len(by_name.get(src, [])) == 1:
            out[src] = by_name[src][0]
        elif src in by_name:
            raise ambiguous(src, by_name[src], mapping.source, canonical)
        else:  # before any time base is looked for: a missing t is the map's fault, not the waveforms'
            raise missing_source(mapping, canonical, src, file)
        claimed.add(f"{out[src].group_name}/{out[src].name}")
    for path, c in by_path.items():
        if path in claimed:
            continue
        if c.name in CANONICAL_CHANNELS:
            if len(by_name[c.name]) > 1:
                raise ambiguous(c.name, by_name[c.name], file, c.name)
            out[c.name] = c
        elif channel_map is None:
            raise foreign_channel(file, path)
    return out


def _numeric(dtype: np.dtype) -> bool:
    return dtype.kind in "iufb"


def _check_declared(name: str, channel: Any, file: str, file_bytes: int) -> None:
    """Refuse a channel that declares more values than the file holds bytes for (before npTDMS
    makes an array of that length)."""
    if not _numeric(np.dtype(channel.dtype)):
        raise InputError(file, name, f"not a numeric channel (TDMS type {getattr(channel.data_type, '__name__', '?')})")
    value_bytes = getattr(channel.data_type, "size", None) or 1  # DAQmx raw data: at least a byte a value
    if len(channel) > file_bytes // value_bytes:
        raise InputError(file, name, f"declares {len(channel)} values of {value_bytes} bytes, more than the file's "
                                     f"{file_bytes} bytes hold")


def _increment(name: str, channel: Any, sample_rate: float | None, file: str, map_file: str | None) -> float:
    stated = channel.properties.get("wf_increment")
    if stated is None:
        if sample_rate is None:
            raise InputError(file, name, "no time base: no t channel, no wf_increment property, and no "
                                         "[file] sample_rate in a channel map")
        return 1.0 / sample_rate
    if isinstance(stated, (bool, np.bool_)) or not isinstance(stated, (int, float, np.integer, np.floating)) or not (
            math.isfinite(float(stated)) and float(stated) > 0):
        raise InputError(file, name, f"wf_increment {stated!r} is not a positive number of seconds")
    if float(stated) < 1.0 / MAX_SAMPLE_RATE:
        raise InputError(file, name, f"wf_increment {float(stated)!r} s is a rate above {MAX_SAMPLE_RATE:g} Hz; "
                                     "no DAQ samples that fast")
    if sample_rate is not None and not math.isclose(float(stated) * sample_rate, 1.0, rel_tol=1e-9):
        raise InputError(file, name, f"wf_increment {float(stated)!r} s is not 1/sample_rate of map {map_file} "
                                     f"({sample_rate!r} Hz)")
    return float(stated)


def _start_offsets(used: dict[str, Any], file: str) -> dict[str, float]:
    """Each channel's start (s) on one clock: ``wf_start_offset``, plus its ``wf_start_time``
    after the earliest when every channel states one (channels of two DAQmx tasks)."""
    offsets = {}
    for name, c in used.items():
        offset = c.properties.get("wf_start_offset", 0.0)
        if not isinstance(offset, (int, float, np.integer, np.floating)) or not math.isfinite(float(offset)):
            raise InputError(file, name, f"wf_start_offset {offset!r} is not a finite number of seconds")
        offsets[name] = float(offset)
    starts = {name: c.properties.get("wf_start_time") for name, c in used.items()}
    if starts and all(isinstance(s, np.datetime64) and not np.isnat(s) for s in starts.values()):
        first = min(starts.values())
        for name, start in starts.items():
            offsets[name] += float((start - first) / np.timedelta64(1, "ns")) * 1e-9
    return offsets


def _time_base(start: float, step: float, n: int) -> np.ndarray:
    """``start + k * step`` (s); a start on the sample grid (within 1 ppm of a step) is put on it
    exactly, so two channels of one rate share bit-equal times: a digital level read with a zero-order
    hold at 8 ms + k*dt against the torque's (k + 40)*dt would otherwise slip a sample at round-off."""
    on_grid = round(start / step)
    if abs(start / step - on_grid) <= 1e-6:
        return (on_grid + np.arange(n, dtype=np.float64)) * step
    return start + step * np.arange(n, dtype=np.float64)


def _columns(used: dict[str, Any], channel_map: ChannelMap | None, file: str) -> dict[str, Column]:
    """The used channels' data as columns: on the rows of the t channel, or each on its own time base."""
    t_source = "t"
    if channel_map is not None and "t" in channel_map.channels:
        t_source = channel_map.channels["t"].name or "t"
    data = {name: np.asarray(c[:]) for name, c in used.items()}
    units = {name: (c.properties.get("unit_string") or None) for name, c in used.items()}
    units = {name: (u if isinstance(u, str) and u.strip() else None) for name, u in units.items()}
    if t_source in used:
        rows = len(data[t_source])
        for name, values in data.items():
            if len(values) != rows:
                raise InputError(file, name, f"{len(values)} values, but the time channel {t_source!r} has {rows} "
                                             "(every channel shares its rows)")
        return {name: Column(values, units[name]) for name, values in data.items()}
    sample_rate = channel_map.file.sample_rate if channel_map is not None else None
    map_file = channel_map.source if channel_map is not None else None
    starts = _start_offsets(used, file)
    columns = {}
    for name, values in data.items():
        step = _increment(name, used[name], sample_rate, file, map_file)
        columns[name] = Column(values, units[name], _time_base(starts[name], step, len(values)))
    return columns


def read_tdms_columns(path: str | Path, channel_map: ChannelMap | None = None
                      ) -> tuple[dict[str, Column], dict[str, MetaValue]]:
    """The columns a capture uses (source names as the map gives them) and the root properties.

    Raises
    ------
    InputError
        Missing or unreadable file, not TDMS, truncated or damaged, a channel of the capture
        that is not numeric or declares more values than the file holds, ambiguous names,
        channels of another length than ``t``, a waveform without its time base.
    """
    file = str(path)
    check_regular(path)  # a FIFO or directory is refused before it is opened
    with open(path, "rb") as fh:  # a file object: npTDMS reads no .tdms_index beside it
        file_bytes = os.fstat(fh.fileno()).st_size
        tag = fh.read(4)
        fh.seek(0)
        if tag != b"TDSm":
            raise InputError(file, None, f"not a TDMS file: it starts with {tag!r}, not a segment's tag b'TDSm'")
        if file_bytes < _LEAD_IN_BYTES:
            raise InputError(file, None, f"truncated TDMS file: {file_bytes} bytes, less than one segment's "
                                         f"{_LEAD_IN_BYTES}-byte lead-in")
        try:
            with _refusing_warnings(file):
                tdms = TdmsFile.open(fh)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - npTDMS raises ValueError, KeyError, EOFError, struct.error ...
            raise InputError(file, None, f"not a readable TDMS file: {exc.__class__.__name__}: {exc}") from None
        channels = [c for g in tdms.groups() for c in g.channels()]
        used = _source_names(channels, channel_map, file)
        for name, c in used.items():
            _check_declared(name, c, file, file_bytes)
        properties = _root_properties(tdms, file)
        try:
            with _refusing_warnings(file):
                columns = _columns(used, channel_map, file)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - npTDMS's errors on data it cannot decode
            raise InputError(file, None, f"not a readable TDMS file: {exc.__class__.__name__}: {exc}") from None
    return columns, properties


def read_tdms(path: str | Path, channel_map: ChannelMap | None = None) -> Capture:
    """Read a TDMS capture into canonical channels and units (not validated; see ``read_capture``).

    Parameters
    ----------
    path : path
        The ``.tdms`` file (or any file the map's ``[file] format = "tdms"`` names).
    channel_map : ChannelMap, optional
        Map for the file's group/channel names, units, sample rate and metadata.
    """
    file = str(path)
    columns, properties = read_tdms_columns(path, channel_map)
    metadata, truth = split_truth(properties)
    columns, metadata = apply_channel_map(columns, metadata, channel_map, file)
    return assemble(columns, metadata, truth, file)
