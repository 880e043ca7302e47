"""Errors shared by several modules."""

from __future__ import annotations


class CaptureError(ValueError):
    """An input capture that cannot be used; the message names the file or folder and what was wrong."""
