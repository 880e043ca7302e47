"""Checkerboard detection on real image sets: lfgraph's `detect_board` against OpenCV's most accurate detector.

Detectors, run on the same images in the same loop (one OpenCV thread, so the times compare the algorithms):
  A  lfgraph `detect_board` (this branch);
  B  ``cv2.findChessboardCornersSB`` with ``CALIB_CB_EXHAUSTIVE | CALIB_CB_ACCURACY``;
  C  the detector before this branch: ``findChessboardCorners`` (ADAPTIVE|NORMALIZE|FAST_CHECK), fallback
     ``findChessboardCornersSB(NORMALIZE_IMAGE)``, ``cornerSubPix`` with a half window of at most 6 px.

There is no ground truth on real images, so accuracy is measured on the frames all three found, per camera:
``cv2.calibrateCamera`` (k1, k2; no tangential, no k3) RMS, and the leave-one-frame-out (LOFO) error: calibrate
without frame f, place frame f's board by PnP with those intrinsics, RMS of its corners; mean over f. Better corners
predict a left-out frame better. On rendered boards the error against the true corners is reported too.

Sets live in ``../shared/data`` (or ``--data``); missing ones are skipped. The BoofCV trinocular set is subsampled
(every third frame) to keep the run under ~3 minutes.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lfgraph.cli.tables import format_table
from lfgraph.detect.board import BoardSpec
from lfgraph.detect.chessboard import _canonical_order, detect_board

TARGET_TIME_RATIO = 1 / 3  # A's time per image over B's
TARGET_LOFO_RATIO = 1.05  # A's leave-one-out error over B's (5 %: LOFO from 4-29 frames varies by a few percent)
TARGET_RENDERED_RMS_PX = 0.05  # same limit as tests/detect/test_checkerboard.py
MIN_FRAMES_FOR_LOFO = 4  # fewer common frames per camera: no calibration reported
CALIB_FLAGS = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
SB_ACCURATE_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@dataclass(frozen=True)
class RealSet:
    name: str
    folder: str
    cameras: dict[str, str]  # camera name -> glob inside the folder
    board: BoardSpec
    step: int = 1  # use every step-th file of each camera (sorted by frame number)


SETS = (
    RealSet("opencv stereo", "opencv_stereo_left_right", {"left": "left*.jpg", "right": "right*.jpg"},
            BoardSpec(9, 6, 1.0)),
    RealSet("bumblebee2", "boofcv_bumblebee2_stereo", {"left": "left*.jpg", "right": "right*.jpg"},
            BoardSpec(4, 6, 0.03)),
    RealSet("trinocular", "boofcv_trinocular", {c: f"{c}/{c}*.jpg" for c in ("left", "middle", "right")},
            BoardSpec(13, 9, 1.0), step=3),
    RealSet("pycalib", "pycalib_chessboard", {"cam": "*.jpg"}, BoardSpec(10, 7, 1.0)),
    RealSet("caliscope", "caliscope_4cam_rig/chessboard_intrinsic", {f"cam_{i}": f"cam_{i}_*.jpg" for i in range(4)},
            BoardSpec(9, 6, 1.0)),
)

TODAY_FIND_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
TODAY_MAX_HALF_WINDOW_PX = 6


def detect_sb_accurate(gray: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    found, corners = cv2.findChessboardCornersSB(gray, board.pattern_size, flags=SB_ACCURATE_FLAGS)
    return _canonical_order(gray, corners.reshape(-1, 2).astype(np.float64), board) if found else None


def detect_before(gray: np.ndarray, board: BoardSpec) -> np.ndarray | None:
    """The detector before this branch, copied so the comparison survives the change."""
    found, corners = cv2.findChessboardCorners(gray, board.pattern_size, flags=TODAY_FIND_FLAGS)
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, board.pattern_size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
    corners = corners.reshape(-1, 2).astype(np.float32)
    grid = corners.reshape(board.rows, board.cols, 2)
    spacing = min(np.min(np.linalg.norm(np.diff(grid, axis=0), axis=-1)),
                  np.min(np.linalg.norm(np.diff(grid, axis=1), axis=-1)))
    half = int(max(2, min(TODAY_MAX_HALF_WINDOW_PX, np.floor(0.45 * spacing))))
    cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (half, half), (-1, -1),
                     (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4))
    return _canonical_order(gray, corners.astype(np.float64), board)


DETECTORS = {"A": detect_board, "B": detect_sb_accurate, "C": detect_before}


def _frame_key(path: Path) -> tuple[int, str]:
    digits = "".join(ch for ch in path.stem if ch.isdigit())
    return (int(digits) if digits else -1, path.name)


def run_detectors(files: list[Path], board: BoardSpec) -> tuple[dict[str, list], dict[str, float]]:
    """Corners per detector and file (None = not found), and summed seconds per detector."""
    found = {k: [] for k in DETECTORS}
    secs = dict.fromkeys(DETECTORS, 0.0)
    for path in files:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        for k, fn in DETECTORS.items():
            t0 = time.perf_counter()
            found[k].append(fn(gray, board))
            secs[k] += time.perf_counter() - t0
    return found, secs


def calibrate_rms(corners: list[np.ndarray], board: BoardSpec, size: tuple[int, int]) -> tuple:
    obj = [board.object_points().astype(np.float32)] * len(corners)
    img = [c.astype(np.float32).reshape(-1, 1, 2) for c in corners]
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None, flags=CALIB_FLAGS)  # noqa: N806
    return rms, K, dist


def lofo_px(corners: list[np.ndarray], board: BoardSpec, size: tuple[int, int]) -> float:
    """Mean over frames f of the RMS error predicting frame f from intrinsics calibrated without it, px."""
    obj = board.object_points()
    errs = []
    for f, held_out in enumerate(corners):
        _, K, dist = calibrate_rms(corners[:f] + corners[f + 1 :], board, size)  # noqa: N806
        _, rvec, tvec = cv2.solvePnP(obj, held_out, K, dist, flags=cv2.SOLVEPNP_IPPE)
        rvec, tvec = cv2.solvePnPRefineLM(obj, held_out, K, dist, rvec, tvec)
        pred = cv2.projectPoints(obj, rvec, tvec, K, dist)[0].reshape(-1, 2)
        errs.append(np.sqrt(np.mean(np.sum((pred - held_out) ** 2, axis=1))))
    return float(np.mean(errs))


def real_set_rows(spec: RealSet, root: Path) -> tuple[list[list], list[str], list[str]]:
    rows, notes, failures = [], [], []
    for cam, pattern in spec.cameras.items():
        files = sorted((root / spec.folder).glob(pattern), key=_frame_key)[:: spec.step]
        if not files:
            continue
        size = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE).shape[::-1]
        det, secs = run_detectors(files, spec.board)
        n = len(files)
        for k in DETECTORS:
            missed_vs_b = [p.name for p, a, b in zip(files, det[k], det["B"], strict=True)
                           if a is None and b is not None]
            if missed_vs_b:
                notes.append(f"{spec.name} {cam}: {k} misses boards B finds: {', '.join(missed_vs_b)}")
                if k == "A":
                    failures.append(f"{spec.name} {cam}: A misses {len(missed_vs_b)} boards B finds")
        missed_b = [p.name for p, a, b in zip(files, det["A"], det["B"], strict=True) if b is None and a is not None]
        if missed_b:
            notes.append(f"{spec.name} {cam}: B misses boards A finds: {', '.join(missed_b)}")
        common = [i for i in range(n) if all(det[k][i] is not None for k in DETECTORS)]
        stats = {}
        if len(common) >= MIN_FRAMES_FOR_LOFO:
            for k in DETECTORS:
                cs = [det[k][i] for i in common]
                stats[k] = (calibrate_rms(cs, spec.board, size)[0], lofo_px(cs, spec.board, size))
        ratio = secs["A"] / secs["B"]
        row = [spec.name, cam, n, *(sum(c is not None for c in det[k]) for k in DETECTORS),
               *(1000 * secs[k] / n for k in DETECTORS), ratio, len(common) if stats else None]
        row += [stats[k][0] if stats else None for k in DETECTORS] + [stats[k][1] if stats else None for k in DETECTORS]
        rows.append(row)
        if stats and stats["A"][1] > TARGET_LOFO_RATIO * stats["B"][1]:
            failures.append(f"{spec.name} {cam}: LOFO A {stats['A'][1]:.4f} px > {TARGET_LOFO_RATIO} x B "
                            f"{stats['B'][1]:.4f} px")
    return rows, notes, failures


def rendered_truth_rows() -> tuple[list[list], list[str]]:
    """Detection error against the true corners on the rendered boards of tests/detect/test_checkerboard.py."""
    from lfgraph.datasets.checkerboard import CheckerboardConfig, iter_view_images, make_checkerboard_truth
    from lfgraph.datasets.rig import RigConfig, make_rig

    calib = make_rig(RigConfig(rows=2, cols=2, image_size_px=(640, 480), focal_px=600, k1=-0.12, pitch_m=0.01),
                     np.random.default_rng(0))
    cfg = CheckerboardConfig(board=BoardSpec(7, 5, 0.02), frames=6, distance_m=(0.3, 0.6), noise_sigma=0.0)
    truth = make_checkerboard_truth(calib, cfg, np.random.default_rng(1))
    sq = {k: [] for k in DETECTORS}
    found = dict.fromkeys(DETECTORS, 0)
    for v in range(calib.num_views):
        for f, img in iter_view_images(calib, truth, cfg, seed=0, view=v):
            if not truth.board_visible[v, f]:
                continue
            for k, fn in DETECTORS.items():
                c = fn(img, cfg.board)
                if c is not None:
                    found[k] += 1
                    sq[k].append(np.sum((c - truth.corners_px[v, f]) ** 2, axis=1))
    rms = {k: float(np.sqrt(np.mean(np.concatenate(sq[k])))) for k in DETECTORS}
    failures = [] if rms["A"] <= TARGET_RENDERED_RMS_PX else [f"rendered RMS A {rms['A']:.4f} px"]
    return [[int(truth.board_visible.sum()), *(found[k] for k in DETECTORS), *(rms[k] for k in DETECTORS)]], failures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding the shared real sets")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    start = time.perf_counter()
    rows, notes, failures = [], [], []
    for spec in SETS:
        if not (args.data / spec.folder).is_dir():
            print(f"skipping {spec.name}: {args.data / spec.folder} not present")
            continue
        r, n, f = real_set_rows(spec, args.data)
        rows += r
        notes += n
        failures += f
    headers = ["set", "camera", "images", "found A", "B", "C", "ms/img A", "B", "C", "A/B time", "common",
               "RMS A", "B", "C", "LOFO A", "B", "C"]
    if rows:
        print("Real sets (RMS: calibrateCamera k1 k2, px; LOFO: leave-one-frame-out prediction error, px)")
        print(format_table(headers, rows, floatfmt=".4g"))
        for n in notes:
            print("  " + n)
        total = {k: sum(r[3 + i] for r in rows) for i, k in enumerate(DETECTORS)}
        ratio_all = sum(r[6] * r[2] for r in rows) / sum(r[7] * r[2] for r in rows)
        print(f"boards found: A {total['A']}, B {total['B']}, C {total['C']}; time A/B over all images "
              f"{ratio_all:.3f} (target <= {TARGET_TIME_RATIO:.3f})")
        if ratio_all > TARGET_TIME_RATIO:
            failures.append(f"A takes {ratio_all:.2f} x B's time")
    truth_rows, f = rendered_truth_rows()
    failures += f
    print("\nRendered boards (tests/detect/test_checkerboard.py setup), error against the true corners, px")
    print(format_table(["visible", "found A", "B", "C", "RMS A", "B", "C"], truth_rows, floatfmt=".4f"))
    print(f"\n{time.perf_counter() - start:.0f} s")
    for msg in failures:
        print("TARGET MISSED: " + msg)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
