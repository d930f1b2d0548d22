"""Channel maps: TOML files that rename and convert a foreign DAQ's channels (capture format v1).

::

    [channels]
    t      = { name = "Zeit", unit = "ms" }
    torque = { name = "Drehmoment", unit = "N*cm" }   # source name and the source's unit
    enc_a  = { name = "DI0" }
    hall   = { bits = ["DI2", "DI3", "DI4"] }         # U, V, W on three digital lines
    iq_ref = { name = "Iq_soll", unit = "A" }

    [metadata]
    serial = "M-0001"                                 # fills or overrides file metadata

    [file]
    format = "text"                                   # what the file is, whatever its suffix
    delimiter = "\t"                                  # (eol_cal.capture.file_options)
    decimal = ","

A unit in the map is the unit of the source channel. When the file states a unit too (CSV
header ``Zeit [ms]``, MDF4 channel unit) the two must agree. Source channels that the map does
not name are dropped, except those already carrying a canonical name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Mapping

from eol_cal.capture.columns import Column, combine_hall_bits
from eol_cal.capture.file_options import FileOptions, parse_file_options
from eol_cal.capture.metadata import MetaValue, coerce_value
from eol_cal.capture.data import CANONICAL_CHANNELS, TRUTH_PREFIX
from eol_cal.capture.units import check_unit, parse_unit, to_canonical
from eol_cal.errors import InputError
from eol_cal.infra.inputs import load_toml


class ForeignChannelError(InputError):
    """A file names a channel in its own way and no channel map says what it is."""


@dataclass(frozen=True)
class ChannelSpec:
    """Where one canonical channel comes from: a source channel (and its unit) or hall bits."""

    name: str | None = None
    unit: str | None = None
    bits: tuple[str, str, str] | None = None

    def sources(self) -> tuple[str, ...]:
        return self.bits if self.bits is not None else (self.name,)  # type: ignore[return-value]


@dataclass(frozen=True)
class ChannelMap:
    """A parsed map file: canonical name -> :class:`ChannelSpec`, metadata overrides, its path,
    and what the file is (its ``[file]`` table, :class:`FileOptions`)."""

    channels: Mapping[str, ChannelSpec] = field(default_factory=dict)
    metadata: Mapping[str, MetaValue] = field(default_factory=dict)
    source: str = "<map>"
    file: FileOptions = field(default_factory=FileOptions)


def _spec(name: str, entry: object, path: str) -> ChannelSpec:
    if name not in CANONICAL_CHANNELS:
        raise InputError(path, name, f"not a canonical channel; known: {', '.join(CANONICAL_CHANNELS)}")
    if not isinstance(entry, dict):
        raise InputError(path, name, "must be a table like { name = \"...\", unit = \"...\" }")
    unknown = set(entry) - {"name", "unit", "bits"}
    if unknown:
        raise InputError(path, name, f"unknown keys {sorted(unknown)}; allowed: name, unit, bits")
    if "bits" in entry:
        if name != "hall":
            raise InputError(path, name, "bits = [...] is only for hall (U, V, W lines)")
        bits = entry["bits"]
        if set(entry) != {"bits"}:
            raise InputError(path, name, "bits takes neither name nor unit")
        if not (isinstance(bits, list) and len(bits) == 3 and all(isinstance(b, str) and b for b in bits)):
            raise InputError(path, name, "bits must list three source channel names: U, V, W")
        return ChannelSpec(bits=tuple(bits))
    source_name = entry.get("name")
    if not isinstance(source_name, str) or not source_name:
        raise InputError(path, name, "needs name = \"<source channel>\"")
    unit = entry.get("unit")
    if unit is not None:
        if not isinstance(unit, str):
            raise InputError(path, name, "unit must be a string")
        check_unit(name, unit, path)
    return ChannelSpec(name=source_name, unit=unit)


def load_channel_map(path: str | Path) -> ChannelMap:
    """Read and check a channel-map TOML file.

    Raises
    ------
    InputError
        Missing or malformed file, unknown canonical names or keys, units that cannot be
        converted, ``truth.*`` metadata, one source feeding two channels.
    """
    path_s = str(path)
    data = load_toml(path)
    unknown = set(data) - {"channels", "metadata", "file"}
    if unknown:
        raise InputError(path_s, sorted(unknown)[0], "unknown table; a map has [channels], [metadata] and [file]")
    raw_channels = data.get("channels", {})
    raw_meta = data.get("metadata", {})
    if not isinstance(raw_channels, dict) or not isinstance(raw_meta, dict):
        raise InputError(path_s, None, "[channels] and [metadata] must be tables")
    channels = {name: _spec(name, entry, path_s) for name, entry in raw_channels.items()}
    used: dict[str, str] = {}
    for name, spec in channels.items():
        for src in spec.sources():
            if src in used:
                raise InputError(path_s, name, f"source channel {src!r} already feeds {used[src]!r}")
            used[src] = name
    metadata = {}
    for key, value in raw_meta.items():
        if key.startswith(TRUTH_PREFIX):
            raise InputError(path_s, key, "truth.* keys are written by simulators only")
        metadata[key] = coerce_value(key, value, path_s)
    file = parse_file_options(data["file"], path_s) if "file" in data else FileOptions()
    return ChannelMap(channels=channels, metadata=metadata, source=path_s, file=file)


def _unit(spec_unit: str | None, file_unit: str | None, file: str, map_file: str, label: str) -> str | None:
    if spec_unit is None:
        return file_unit
    if file_unit is None or not file_unit.strip():
        return spec_unit
    a, b = parse_unit(spec_unit, map_file, label), parse_unit(file_unit, file, label)
    if a != b:
        raise InputError(file, label, f"file states unit {file_unit!r} but map {map_file} says {spec_unit!r}")
    return spec_unit


def _convert(name: str, column: Column, unit: str | None, file: str, label: str) -> Column:
    values = to_canonical(name, column.values, unit, file, label)
    return Column(values, None, column.times, column.events)


def apply_channel_map(
    columns: Mapping[str, Column],
    metadata: Mapping[str, MetaValue],
    channel_map: ChannelMap | None,
    file: str,
) -> tuple[dict[str, Column], dict[str, MetaValue]]:
    """Canonical, unit-converted columns and metadata from a file's raw columns.

    Parameters
    ----------
    columns : mapping
        Source name -> :class:`Column` as read (units as the file states them).
    metadata : mapping
        File metadata (no ``truth.*`` keys).
    channel_map : ChannelMap or None
        Map to apply; without one every column must already carry a canonical name.
    file : str
        The capture file, for error messages.

    Returns
    -------
    (dict[str, Column], dict)
        Canonical name -> column in canonical units, and metadata with the map's overrides.
    """
    out: dict[str, Column] = {}
    meta = dict(metadata)
    claimed: set[str] = set()
    if channel_map is not None:
        for name, spec in channel_map.channels.items():
            missing = [s for s in spec.sources() if s not in columns]
            if missing:
                raise missing_source(channel_map, name, missing[0], file)
            claimed.update(spec.sources())
            if spec.bits is not None:
                labels = [f"hall (bit line {b!r})" for b in spec.bits]
                out[name] = combine_hall_bits([columns[b] for b in spec.bits], file, labels)
            else:
                label = name if spec.name == name else f"{name} (source channel {spec.name!r})"
                column = columns[spec.name]  # type: ignore[index]
                unit = _unit(spec.unit, column.unit, file, channel_map.source, label)
                out[name] = _convert(name, column, unit, file, label)
        meta.update(channel_map.metadata)
    for source_name, column in columns.items():
        if source_name in claimed:
            continue
        if source_name in CANONICAL_CHANNELS:
            if source_name in out:
                raise InputError(
                    file, source_name, f"channel present in the file and also produced by the map {channel_map.source}"  # type: ignore[union-attr]
                )
            out[source_name] = _convert(source_name, column, column.unit, file, source_name)
        elif channel_map is None:
            raise foreign_channel(file, source_name)
    return out, meta


def missing_source(channel_map: ChannelMap, name: str, source: str, file: str) -> InputError:
    """The refusal of a map whose channel ``name`` reads a ``source`` channel that ``file`` lacks."""
    return InputError(channel_map.source, name, f"source channel {source!r} not found in {file}")


def foreign_channel(file: str, name: str) -> ForeignChannelError:
    """The refusal of a channel that is not a canonical name, in a file read without a map."""
    return ForeignChannelError(
        file, name, f"unknown channel name; canonical names are {', '.join(CANONICAL_CHANNELS)} "
                    "(a foreign file needs a channel map)")

