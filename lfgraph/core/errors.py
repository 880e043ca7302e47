"""Errors shared by several modules."""

from __future__ import annotations


class CaptureError(ValueError):
    """An input capture that cannot be used; the message names the file or folder and what was wrong."""


class RectificationError(ValueError):
    """A rectification that cannot be built or applied; the message says what does not match."""
