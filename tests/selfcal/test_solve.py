"""The staged graph's helpers: where the landmarks start when the design geometry cannot triangulate them."""

from __future__ import annotations

import numpy as np

from lfgraph.core.camera import project_world
from lfgraph.engine.triangulate import triangulate_dlt
from lfgraph.selfcal import Design
from lfgraph.selfcal.solve import MIN_DLT_FRONT_SHARE, NO_DEPTH_DISPARITY_PX, initial_landmarks
from lfgraph.selfcal.stages import reachable

# the paper-4x4 benchmark rig's design (its rig seed 4 refused with 0 tracks before its first stage)
DESIGN = Design(4, 4, pitch_mm=6.0, focal_px=425.0, image_size_px=(480, 480))
TOE_OUT_DEG = 5.0  # the outer column turned out by this (the others in proportion to their offset)
DEPTH_M = (0.5, 2.0)
RAY_TOLERANCE_PX = 1e-6  # a landmark put on its reference ray reprojects there to round-off


def toed_out_tracks(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Exact tracks of landmarks at ``DEPTH_M`` through views turned outwards in proportion to their column offset:
    through the parallel design views every landmark triangulates behind the reference view."""
    nominal = DESIGN.calibration()
    poses = np.array(nominal.ref_T_view)
    outer = float(np.max(poses[:, 0, 3]))
    for v in range(nominal.num_views):
        a = -np.radians(TOE_OUT_DEG) * poses[v, 0, 3] / outer
        poses[v, :3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    truth = nominal.replace(ref_T_view=poses)
    uv = rng.uniform(40.0, 440.0, (n, 2))
    z = rng.uniform(*DEPTH_M, n)
    points = np.column_stack([nominal.intrinsics[0].undistort(uv) * z[:, None], z])
    pixels = np.stack([project_world(truth.intrinsics[v], truth.view_T_ref(v), points) for v in range(16)])
    return pixels, np.ones(pixels.shape[:2], dtype=bool)


def test_landmarks_the_design_puts_behind_start_where_the_array_sees_them():
    nominal = DESIGN.calibration()
    pixels, valid = toed_out_tracks(200, np.random.default_rng(0))
    assert np.all(triangulate_dlt(nominal, pixels, valid)[:, 2] < 0)  # the case: none in front of the reference
    points = initial_landmarks(nominal, pixels, valid)
    # all kept by the depth rule (the old start, 1000x the largest view offset, put them at 18 m: none kept)
    assert reachable(nominal, points, valid, DESIGN.focal_px).all()
    centres = nominal.ref_T_view[:, :3, 3]
    span_m = np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1))
    assert np.allclose(points[:, 2], DESIGN.focal_px * span_m / NO_DEPTH_DISPARITY_PX)
    ref = nominal.grid.reference
    back = project_world(nominal.intrinsics[ref], nominal.view_T_ref(ref), points)
    assert np.max(np.abs(back - pixels[ref])) < RAY_TOLERANCE_PX


def test_a_few_landmarks_in_front_do_not_set_the_others_start():
    # rig seed 4 at 20 frames: 35 of 5686 in front at 0-4 mm, whose median started every other landmark
    nominal = DESIGN.calibration()
    pixels, valid = toed_out_tracks(200, np.random.default_rng(1))
    near = np.column_stack([np.full(4, 0.001), np.full(4, 0.002), np.linspace(0.002, 0.004, 4)])
    extra = np.stack([project_world(nominal.intrinsics[v], nominal.view_T_ref(v), near) for v in range(16)])
    pixels = np.concatenate([pixels, extra], axis=1)
    valid = np.ones(pixels.shape[:2], dtype=bool)
    front = triangulate_dlt(nominal, pixels, valid)[:, 2] > 0
    assert 0 < np.mean(front) < MIN_DLT_FRONT_SHARE  # the case
    points = initial_landmarks(nominal, pixels, valid)
    assert reachable(nominal, points, valid, DESIGN.focal_px).all()
    assert np.ptp(points[:, 2]) == 0.0  # all on their rays at the one depth
