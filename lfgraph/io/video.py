"""Video input: frames of one video per view, decoded in order where possible (a capture pickled to a worker process
opens its own readers there)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from lfgraph.core.errors import CaptureError

VIDEO_GRAB_AHEAD = 16  # a reader this few frames behind decodes forward; further (or backwards) it seeks
VIDEO_READERS = 16  # open video readers kept per process

# per process: path -> [reader, index of the frame its next read() returns]; a capture pickled to a worker
# process opens its own readers there, and frames asked for in order are decoded sequentially
_READERS: dict[str, list] = {}
_READERS_PID = [os.getpid()]
_INHERITED: list = []  # readers a forked process inherited: never used nor released there (FFmpeg's threads did
# not survive the fork; touching them can hang), only kept from being garbage-collected


def _video_reader(path: Path) -> list:
    if _READERS_PID[0] != os.getpid():
        _INHERITED.extend(_READERS.values())
        _READERS.clear()
        _READERS_PID[0] = os.getpid()
    key = str(path)
    entry = _READERS.pop(key, None)
    if entry is None:
        reader = cv2.VideoCapture(key)
        if not reader.isOpened():
            raise CaptureError(f"{path}: cannot open this video (missing, unreadable or an unsupported codec)")
        entry = [reader, 0]
        while len(_READERS) >= VIDEO_READERS:
            _READERS.pop(next(iter(_READERS)))[0].release()
    _READERS[key] = entry  # most recently used last
    return entry


def close_videos() -> None:
    """Release the video readers this process keeps open."""
    if _READERS_PID[0] != os.getpid():
        return
    while _READERS:
        _READERS.popitem()[1][0].release()


def read_video_frame(path: Path, index: int, grayscale: bool) -> np.ndarray:
    """Frame ``index`` (0-based) of a video, decoding forward when the reader is close behind, else seeking."""
    entry = _video_reader(path)
    reader, next_index = entry
    if not 0 <= index - next_index <= VIDEO_GRAB_AHEAD:
        reader.set(cv2.CAP_PROP_POS_FRAMES, index)
    else:
        for _ in range(index - next_index):
            if not reader.grab():
                break
    ok, img = reader.read()
    if not ok or img is None:
        entry[1] = -VIDEO_GRAB_AHEAD - 1  # unknown position: seek next time
        raise CaptureError(f"{path}: cannot decode frame {index} of this video")
    entry[1] = index + 1
    if grayscale and img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if not grayscale and img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return img


def video_info(path: Path) -> tuple[int, tuple[int, int]]:
    """(frame count, (width, height)) of a video; frames are counted by decoding when the container does not say."""
    reader = cv2.VideoCapture(str(path))
    try:
        if not reader.isOpened():
            raise CaptureError(f"{path}: cannot open this video (unreadable or an unsupported codec)")
        ok, img = reader.read()
        if not ok or img is None:
            raise CaptureError(f"{path}: cannot decode the first frame of this video")
        count = int(reader.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            count = 1
            while reader.grab():
                count += 1
        return count, (img.shape[1], img.shape[0])
    finally:
        reader.release()
