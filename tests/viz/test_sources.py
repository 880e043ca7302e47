"""Where a calibration recording finds its images when it is not told (`lfgraph.viz.sources`): the files the
observations name, read as the capture reads them, and nothing that could fail the calibration."""

import dataclasses

import cv2
import numpy as np

from lfgraph.core.grid import ViewGrid
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.viz.sources import frames_from_sources

SIZE = (64, 48)  # (width, height) px of the little test images


def observations(grid: ViewGrid, frames: int):
    board = BoardSpec.parse("7x5", 15.0)
    corners = np.zeros((grid.num_views, frames, board.num_corners, 2))
    return observations_from_arrays(board, grid, SIZE, corners, np.zeros(corners.shape[:3], dtype=bool))


def test_images_come_from_the_files_each_view_frame_names(tmp_path):
    grid = ViewGrid(1, 2, 0)
    sources = []
    for f in range(2):
        paths = []
        for v in range(2):
            path = tmp_path / f"{f:03d}" / f"{grid.name(v)}.png"
            path.parent.mkdir(exist_ok=True)
            cv2.imwrite(str(path), np.full(SIZE[::-1], 10 * (2 * f + v), np.uint8))
            paths.append(str(path))
        sources.append(tuple(paths))
    obs = dataclasses.replace(observations(grid, 2), sources=tuple(sources))
    load = frames_from_sources(obs)
    assert load is not None
    for f in range(2):
        assert [int(image[0, 0]) for image in load(f)] == [10 * (2 * f), 10 * (2 * f + 1)]
    (tmp_path / "001" / "r00_c01.png").unlink()  # a file gone while the recording is written: no images, no failure
    assert load(1) is None and load(0) is not None


def test_no_images_without_files():
    grid = ViewGrid(1, 2, 0)
    assert frames_from_sources(observations(grid, 2)) is None  # synthetic corners name no files
    gone = dataclasses.replace(observations(grid, 1), sources=(("/nonexistent/a.png", "/nonexistent/b.png"),))
    assert frames_from_sources(gone) is None
