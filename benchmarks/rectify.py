"""Rectification speed: LUT build and remapping of a 16-view 960x960 capture, against OpenCV float maps.

Peer: what an OpenCV user writes — ``cv2.initUndistortRectifyMap(..., CV_32FC1)`` per view and ``cv2.remap`` with
the float maps. lfgraph builds the same maps in OpenCV's fixed-point form (CV_16SC2 + interpolation table) and
remaps the views on a thread pool. Also prints the alignment at infinity of the true and an estimated calibration.
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from lfgraph.cli.tables import alignment_table, format_table
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.rig import make_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.detect.detections import observations_from_arrays
from lfgraph.judge.alignment import infinity_alignment
from lfgraph.pattern import CalibrateConfig, calibrate
from lfgraph.rectification.rectify import build_maps, compute_rectification, remap_views

REPEATS = 10
TARGET_BUILD_S = 1.0
TARGET_REMAP_S = 0.050


def best_of(fn, repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.min(times))


def main() -> int:
    scene = get_scene("paper-4x4")
    rng = np.random.default_rng(0)
    calib = make_rig(scene.rig, rng)
    w, h = calib.image_size_px
    images = np.stack([(np.random.default_rng(v).random((h, w)) * 255).astype(np.uint8)
                       for v in range(calib.num_views)])

    build_ours = best_of(lambda: build_maps(calib, compute_rectification(calib)), 3)
    rect = compute_rectification(calib)
    maps = build_maps(calib, rect)

    def build_peer():
        return [cv2.initUndistortRectifyMap(i.K, i.dist_cv, rect.rect_R_view[v], rect.K_r, rect.image_size_px,
                                            cv2.CV_32FC1) for v, i in enumerate(calib.intrinsics)]

    build_cv = best_of(build_peer, 3)
    float_maps = build_peer()
    remap_serial = best_of(lambda: remap_views(images, maps))
    pool = ThreadPoolExecutor(max_workers=2)

    def remap_threads():
        list(pool.map(lambda a: cv2.remap(images[a], maps.map_xy[a], maps.map_frac[a], cv2.INTER_LINEAR),
                      range(calib.num_views)))

    remap_pool = best_of(remap_threads)
    remap_peer = best_of(lambda: [cv2.remap(images[v], mx, my, cv2.INTER_LINEAR)
                                  for v, (mx, my) in enumerate(float_maps)])
    lut_mb = sum(m.nbytes + f.nbytes for m, f in zip(maps.map_xy, maps.map_frac, strict=True)) / 2**20
    peer_mb = sum(mx.nbytes + my.nbytes for mx, my in float_maps) / 2**20
    rows = [["LUT build (incl. rectification), 16 views", f"{build_ours:.3f} s", f"{build_cv:.3f} s",
             f"{build_ours / build_cv:.2f}", f"< {TARGET_BUILD_S:g}"],
            ["remap 16 views (one thread)", f"{remap_serial * 1e3:.1f} ms", f"{remap_peer * 1e3:.1f} ms",
             f"{remap_serial / remap_peer:.2f}", "-"],
            ["remap 16 views (2 threads)", f"{remap_pool * 1e3:.1f} ms", f"{remap_peer * 1e3:.1f} ms",
             f"{remap_pool / remap_peer:.2f}", f"< {TARGET_REMAP_S * 1e3:g} ms"],
            ["LUT memory (MB)", f"{lut_mb:.0f}", f"{peer_mb:.0f}", f"{lut_mb / peer_mb:.2f}", "-"]]
    print(f"paper-4x4 rectification, {calib.num_views} views of {w}x{h} px -> {rect.image_size_px} "
          f"(OpenCV threads: {cv2.getNumThreads()})")
    print(format_table(["step", "lfgraph", "OpenCV float maps", "ratio", "target"], rows))

    truth = make_checkerboard_truth(calib, scene.checkerboard, rng)
    corners, valid = make_corner_observations(truth, 0.1, np.random.default_rng(1))
    est, _ = calibrate(observations_from_arrays(truth.board, calib.grid, calib.image_size_px, corners, valid))
    est_paper, _ = calibrate(observations_from_arrays(truth.board, calib.grid, calib.image_size_px, corners, valid),
                             CalibrateConfig(method="paper"))
    print("misalignment at infinity (true cameras, rectified with each calibration; corner noise 0.1 px):")
    print(alignment_table([
        ("true calibration", infinity_alignment(calib, rect)),
        ("lfgraph joint calibration", infinity_alignment(est, compute_rectification(est), seen_by=calib)),
        ("paper-route calibration", infinity_alignment(est_paper, compute_rectification(est_paper), seen_by=calib)),
    ]))
    failures = []
    if build_ours >= TARGET_BUILD_S:
        failures.append(f"LUT build {build_ours:.2f} s")
    if remap_pool >= TARGET_REMAP_S:
        failures.append(f"remap {remap_pool * 1e3:.1f} ms")
    print("targets missed: " + ("; ".join(failures) if failures else "none"))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
