"""`lfgraph demo` / `make demo`: the main job on the embedded synthetic default (paper-4x4)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from lfgraph.board import detect_board
from lfgraph.datasets.checkerboard import iter_view_images, make_checkerboard_truth, write_checkerboard_dataset
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.report import calibration_summary, format_table

DEMO_SCENE = "paper-4x4"
DEMO_SEED = 0


def run_demo(out: Path, jobs: int, quiet: bool = False) -> int:
    """Render paper-4x4 with ground truth, then check that OpenCV finds the rendered corners where they belong."""
    scene = get_scene(DEMO_SCENE)
    rng = np.random.default_rng(DEMO_SEED)
    calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(calib, scene.checkerboard, rng)
    data_dir = out / DEMO_SCENE
    print(f"[1/2] rendering {DEMO_SCENE}: {scene.description}")
    start = time.perf_counter()
    write_checkerboard_dataset(data_dir, calib, truth, scene.checkerboard, seed=DEMO_SEED, jobs=jobs,
                               progress=not quiet)
    n_images = calib.num_views * scene.checkerboard.frames
    seconds = time.perf_counter() - start
    print(f"      {n_images} images in {seconds:.1f} s ({seconds / n_images * 1e3:.0f} ms/image) -> {data_dir}")
    print("ground-truth rig (truth.json):")
    print(calibration_summary(calib))

    print("[2/2] detecting the board in frame 0 of every view and comparing with the true corners")
    rows = []
    for v in range(calib.num_views):
        _, img = next(iter_view_images(calib, truth, scene.checkerboard, DEMO_SEED, v, frames=range(1)))
        corners = detect_board(img, scene.checkerboard.board)
        if corners is None:
            rows.append([calib.grid.name(v), "no" if truth.board_visible[v, 0] else "no (board leaves view)", None])
            continue
        rms = float(np.sqrt(np.mean(np.sum((corners - truth.corners_px[v, 0]) ** 2, axis=1))))
        rows.append([calib.grid.name(v), "yes", rms])
    print(format_table(["view", "found", "rms_vs_truth_px"], rows))
    print("next steps (coming issues): calibrate these images, rectify, auto-refine")
    return 0
