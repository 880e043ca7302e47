"""What the self-calibration's zoom error is made of, against the ray-cast truth of `benchmarks/targetless.py`'s rigs.

For the cached unpinned fit of a rig seed: every track's true point is the rendered depth at its reference pixel
(tracks whose reference pixel lies within `EDGE_PX` of a depth change of `EDGE_DEPTH` are "depth-edge" tracks: their
true error is taken against the track's point triangulated through the true cameras instead), the track's error is
its pixels minus the true projections, and each observation's pull on the zoom (`lfgraph.selfcal.scatter`) turns
the errors into the zoom's error, linearly: summed over all tracks, per frame, over flat and depth-edge tracks. Then
the zoom's spread with tracks or frames as clusters, from the true errors and from the residuals (what the sandwich
sees), and the flat tracks' pull when the chain tracks are re-tracked with the final fit's local maps.

    python benchmarks/targetless_zoom_anatomy.py --rig paper-4x4 --seed 5 --frames 10
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import targetless as bench  # noqa: E402
import targetless_data as data  # noqa: E402

from lfgraph.datasets.scene import make_scene, render_scene_depth  # noqa: E402
from lfgraph.engine.stage_engine import FINAL_RELATIVE_TOL  # noqa: E402
from lfgraph.engine.triangulate import (
    project_views,  # noqa: E402
    triangulate_dlt,  # noqa: E402
)
from lfgraph.factors.noise import RobustKernel  # noqa: E402
from lfgraph.selfcal import SelfCalConfig  # noqa: E402
from lfgraph.selfcal.pinned import mode_rows  # noqa: E402
from lfgraph.selfcal.retrack import retrack  # noqa: E402
from lfgraph.selfcal.scatter import mode_pulls  # noqa: E402
from lfgraph.selfcal.solve import LANDMARK_ITERATIONS, measurement, posterior, run_map_stage  # noqa: E402

EDGE_PX = 4  # a depth-edge track: a depth change beyond EDGE_DEPTH within this many px of its reference pixel
EDGE_DEPTH = 0.01


def true_points(rig: str, seed: int, truth, tracks) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) each track's true point from the ray-cast depth at its reference pixel and (N,) whether it is flat."""
    ref = truth.grid.reference
    points, flat = np.full((tracks.num_tracks, 3), np.nan), np.zeros(tracks.num_tracks, dtype=bool)
    inv = np.linalg.inv(truth.view_T_ref(ref))
    for f in np.unique(tracks.frame):
        scene = make_scene(data.frame_scene_config(rig, int(f)), np.random.default_rng([seed, 23, int(f)]))
        depth = render_scene_depth(scene, truth.intrinsics[ref], truth.image_size_px, truth.view_T_ref(ref))
        mine = np.nonzero(tracks.frame == f)[0]
        uv = tracks.pixels[ref, mine]
        z = 1.0 / cv2.remap((1.0 / depth).astype(np.float32), uv[:, 0].astype(np.float32),
                            uv[:, 1].astype(np.float32), cv2.INTER_LINEAR).ravel()
        near = cv2.erode(np.nan_to_num(depth, nan=0.0), np.ones((2 * EDGE_PX + 1,) * 2))
        far = cv2.dilate(np.nan_to_num(depth, nan=np.inf), np.ones((2 * EDGE_PX + 1,) * 2))
        col, row = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        flat[mine] = far[row, col] - near[row, col] < EDGE_DEPTH * depth[row, col]
        cam = np.column_stack([truth.intrinsics[ref].undistort(uv) * z[:, None], z])
        points[mine] = cam @ inv[:3, :3].T + inv[:3, 3]
    return points, flat


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", default="paper-4x4", choices=data.RIGS)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--cache", type=Path, default=data.CACHE)
    args = parser.parse_args()
    config = SelfCalConfig()
    chain = bench.first_frames(bench.tracks_for(args.rig, args.frames, config, args.cache, args.seed), args.frames)
    est, report = bench.fitted(args.rig, args.frames, chain, bench.design_of(args.rig), config, args.cache, args.seed)
    scene, truth = report.scene, data.truth_rig(args.rig, args.seed)
    t = scene.tracks
    calib, points, graph, values, _ = run_map_stage(
        scene.calib, scene.nominal, t.pixels, t.valid, scene.points, scene.free, scene.sigmas,
        measurement(RobustKernel("none"), scene.noise_px), 300, FINAL_RELATIVE_TOL, None, (), hold_gauges=False,
        landmark_iterations=LANDMARK_ITERATIONS)
    cameras = posterior(graph, values, calib.lenses, poses=True)[1]
    n_cal = len(cameras) - 6 * calib.num_views
    rows = mode_rows(calib.grid, calib.num_views, n_cal // calib.num_views)[:1]  # the zoom
    pull = mode_pulls(calib, values, points, t.valid, cameras, rows)[0] / scene.noise_px**2
    true_pts, flat = true_points(args.rig, args.seed, truth, t)
    exact = np.where(flat[None, :, None], project_views(truth, true_pts),
                     project_views(truth, triangulate_dlt(truth, t.pixels, t.valid)))
    err = np.where(t.valid[..., None], np.nan_to_num(t.pixels - exact), 0.0)
    res = np.where(t.valid[..., None], np.nan_to_num(t.pixels - project_views(calib, points)), 0.0)
    zoom_error = bench.zoom_px(calib) - bench.zoom_px(truth)
    sigma = float(np.sqrt(rows[0] @ cameras[:n_cal, :n_cal] @ rows[0]))
    by_track, by_res = np.einsum("vni,vni->n", pull, err), np.einsum("vni,vni->n", pull, res)
    frames = np.unique(t.frame)
    by_frame = np.array([by_track[t.frame == f].sum() for f in frames])
    print(f"{args.rig} seed {args.seed}, {args.frames} frames: zoom error {zoom_error:+.2f} px, the graph's sigma "
          f"{sigma:.2f} px; {t.num_tracks} tracks, {flat.sum()} flat")
    print(f"the true errors' pull on the zoom: {by_track.sum():+.2f} px; flat tracks {by_track[flat].sum():+.2f}, "
          f"depth-edge tracks {by_track[~flat].sum():+.2f}")
    print("per frame: " + " ".join(f"{c:+.2f}" for c in by_frame))
    print(f"spread with tracks as clusters: from the truth {np.sqrt(np.sum(by_track**2)):.2f} px, from the residuals "
          f"{np.sqrt(np.sum(by_res**2)):.2f} px; frames as clusters: from the truth "
          f"{np.sqrt(np.sum(by_frame**2)):.2f} px, from the residuals "
          f"{np.sqrt(sum(by_res[t.frame == f].sum() ** 2 for f in frames)):.2f} px")
    ref = truth.grid.reference
    def keys(tracks) -> list[tuple]:  # a track: its frame and reference pixel
        return [(int(f), float(x), float(y)) for (x, y), f in zip(tracks.pixels[ref], tracks.frame, strict=True)]

    column = {k: j for j, k in enumerate(keys(chain))}
    mine = chain.subset(np.array([column[k] for k in keys(t)]))
    again, _, done, _ = retrack(mine.pixels, mine.valid, mine.patches, calib, points)
    use = done & t.valid & flat[None] & np.all(np.isfinite(t.pixels), axis=2)
    for name, px in (("as fitted", t.pixels), ("re-tracked with the final fit's maps", again)):
        e = np.where(use[..., None], np.nan_to_num(px - exact), 0.0)
        print(f"flat tracks {name}: error RMS {np.sqrt(np.sum(e**2) / use.sum() / 2):.4f} px, pull on the zoom "
              f"{np.einsum('vni,vni->', pull, e):+.2f} px")
    return 0


if __name__ == "__main__":
    sys.exit(main())
