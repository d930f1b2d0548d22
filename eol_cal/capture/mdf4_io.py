"""ASAM MDF 4 captures (``.mf4``) with asammdf (capture format v1).

Writing: analog channels in one channel group on the capture's time base; the digital
channels either in that group as sampled levels (``digital="levels"``) or each in a group of
its own holding only its change events (``digital="events"``: the first row is the level at
the start, every further row a change at its exact time). Metadata and ``truth.*`` go into the
header comment's common properties, ``<e name="serial">M-0001</e>``, values as text in the
encoding of :mod:`eol_cal.capture.metadata`.

Reading: every channel of every group, each on its group's time base; a group of integral
channels only whose rows each change a level (or whose times are irregular) is read as change
events, kept exactly in ``Capture.events``. Then the channel map, and everything is put on the
torque channel's time base (analog: linear interpolation; digital: zero-order hold).
"""

from __future__ import annotations

import contextlib
import gc
import io
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal
from collections.abc import Callable

import numpy as np

from eol_cal.infra.atomic import atomic_path
from eol_cal.capture.channel_map import ChannelMap, apply_channel_map
from eol_cal.capture.columns import Column, assemble, change_events, is_change_list
from eol_cal.capture.metadata import MetaValue, decode_value, encode_value, join_truth, split_truth
from eol_cal.capture.data import CANONICAL_CHANNELS, DIGITAL_CHANNELS, Capture
from eol_cal.capture.mdf4_check import checked_mdf4
from eol_cal.capture.mdf4_decode import Group, decode_checked
from eol_cal.errors import InputError
from eol_cal.infra.inputs import check_regular

_MDF_VERSION = "4.10"
_DESCRIPTION = "eol-cal capture (capture format v1)"


def header_comment(properties: dict[str, MetaValue], file: str | None = None) -> str:
    """The ``<HDcomment>`` XML carrying ``properties`` as common properties."""
    root = ET.Element("HDcomment")
    ET.SubElement(root, "TX").text = _DESCRIPTION
    common = ET.SubElement(root, "common_properties")
    for key, value in properties.items():
        ET.SubElement(common, "e", name=key).text = encode_value(key, value, file)
    return ET.tostring(root, encoding="unicode")


#: elements of ``common_properties`` that group others (ASAM MDF 4.2, HD comment); each names its group
_GROUPS = ("tree", "list", "elist", "li", "eli")


def parse_header_comment(comment: str, file: str) -> dict[str, MetaValue]:
    """Typed properties from an ``<HDcomment>``'s ``common_properties/e`` elements.

    ``comment`` is the text stored in the file (:attr:`Mdf4Layout.header_comment`), not asammdf's
    ``header.comment``: asammdf rebuilds that from a dict, so a key given twice came back once,
    with the last value. Refused, as in a CSV: a key given twice (names compared without
    surrounding blanks), two ``common_properties``, an ``e`` or a group without its ``name``
    (asammdf prints a traceback on stdout for that one).
    """
    return header_properties(header_xml(comment, file), file)


def header_xml(comment: str, file: str) -> ET.Element | None:
    """The parsed ``<HDcomment>`` of :func:`parse_header_comment` (``None``: a comment that is not
    XML, which holds no properties); :class:`InputError` for malformed XML. Parsed once a file:
    the direct decoder judges the same tree (:func:`eol_cal.capture.mdf4_decode.decode_checked`)."""
    if not comment.strip().startswith("<"):
        return None
    try:
        return ET.fromstring(comment)
    except ET.ParseError as exc:
        raise InputError(file, "header comment", f"not valid XML: {exc}") from None


def _local(tag: str) -> str:
    """An element's name without the ASAM namespace a writer may have used."""
    return tag.split("}", 1)[1] if "}" in tag else tag


def header_properties(root: ET.Element | None, file: str) -> dict[str, MetaValue]:
    """The properties of a parsed header comment (:func:`header_xml`), refused as
    :func:`parse_header_comment` says. The tree is left as it is (names read without their
    namespace), for the decoder that judges it too."""
    properties: dict[str, MetaValue] = {}
    if root is None:
        return properties
    commons = [element for element in root if _local(element.tag) == "common_properties"]
    if len(commons) > 1:
        raise InputError(file, "header comment", "common_properties given twice")
    if not commons:
        return properties
    for element in commons[0].iter():
        tag = _local(element.tag)
        if tag not in ("e", *_GROUPS) or tag == "li":
            continue
        name = element.get("name")
        if name is None or not name.strip():
            raise InputError(file, "header comment", f"a <{tag}> element without its name")
    for element in commons[0]:
        if _local(element.tag) != "e":
            continue
        key = element.get("name", "").strip()
        if key in properties:
            raise InputError(file, key, "metadata key given twice in the header comment")
        properties[key] = decode_value(key, element.text or "", file)
    return properties


def _stored(values: np.ndarray, digital: bool) -> np.ndarray:
    """uint8 for digital levels that fit; anything else as float64, so that no value changes."""
    values = np.asarray(values)
    if (digital and values.size and np.all(np.isfinite(values)) and np.array_equal(values, np.round(values))
            and values.min() >= 0 and values.max() <= 255):
        return values.astype(np.uint8)
    return values.astype(np.float64)


def _initial_and_events(capture: Capture, name: str) -> tuple[np.ndarray, np.ndarray]:
    levels = np.asarray(capture.channels[name])
    if name in capture.events:
        times, new = (np.asarray(a) for a in capture.events[name])
        inside = times > capture.t[0]
        times, new = times[inside], new[inside]
    else:
        times, new = change_events(capture.t, levels)
    return (
        np.concatenate([[float(capture.t[0])], np.asarray(times, dtype=np.float64)]),
        _stored(np.concatenate([[levels[0]], new]), digital=True),
    )


def write_mdf4(
    capture: Capture,
    path: str | Path,
    digital: Literal["levels", "events"] = "levels",
    compression: int = 2,
) -> None:
    """Write a capture as MDF 4.10, atomically.

    Parameters
    ----------
    capture : Capture
        The capture to write.
    path : path
        Target ``.mf4`` file.
    digital : {"levels", "events"}
        Digital channels as levels sampled with the analog ones, or as change events, one
        channel group each (exact times from ``capture.events`` where present, else the sample
        times at which the level changed).
    compression : int
        asammdf compression (0 none, 1 deflate, 2 transposed deflate).
    """
    from asammdf import MDF, Signal

    file = str(path)
    if digital not in ("levels", "events"):
        raise InputError(file, "digital", f"must be 'levels' or 'events', got {digital!r}")
    unknown = [n for n in capture.channels if n not in CANONICAL_CHANNELS or n == "t"]
    if unknown:
        raise InputError(file, unknown[0], "not a canonical channel name; cannot be written")
    t = np.asarray(capture.t, dtype=np.float64)
    mdf = MDF(version=_MDF_VERSION)
    try:
        mdf.header.comment = header_comment(join_truth(capture.metadata, capture.truth), file)
        sampled = [
            Signal(
                _stored(values, name in DIGITAL_CHANNELS),
                t,
                name=name,
                unit="" if CANONICAL_CHANNELS[name] == "1" else CANONICAL_CHANNELS[name],
            )
            for name, values in capture.channels.items()
            if digital == "levels" or name not in DIGITAL_CHANNELS
        ]
        mdf.append(sampled, acq_name="sampled", comment="channels sampled on the capture's time base")
        if digital == "events":
            for name in (n for n in DIGITAL_CHANNELS if n in capture.channels):
                times, levels = _initial_and_events(capture, name)
                mdf.append(
                    [Signal(levels, times, name=name, unit="")],
                    acq_name=f"{name} events",
                    comment=f"{name}: level at the start, then every change at its time",
                )
        with atomic_path(path) as tmp:
            mdf.save(tmp, overwrite=True, compression=compression)
    finally:
        mdf.close()


def _numeric_1d(samples: np.ndarray) -> bool:
    # real numbers only: a complex channel read as its real part was a current of 0 A and a warning.
    # By kind, one test a channel: booleans, integers (numpy counts timedelta64 among them) and floats
    return samples.ndim == 1 and samples.dtype.names is None and samples.dtype.kind in "biufm"


def read_mdf4_columns(
    path: str | Path,
) -> tuple[dict[str, Column], dict[str, MetaValue], dict[str, str]]:
    """Raw columns (source names, each on its group's time base), header properties, and the
    channels that cannot be used (name -> reason: ambiguous name, non-numeric).

    The file's structure is checked first (:mod:`eol_cal.capture.mdf4_check`): asammdf only
    decodes a file whose links, sizes and compressed data hold. A plain file (eol-cal's own
    layout, most loggers') is decoded from the checked bytes directly
    (:mod:`eol_cal.capture.mdf4_decode`: the same columns, ~5x faster); any other with asammdf.

    Raises
    ------
    InputError
        Missing or unreadable file, a structural fault (naming the block), not MDF version 4,
        a malformed header comment.
    """
    file = str(path)
    check_regular(path)
    # structure, sizes and compressed data, before anything trusts any of it
    with checked_mdf4(path) as (data, layout):
        # the comment as the file stores it, whichever decoder reads the data (asammdf's
        # header.comment is rebuilt from a dict: a key given twice came back once); parsed once,
        # for the direct decoder's judgement of it and for the properties
        header = header_xml(layout.header_comment, file)
        groups = decode_checked(data, layout, header)
    properties = header_properties(header, file)
    if groups is not None:
        return _columns(groups, properties)
    with _quiet_asammdf(file) as decode:
        columns, _none, bad = decode(_decode, path, file)
    return columns, properties, bad


class _Quiet:
    def __init__(self, file: str) -> None:
        self.file = file
        self.failure: InputError | None = None

    def __call__(self, func, *args):  # the decode and its arguments
        try:
            return func(*args)
        except InputError as exc:
            self.failure = exc
        except Exception as exc:  # noqa: BLE001 - whatever asammdf trips over in a file that passed the check
            self.failure = InputError(self.file, None, f"not a readable MDF file: {exc.__class__.__name__}: {exc}")
        # out of the except block: the failed decode's frames, and the half-built asammdf objects
        # they hold, are free once the failure forgets its traceback and context
        self.failure.__traceback__ = self.failure.__context__ = None
        self.failure.__suppress_context__ = True
        raise _DecodeFailed


class _DecodeFailed(Exception):
    pass


@contextlib.contextmanager
def _quiet_asammdf(file: str) -> Iterator[_Quiet]:
    """asammdf objects that failed half-way complain from ``__del__`` on stderr, and asammdf
    prints the traceback of a header comment it cannot parse on stdout (a ``--json`` output's
    stream); the error we raise says what went wrong, once.

    Only a failed read collects its garbage here: a full ``gc.collect`` walks every object of the
    process (about 0.1 s once JAX is imported, more in a Dask worker), which on every good capture
    was most of a lot refit's time (docs/benchmarks.md, "Lot refit throughput")."""
    quiet = _Quiet(file)
    previous = sys.unraisablehook
    # a signal's exception dropped in there still goes to the command's hook (sent again)
    sys.unraisablehook = lambda u: previous(u) if isinstance(u.exc_value, KeyboardInterrupt) else None
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield quiet
    except _DecodeFailed:
        pass
    finally:
        if quiet.failure is not None:
            gc.collect()  # the half-built objects die now, while their complaints go nowhere
        sys.unraisablehook = previous
    if quiet.failure is not None:
        raise quiet.failure


def _decode(path: str | Path, file: str) -> tuple[dict[str, Column], dict[str, MetaValue], dict[str, str]]:
    """asammdf's decode of a file that is not plain (its columns; the properties come from the check)."""
    from asammdf import MDF

    mdf = MDF(str(path))  # asammdf raises MdfException, struct.error, ... for bad files: said by _Quiet
    try:
        if not str(mdf.version).startswith("4"):
            raise InputError(file, None, f"MDF version {mdf.version}; capture format v1 takes MDF 4")
        groups: list[Group] = []
        for gi, group in enumerate(mdf.groups):
            master = mdf.masters_db.get(gi)
            groups.append([(channel.name, _signal_loader(mdf, gi, ci)) for ci, channel in enumerate(group.channels)
                           if ci != master])
        return _columns(groups, {})
    finally:
        mdf.close()


def _signal_loader(mdf: Any, gi: int, ci: int) -> Callable[[], tuple[np.ndarray, str | None, np.ndarray]]:
    def load() -> tuple[np.ndarray, str | None, np.ndarray]:
        signal = mdf.get(group=gi, index=ci)
        return np.asarray(signal.samples), signal.unit or None, np.asarray(signal.timestamps)

    return load


def _columns(groups: list[Group], properties: dict[str, MetaValue]
             ) -> tuple[dict[str, Column], dict[str, MetaValue], dict[str, str]]:
    """Columns of the decoded channel groups (either decoder's), the unusable channels named."""
    columns: dict[str, Column] = {}
    bad: dict[str, str] = {}
    for group in groups:
        found: list[tuple[str, np.ndarray, str | None, np.ndarray]] = []
        for name, load in group:
            samples, unit, times = load()
            if name in columns or any(name == f[0] for f in found):
                bad[name] = "channel name found in more than one channel group; ambiguous"
                continue
            if not _numeric_1d(samples):
                bad[name] = f"not a numeric scalar channel (dtype {samples.dtype})"
                continue
            times = np.asarray(times, dtype=np.float64)
            if times.shape != samples.shape:
                bad[name] = f"{samples.size} samples on {times.size} time stamps"
                continue
            found.append((name, samples, unit, times))
        if not found:
            continue
        # a decoder's channels of one group share its time stamps (one array): each array compared once
        bases = list({id(f[3]): f[3] for f in found}.values())
        events = all(np.array_equal(b, bases[0]) for b in bases) and is_change_list(
            found[0][3], [f[1] for f in found]
        )
        for name, samples, unit, times in found:
            columns[name] = Column(samples, unit, times, events)
    for name in bad:
        columns.pop(name, None)
    return columns, properties, bad



def read_mdf4(path: str | Path, channel_map: ChannelMap | None = None) -> Capture:
    """Read an MDF4 capture into canonical channels and units (not validated; see ``read_capture``).

    Parameters
    ----------
    path : path
        The ``.mf4`` file.
    channel_map : ChannelMap, optional
        Map for a foreign file's names and units.
    """
    file = str(path)
    columns, properties, unusable = read_mdf4_columns(path)
    wanted = set(CANONICAL_CHANNELS) if channel_map is None else set(CANONICAL_CHANNELS).union(
        *(spec.sources() for spec in channel_map.channels.values())
    )
    for name, reason in unusable.items():
        if name in wanted or channel_map is None:
            raise InputError(file, name, reason)
    metadata, truth = split_truth(properties)
    columns, metadata = apply_channel_map(columns, metadata, channel_map, file)
    return assemble(columns, metadata, truth, file)
