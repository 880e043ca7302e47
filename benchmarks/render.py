"""Rendering the whole paper-4x4 checkerboard set: wall time and peak memory, against a plain OpenCV peer.

The peer does the least an OpenCV user would: warp a pre-drawn board image with cv2.warpPerspective (pinhole) and
apply the lens distortion with cv2.remap — no anti-aliasing beyond bilinear interpolation, same image count.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from lfgraph.datasets.checkerboard import make_checkerboard_truth, write_checkerboard_dataset
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.report import format_table


def peak_rss_mb() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 1024.0


def opencv_peer(calib, truth, board, out: Path) -> float:
    """Warp a drawn board into each view (homography + distortion remap), write PNGs; returns seconds."""
    px_per_square = 40
    s = board.square_m
    m = board.margin_squares
    wb, hb = int((board.cols + 1 + 2 * m) * px_per_square), int((board.rows + 1 + 2 * m) * px_per_square)
    yy, xx = np.mgrid[0:hb, 0:wb]
    u = xx / px_per_square - (1 + m)
    v = yy / px_per_square - (1 + m)
    sq = (u >= -1) & (u < board.cols) & (v >= -1) & (v < board.rows)
    texture = np.where(sq & ((np.floor(u) + np.floor(v)) % 2 == 0), 30, 220).astype(np.uint8)
    # board pixel (i, j) -> board metres
    A = np.array([[s / px_per_square, 0, -(1 + m) * s], [0, s / px_per_square, -(1 + m) * s], [0, 0, 1]])  # noqa: N806
    w, h = calib.image_size_px
    start = time.perf_counter()
    for v_idx in range(calib.num_views):
        intr = calib.intrinsics[v_idx]
        map1, map2 = cv2.initUndistortRectifyMap(intr.K, intr.dist_cv, None, intr.K, (w, h), cv2.CV_32FC1)
        for f in range(truth.ref_T_board.shape[0]):
            T = calib.view_T_ref(v_idx) @ truth.ref_T_board[f]  # noqa: N806
            H = intr.K @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]) @ A  # noqa: N806
            undist = cv2.warpPerspective(texture, H, (w, h), flags=cv2.INTER_LINEAR, borderValue=120)
            img = cv2.remap(undist, map1, map2, cv2.INTER_LINEAR)
            cv2.imwrite(str(out / f"{v_idx:02d}_{f:03d}.png"), img)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scene", default="paper-4x4")
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args(argv)
    scene = get_scene(args.scene)
    rng = np.random.default_rng(0)
    calib = make_rig(scene.rig, rng)
    truth = make_checkerboard_truth(calib, scene.checkerboard, rng)
    n = calib.num_views * scene.checkerboard.frames
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        write_checkerboard_dataset(Path(tmp) / "lfgraph", calib, truth, scene.checkerboard, seed=0, jobs=args.jobs,
                                   progress=False)
        ours = time.perf_counter() - start
        ours_mb = peak_rss_mb()
        peer_dir = Path(tmp) / "peer"
        peer_dir.mkdir()
        peer = opencv_peer(calib, truth, scene.checkerboard.board, peer_dir)
    w, h = calib.image_size_px
    print(f"render benchmark: {args.scene}, {n} images of {w}x{h}, lfgraph with {args.jobs} jobs, peer single process")
    print(format_table(
        ["renderer", "images", "wall_s", "ms_per_image", "peak_rss_mb", "time_vs_peer"],
        [["lfgraph (exact rays, AA)", n, ours, 1e3 * ours / n, ours_mb, ours / peer],
         ["opencv warp+remap (peer)", n, peer, 1e3 * peer / n, None, 1.0]], floatfmt=".3g"))
    print("targets: whole paper-4x4 set < 90 s, peak memory < 1 GB")
    return 0 if ours < 90 and ours_mb < 1024 else 1


if __name__ == "__main__":
    sys.exit(main())
