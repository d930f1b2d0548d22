"""Captures: the in-memory model, its validation, and file readers and writers."""

from eol_cal.capture.channel_map import ChannelMap, ChannelSpec, load_channel_map
from eol_cal.capture.io import read_capture, write_capture
from eol_cal.capture.data import CANONICAL_CHANNELS, Capture
from eol_cal.capture.validate import validate

__all__ = [
    "CANONICAL_CHANNELS",
    "Capture",
    "ChannelMap",
    "ChannelSpec",
    "load_channel_map",
    "read_capture",
    "validate",
    "write_capture",
]
