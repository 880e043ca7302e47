"""What a recording's 3-D and 2-D views show at the default zoom (issue 40): the eye read back from the .rrd frames the
rig — a 5x5, an 8x8, a 1x8, a 1x20, a fisheye 1x3 — and not the landmarks metres away, the change labels shown fit
side by side, and a fisheye view draws its points only inside its (undistorted) image. Fast: no rendering, only the
logger and rerun's reader."""

import dataclasses

import numpy as np
import pytest

from lfgraph.core.camera import project_world, view_to_pinhole_px
from lfgraph.datasets.rig import ShakeConfig, make_rig, shake_rig
from lfgraph.datasets.scenes import get_scene
from lfgraph.viz import RerunLogger
from tests.viz.test_rerun import (
    RERUN_FOV_Y_DEG,
    RIG_MIN_WIDTH_SHARE,
    VIEW_ASPECT,
    read_blueprint,
    read_rrd,
    view_share,
)

LANDMARK_DEPTH_M = (2.0, 8.0)  # the landmarks of the scenes: 2-8 m in front of the rig
LABEL_CHAR_PX = 6.2  # a label character in rerun's UI font, px (measured on a screenshot: 20 characters, 123 px)
LABEL_BOX_PX = (12.0, 24.0)  # a label's box: its text plus 12 px wide, 24 px high, drawn below its anchor
VIEW_WIDTH_PX = 650.0  # the default layouts' 3-D view in a 1400x860 window (screenshots)
MIN_LABELS_5X5 = 5  # a shaken 5x5 (24 changed views) shows at least this many change labels side by side
EDGE_PX = 0.5  # a point on the image's border is inside it (pixel centres run 0 .. w-1)


def rig(scene: str, rows: int | None = None, cols: int | None = None, seed: int = 0):
    config = get_scene(scene).rig
    if rows is not None:
        config = dataclasses.replace(config, rows=rows, cols=cols, reference=0)
    return make_rig(config, np.random.default_rng(seed))


def far_landmarks(calib, n: int = 400, seed: int = 1) -> np.ndarray:
    """(n, 3) points spread 2-8 m in front of the rig, over its field of view."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(*LANDMARK_DEPTH_M, n)
    return np.column_stack([rng.uniform(-1, 1, n) * depth, rng.uniform(-0.7, 0.7, n) * depth, depth])


@pytest.mark.parametrize(("scene", "rows", "cols"), [("paper-5x5", None, None), ("paper-5x5", 1, 8),
                                                     ("paper-5x5", 8, 8), ("paper-5x5", 1, 20),
                                                     ("fisheye-1x3", None, None)])
def test_default_eye_frames_the_rig_not_the_landmarks(tmp_path, scene, rows, cols):
    """A refinement logged through `to_file(path, grid)` (no kind: the README's snippet) opens in refine's layout
    with the eye on the rig: its views span at least a third of the 3-D view's width, all inside it, and the eye is
    nearer the rig than any landmark is."""
    calib = rig(scene, rows, cols)
    landmarks = far_landmarks(calib)
    with RerunLogger.to_file(tmp_path / "r.rrd", calib.grid) as rec:
        rec.run_start("refine", calib)
        rec.landmarks(landmarks, np.zeros(len(landmarks)))
    eye = []
    views, _ = read_blueprint(tmp_path / "r.rrd", eye)
    assert ("TextLog", "optimizer/stages") in {(k, o) for k, o, _ in views}  # refine's layout, not calibrate's
    centres = calib.ref_T_view[:, :3, 3]
    width, height, reach = view_share(eye[0], centres)
    assert width >= RIG_MIN_WIDTH_SHARE and reach <= 1.0, (width, height, reach)
    position, target, _ = eye[0]
    assert np.linalg.norm(target - centres.mean(axis=0)) < np.ptp(centres, axis=0).max() / 2 + 1e-9  # on the rig
    assert np.linalg.norm(position - target) < np.linalg.norm(landmarks - target, axis=1).min()


def label_boxes(eye, anchors: np.ndarray, labels: list[str]) -> np.ndarray:
    """(N, 4) screen boxes (left, top, right, bottom; px) of labels as rerun draws them: centred below their anchor
    in a view `VIEW_WIDTH_PX` wide of `VIEW_ASPECT`."""
    position, target, up = eye
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = anchors - position
    depth = rel @ forward
    tan_v = np.tan(np.radians(RERUN_FOV_Y_DEG) / 2)
    height_px = VIEW_WIDTH_PX / VIEW_ASPECT
    u = VIEW_WIDTH_PX / 2 * (1 + rel @ right / depth / (tan_v * VIEW_ASPECT))
    v = height_px / 2 * (1 - rel @ up / depth / tan_v)
    half = 0.5 * (LABEL_CHAR_PX * np.array([len(s) for s in labels]) + LABEL_BOX_PX[0])
    return np.column_stack([u - half, v, u + half, v + LABEL_BOX_PX[1]])


def test_change_labels_fit_side_by_side(tmp_path):
    """Issue 40: a 5x5's 25 labels overlapped into a smear. Every view's change stays in its arrow's label (hover);
    those drawn (``world/change/labels``: a caption with the arrows' factor, then the largest changes) do not
    overlap in the default eye's picture and lie inside it."""
    before = rig("paper-5x5")
    after = shake_rig(before, ShakeConfig(rot_deg=1.0, trans_mm=3.0, axis="any"), np.random.default_rng(2))
    with RerunLogger.to_file(tmp_path / "c.rrd", before.grid) as rec:
        rec.refinement_result(before, after)
    eye = []
    read_blueprint(tmp_path / "c.rrd", eye)
    _, static, _ = read_rrd(tmp_path / "c.rrd", None)
    assert len(static["/world/change:Arrows3D:labels"][0]) == before.num_views
    assert static["/world/change:Arrows3D:show_labels"][0] == [False]
    labels = static["/world/change/labels:Points3D:labels"][0]
    anchors = np.array(static["/world/change/labels:Points3D:positions"][0])
    assert "arrows x" in labels[0] and len(labels) > MIN_LABELS_5X5, labels
    boxes = label_boxes(eye[0], anchors, labels)
    height_px = VIEW_WIDTH_PX / VIEW_ASPECT
    assert boxes[:, 0].min() >= 0 and boxes[:, 2].max() <= VIEW_WIDTH_PX and boxes[:, 3].max() <= height_px
    for i in range(len(boxes)):
        for j in range(i):
            a, b = boxes[i], boxes[j]
            overlap = min(a[2], b[2]) - max(a[0], b[0]), min(a[3], b[3]) - max(a[1], b[1])
            assert min(overlap) <= 0, (labels[i], labels[j])


def test_fisheye_points_only_inside_their_image(tmp_path):
    """Issue 40: a fisheye's periphery, shown undistorted to the pinhole of its K, lands far outside that pinhole's
    image: the 2-D views drew such tracks in bands above and below the image. Only what lies inside is drawn."""
    calib = rig("fisheye-1x3")
    rng = np.random.default_rng(3)
    angle = np.radians(rng.uniform(0, 62, 3000))  # up to 62 deg off axis: inside the fisheye's ~120 deg diagonal
    azimuth = rng.uniform(0, 2 * np.pi, 3000)
    world = 3.0 * np.column_stack([np.sin(angle) * np.cos(azimuth), np.sin(angle) * np.sin(azimuth), np.cos(angle)])
    w, h = calib.image_size(0)
    observed = np.stack([project_world(calib.intrinsics[v], calib.view_T_ref(v), world)
                         for v in range(calib.num_views)])
    valid = np.all((observed >= 0) & (observed <= [w - 1, h - 1]), axis=-1)  # tracks the fisheye images hold
    shown = view_to_pinhole_px(observed[0][valid[0]], calib.intrinsics[0].K, np.eye(3), calib.intrinsics[0])
    outside = ~np.all((shown >= -EDGE_PX) & (shown <= [w - EDGE_PX, h - EDGE_PX]), axis=1)
    assert outside.sum() > 100  # the case of the issue: many of them fall outside the pinhole image
    with RerunLogger.to_file(tmp_path / "f.rrd", calib.grid, "refine") as rec:
        rec.rig(calib, name="refined_rig")
        rec.rec.set_time("frame", sequence=0)
        rec.observations(calib, observed, observed + 0.2, valid, [observed[v][valid[v]] for v in range(3)])
    _, _, rows = read_rrd(tmp_path / "f.rrd", "frame")
    for v in range(calib.num_views):
        name = calib.grid.name(v)
        for part, column in (("observed", "Points2D:positions"), ("reprojected", "Points2D:positions"),
                             ("residuals", "Arrows2D:origins"), ("outliers", "Points2D:positions")):
            px = np.array([p for p in rows[f"/views/{name}/{part}:{column}"] if p is not None][-1])
            assert len(px) > 0, (name, part)
            assert np.all((px >= -EDGE_PX) & (px <= [w - EDGE_PX, h - EDGE_PX])), (name, part)
        kept = np.array([p for p in rows[f"/views/{name}/observed:Points2D:positions"] if p is not None][-1])
        assert len(kept) < valid[v].sum()  # ... and those outside were left out
