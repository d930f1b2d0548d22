"""Captures: the in-memory model, its validation, and file readers and writers."""

from eol_cal.capture.model import CANONICAL_CHANNELS, Capture

__all__ = ["CANONICAL_CHANNELS", "Capture"]
