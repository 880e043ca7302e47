"""How the self-calibration's common zoom scatters under its tracks' own errors, against its posterior sigma.

One rig seed gives one draw of the zoom's error, so `benchmarks/targetless.py`'s error / sigma over a few rig seeds
says little about the sigma. Here the unpinned fit of ``targetless.py`` (its cache) is solved again many times on
tracks rebuilt from the truth: every track's landmark triangulated through the true cameras, projected exactly, plus
the real tracks' own errors (real pixels minus those projections) with their signs flipped at random:

- ``white``: Gaussian errors of the fit's measured noise instead (what the graph assumes);
- ``observation``: each observation's error its own random sign (the real errors' sizes, no correlation);
- ``track``: one sign per track (keeps the correlation within a track);
- ``frame``: one sign per frame for all its tracks (keeps the correlation within a frame too).

Draw 0 is the real errors unflipped (the fit itself). Each draw is the scene's final stage from its optimum, and the
zoom's error over the draw's posterior sigma; the RMS over draws is about 1 when the sigma is honest for errors of
that structure. (The zoom's error includes the design prior's pull towards the nominal focal length, the same in
every draw.)

    python benchmarks/targetless_zoom_scatter.py --rig paper-4x4 --seed 2 --frames 10 --mode frame --draws 30
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import targetless as bench  # noqa: E402
import targetless_data as data  # noqa: E402

from lfgraph.core.camera import project_world  # noqa: E402
from lfgraph.engine.stage_engine import FINAL_RELATIVE_TOL  # noqa: E402
from lfgraph.engine.triangulate import triangulate_dlt  # noqa: E402
from lfgraph.factors.noise import RobustKernel  # noqa: E402
from lfgraph.selfcal import SelfCalConfig  # noqa: E402
from lfgraph.selfcal.pinned import zoom_of  # noqa: E402
from lfgraph.selfcal.solve import LANDMARK_ITERATIONS, measurement, posterior, run_map_stage  # noqa: E402

MODES = ("white", "observation", "track", "frame")
MAX_ITERATIONS = 300


def signs(mode: str, shape: tuple[int, int], frame: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(V, N) random signs of the real errors: per observation, per track or per frame (module docstring)."""
    if mode == "observation":
        return rng.choice([-1.0, 1.0], size=shape)
    if mode == "track":
        return np.broadcast_to(rng.choice([-1.0, 1.0], size=(1, shape[1])), shape)
    return np.broadcast_to(rng.choice([-1.0, 1.0], size=int(frame.max()) + 1)[frame][None], shape)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", default="paper-4x4", choices=data.RIGS)
    parser.add_argument("--seed", type=int, default=0, help="the rig and its scenes")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--mode", default="frame", choices=MODES)
    parser.add_argument("--draws", type=int, default=30)
    parser.add_argument("--cache", type=Path, default=data.CACHE)
    args = parser.parse_args()
    config = SelfCalConfig()
    design = bench.design_of(args.rig)
    tracks = bench.first_frames(bench.tracks_for(args.rig, args.frames, config, args.cache, args.seed), args.frames)
    scene = bench.fitted(args.rig, args.frames, tracks, design, config, args.cache, args.seed)[1].scene
    truth = data.truth_rig(args.rig, args.seed)
    t = scene.tracks
    pts = triangulate_dlt(truth, t.pixels, t.valid)
    ok = np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0)
    valid, pts, frame = t.valid[:, ok], pts[ok], t.frame[ok]
    exact = np.stack([project_world(truth.intrinsics[v], truth.view_T_ref(v), pts) for v in range(truth.num_views)])
    real = np.where(valid[..., None], t.pixels[:, ok] - exact, 0.0)
    true_zoom = bench.zoom_px(truth)
    rng = np.random.default_rng(11)
    z = []
    for k in range(args.draws + 1):
        err = real if k == 0 else scene.noise_px * rng.standard_normal(real.shape) if args.mode == "white" else \
            real * signs(args.mode, valid.shape, frame, rng)[..., None]
        pixels = np.where(valid[..., None], exact + err, np.nan)
        calib, _, graph, values, _ = run_map_stage(
            scene.calib, scene.nominal, pixels, valid, scene.points[ok], scene.free, scene.sigmas,
            measurement(RobustKernel("none"), scene.noise_px), MAX_ITERATIONS, FINAL_RELATIVE_TOL, None, (),
            hold_gauges=False, landmark_iterations=LANDMARK_ITERATIONS)
        zoom, sigma = zoom_of(calib, posterior(graph, values, calib.lenses)[1], scene.sigmas, True)
        if k:
            z.append((zoom - true_zoom) / sigma)
        print(f"draw {k}{' (the real errors)' if k == 0 else ''}: zoom error {zoom - true_zoom:+.3f} px, sigma "
              f"{sigma:.3f} px, error / sigma {(zoom - true_zoom) / sigma:+.2f}", flush=True)
    z = np.array(z)
    print(f"{args.rig} seed {args.seed}, {args.frames} frames, {args.mode} signs: the zoom's error / sigma over "
          f"{len(z)} draws: RMS {np.sqrt(np.mean(z**2)):.2f}, mean {z.mean():+.2f}, sd {z.std():.2f}, "
          f"range {z.min():+.2f} to {z.max():+.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
