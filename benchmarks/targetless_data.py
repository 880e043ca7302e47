"""Rigs and rendered scene frames of the target-less benchmark (`benchmarks/targetless.py`), cached on disk.

Rigs: paper-4x4 and paper-5x5 *style* arrays (and fisheye-4x4: the 4x4 through ~108 deg fisheye lenses) with the
issue's spreads (standard deviations): focal length 3 %,
principal points 15 px, k1 = -0.1 (0.01 spread), rotations 1 deg, positions 0.3 mm per axis. The 4x4 rig is rendered
at half the paper's resolution (480x480 px, f = 425 px: the same field of view) to keep rendering affordable on a
shared machine. Frames: dead-leaves scenes whose depth band cycles through three log-spaced bands of the named
scene's range, so every frame set of three or more spans near and far depths.

    python benchmarks/targetless_data.py --rig paper-5x5 --frames 30    # render (resumes; existing frames kept)
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.datasets.rig import RigConfig, make_rig
from lfgraph.datasets.scene import SceneConfig, make_scene, render_scene_view
from lfgraph.datasets.scenes import get_scene
from lfgraph.io.capture import write_frame

FOCAL_SPREAD = 0.03  # std of fx, fy relative to the design focal length
PRINCIPAL_SPREAD_PX = 15.0
K1 = -0.1
K1_SPREAD = 0.01
ROT_SPREAD_DEG = 1.0
POS_SPREAD_MM = 0.3
DEPTH_BANDS = 3  # frames cycle through this many log-spaced depth bands of the scene's range
BACKGROUND_FACTOR = 1.4  # background plane at this multiple of a frame's far depth
CACHE = Path("out/bench-targetless")


RIGS = ("paper-4x4", "paper-5x5", "fisheye-4x4")
FISHEYE_FOCAL_SCALE = 0.6  # fisheye-4x4: paper-4x4 at this times its focal length through Kannala-Brandt lenses
FISHEYE_K1, FISHEYE_K1_SPREAD = -0.02, 0.002  # (a ~108 deg field across; k2 0.004)


def base_scene(name: str):
    """The named scene a benchmark rig is built on (fisheye-4x4: paper-4x4's)."""
    return get_scene(name.replace("fisheye", "paper"))


def rig_config(name: str) -> RigConfig:
    """The benchmark rig ``paper-4x4`` or ``paper-5x5`` with the issue's spreads, or ``fisheye-4x4``: the 4x4 through
    fisheye lenses (`FISHEYE_FOCAL_SCALE`, `FISHEYE_K1`) with the same spreads of focal length, principal point,
    rotation and position."""
    base = base_scene(name).rig
    if name in ("paper-4x4", "fisheye-4x4"):
        base = dataclasses.replace(base, image_size_px=(480, 480), focal_px=base.focal_px / 2)
    k1, k1_spread, extra = K1, K1_SPREAD, {}
    if name == "fisheye-4x4":
        base = dataclasses.replace(base, focal_px=FISHEYE_FOCAL_SCALE * base.focal_px)
        k1, k1_spread, extra = FISHEYE_K1, FISHEYE_K1_SPREAD, dict(lens="fisheye", k2=0.004)
    return dataclasses.replace(base, focal_jitter_px=FOCAL_SPREAD * base.focal_px,
                               principal_jitter_px=PRINCIPAL_SPREAD_PX, k1=k1, distortion_jitter=k1_spread,
                               rot_jitter_deg=ROT_SPREAD_DEG, trans_jitter_mm=POS_SPREAD_MM, **extra)


def frame_scene_config(name: str, frame: int) -> SceneConfig:
    """Scene options of frame ``frame``: its depth band (cycling near, middle, far)."""
    near, far = base_scene(name).scene_depth_m
    edges = np.geomspace(near, far, DEPTH_BANDS + 1)
    band = frame % DEPTH_BANDS
    lo, hi = float(edges[band]), float(edges[band + 1])
    return SceneConfig(depth_m=(lo, hi), background_depth_m=hi * BACKGROUND_FACTOR)


def truth_rig(name: str, seed: int = 0) -> Calibration:
    """The ground-truth rig of the benchmark (seeded)."""
    return make_rig(rig_config(name), np.random.default_rng([seed, 17]))


def dataset_dir(name: str, seed: int = 0, cache: Path = CACHE) -> Path:
    return cache / f"{name}_seed{seed}"


def render(name: str, frames: int, seed: int = 0, cache: Path = CACHE) -> Path:
    """Render frames 0..frames-1 of rig ``name`` (skipping frames already on disk); returns the folder."""
    truth = truth_rig(name, seed)
    out = dataset_dir(name, seed, cache)
    out.mkdir(parents=True, exist_ok=True)
    truth.save(out / "truth.json")
    last = truth.grid.name(truth.num_views - 1)
    for f in range(frames):
        if (out / f"{f:03d}" / f"{last}.png").exists():
            continue
        cfg = frame_scene_config(name, f)
        scene = make_scene(cfg, np.random.default_rng([seed, 23, f]))
        images = np.stack([render_scene_view(scene, truth.intrinsics[v], truth.image_size_px, truth.view_T_ref(v),
                                             cfg, np.random.default_rng([seed, 29, f, v]))
                           for v in range(truth.num_views)])
        write_frame(out, f"{f:03d}", images, truth.grid)
        print(f"{name}: frame {f} rendered", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", choices=RIGS, required=True)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=CACHE)
    args = parser.parse_args()
    render(args.rig, args.frames, args.seed, args.cache)


if __name__ == "__main__":
    main()
