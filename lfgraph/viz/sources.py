"""Where a calibration recording finds its images when it is not told: the files the observations were detected in
(`lfgraph.detect.BoardObservations.sources`, filled by `lfgraph.detect_capture`), read as the capture reads them."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from lfgraph.core.errors import CaptureError
from lfgraph.io.capture import CaptureSet
from lfgraph.io.layouts import VIDEO_EXTENSIONS

MISSING = "(missing)"  # how `detect_capture` names a view image the capture does not have


def frames_from_sources(obs) -> Callable[[int], np.ndarray] | None:
    """A loader ``f -> frame f's (V, H, W) images`` from the files ``obs`` was detected in: one image per view, a
    mosaic (one file per frame) or one video per view. None when ``obs`` names no files (synthetic or imported
    corners) or some are no longer regular files. A frame that cannot be read any more loads as None (the
    recording goes without its images; the calibration it records is not failed by it)."""
    sources = getattr(obs, "sources", ())
    if not sources:
        return None
    files = tuple(tuple(None if s == MISSING else Path(s) for s in frame) for frame in sources)
    present = [p for frame in files for p in frame if p is not None]
    if not present or not all(p.is_file() for p in dict.fromkeys(present)):
        return None
    n_views = obs.grid.num_views
    if all(len(frame) == 1 for frame in files) and n_views > 1:
        layout = "mosaic"
    elif all(len(frame) == n_views for frame in files):
        layout = "video" if present[0].suffix.lower() in VIDEO_EXTENSIONS else "folders"
    else:
        return None
    capture = CaptureSet(present[0].parent, layout, obs.grid, tuple(obs.frame_names), files,
                         tuple(obs.image_size_px), view_image_sizes_px=obs.view_image_sizes_px)

    def load(f: int) -> np.ndarray | list[np.ndarray] | None:
        try:
            return capture.load_frame(f)
        except (OSError, CaptureError, ValueError):
            return None

    return load
