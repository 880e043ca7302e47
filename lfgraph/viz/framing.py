"""Where the 3-D view's eye goes, and which of the rig's labels it can show without overlap (used by
`lfgraph.viz.blueprint` and `lfgraph.viz.rerun_scene`).

The eye looks at the rig from a fixed direction (`EYE_DIRECTION`: a little left of, above and behind it, nearly along
the views, so that a grid spreads over the picture) and from the distance at which the rig — every view centre and
its frustum's image plane — fills `RIG_FILL` of rerun's field of view in a view of the default layouts' shape
(`VIEW_ASPECT`); the landmarks metres away and the boards do not move it. A 5x5, a 1x20 line and a fisheye 1x3 are
framed alike. Labels in a 3-D view are drawn at a fixed size in screen pixels whatever the zoom, so on a large rig
only some fit: `spaced_labels` picks them, most important first, so that no two overlap in the picture that eye sees
(a caption goes above the rig, `RigFrame.caption_anchor`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rerun.blueprint as rrb

from lfgraph.core.calibration import Calibration

VIEW_FOV_Y_DEG = 55.0  # rerun's vertical field of view of a 3-D view's eye (its default; a blueprint cannot set it)
VIEW_ASPECT = 1.5  # width / height of the 3-D view in the default layouts (about 650 x 430 px in a 1400 x 860 window)
VIEW_WIDTH_PX = 650.0  # ... and its width, for laying out the labels
RIG_FILL = 0.75  # the rig spans this share of the view's width or height, whichever binds
EYE_DIRECTION = (-0.3, -0.45, -1.7)  # from the rig's centre towards the eye (world = RDF: left, up, behind)
EYE_UP = (0.0, -1.0, 0.0)  # image-up (-y in the OpenCV axes) is up on the screen
FRUSTUM_BASELINE_SHARE = 0.4  # each camera's frustum is drawn this share of the smallest baseline deep
FRUSTUM_DEPTH_M = 0.02  # frustum depth of a single view (no baseline)
LABEL_CHAR_PX = 6.5  # a label character's width in rerun's UI font (px; measured on a screenshot: 6.2)
LABEL_PAD_PX = (12.0, 8.0)  # a label's box is its text plus this much (width, height), drawn below its anchor
LABEL_TEXT_HEIGHT_PX = 16.0
LABEL_OFFSET_PX = 5.0  # ... starting this far below it
LABEL_GAP_PX = 4.0  # the least gap between two labels' boxes
CAPTION_HEIGHT_SHARE = 0.95  # a caption's anchor: this share of the half-height above the centre (the rig: 0.75)


def smallest_baseline_m(calib: Calibration) -> float:
    """The smallest distance between two view centres (m); `FRUSTUM_DEPTH_M` for a single view."""
    centres = calib.ref_T_view[:, :3, 3]
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    d = d[~np.eye(len(centres), dtype=bool)]
    d = d[d > 0]
    return float(d.min()) if d.size else FRUSTUM_DEPTH_M


def frustum_depth_m(calib: Calibration) -> float:
    """How deep every view's frustum (its image plane) is drawn: `FRUSTUM_BASELINE_SHARE` of the smallest
    baseline."""
    return FRUSTUM_BASELINE_SHARE * smallest_baseline_m(calib)


def rig_points(calib: Calibration) -> np.ndarray:
    """(V + 4V, 3) what the 3-D view draws of a rig: the view centres and the corners of their frustums' image
    planes (reference frame, m)."""
    depth = frustum_depth_m(calib)
    points = [calib.ref_T_view[:, :3, 3]]
    for v in range(calib.num_views):
        w, h = calib.image_size(v)
        corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], dtype=np.float64)
        rays = corners @ np.linalg.inv(calib.intrinsics[v].K).T  # z = 1
        pose = calib.ref_T_view[v]
        points.append(pose[:3, 3] + depth * rays @ pose[:3, :3].T)
    return np.concatenate(points)


@dataclass(frozen=True)
class RigFrame:
    """An eye on a rig: where it is, what it looks at, its axes (world), and the picture it sees."""

    position: np.ndarray
    target: np.ndarray
    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray

    def eye(self) -> rrb.EyeControls3D:
        """The blueprint's 3-D eye."""
        return rrb.EyeControls3D(position=self.position, look_target=self.target, eye_up=self.up)

    def pixels(self, points: np.ndarray, width_px: float = VIEW_WIDTH_PX) -> np.ndarray:
        """(N, 2) where (N, 3) world points appear in a view ``width_px`` wide of `VIEW_ASPECT` (px from its top
        left); NaN behind the eye."""
        rel = np.asarray(points, dtype=np.float64) - self.position
        depth = rel @ self.forward
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(depth > 0, (rel @ self.right) / depth, np.nan)
            y = np.where(depth > 0, (rel @ self.up) / depth, np.nan)
        tan_v = np.tan(np.radians(VIEW_FOV_Y_DEG) / 2)
        height_px = width_px / VIEW_ASPECT
        return np.column_stack([width_px / 2 * (1 + x / (tan_v * VIEW_ASPECT)), height_px / 2 * (1 - y / tan_v)])

    def caption_anchor(self) -> np.ndarray:
        """(3,) a point in the target's plane that the eye sees centred above the rig, at the top of the margin
        that `RIG_FILL` leaves (labels hang below their anchors: the views' never reach up there): where a caption
        of the scene goes."""
        tan_v = np.tan(np.radians(VIEW_FOV_Y_DEG) / 2)
        distance = float(np.linalg.norm(self.target - self.position))
        return self.target + CAPTION_HEIGHT_SHARE * tan_v * distance * self.up


def rig_frame(calib: Calibration) -> RigFrame:
    """The eye on ``calib``'s rig: from `EYE_DIRECTION`, at the distance where the rig (`rig_points`) fills
    `RIG_FILL` of the view's width or height."""
    points = rig_points(calib)
    target = 0.5 * (points.min(axis=0) + points.max(axis=0))
    back = np.asarray(EYE_DIRECTION, dtype=np.float64) / np.linalg.norm(EYE_DIRECTION)
    forward = -back
    right = np.cross(forward, EYE_UP)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = points - target
    x, y, z = np.abs(rel @ right), np.abs(rel @ up), rel @ forward
    tan_v = RIG_FILL * np.tan(np.radians(VIEW_FOV_Y_DEG) / 2)
    # a point at (x, y, z) about the target is in the filled share when |x| <= tan_h (d + z), |y| <= tan_v (d + z)
    distance = max(float(np.max(x / (VIEW_ASPECT * tan_v) - z)), float(np.max(y / tan_v - z)),
                   float(np.max(-z)) + smallest_baseline_m(calib))
    return RigFrame(target + distance * back, target, right, up, forward)


def rig_eye(calib: Calibration) -> rrb.EyeControls3D:
    """A 3-D eye on the rig (`rig_frame`), so that the views (not landmarks metres away) fill the picture."""
    return rig_frame(calib).eye()


def spaced_labels(frame: RigFrame, anchors: np.ndarray, labels: list[str], order: list[int]) -> list[int]:
    """Which ``labels`` to show: in ``order`` (most important first) each one whose box, where ``frame``'s eye sees
    its anchor (rerun draws a label centred below its anchor), lies inside the view and keeps `LABEL_GAP_PX` from
    every box chosen before."""
    px = frame.pixels(anchors)
    width, height = VIEW_WIDTH_PX, VIEW_WIDTH_PX / VIEW_ASPECT
    chosen: list[int] = []
    boxes: list[tuple[float, float, float, float]] = []
    for i in order:
        u, v = px[i]
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        half_w = 0.5 * (LABEL_CHAR_PX * len(labels[i]) + LABEL_PAD_PX[0]) + 0.5 * LABEL_GAP_PX
        top = v + LABEL_OFFSET_PX - 0.5 * LABEL_PAD_PX[1] - 0.5 * LABEL_GAP_PX
        box = (u - half_w, top, u + half_w, top + LABEL_TEXT_HEIGHT_PX + LABEL_PAD_PX[1] + LABEL_GAP_PX)
        if box[0] < 0 or box[1] < 0 or box[2] > width or box[3] > height:
            continue
        if all(box[2] <= b[0] or b[2] <= box[0] or box[3] <= b[1] or b[3] <= box[1] for b in boxes):
            chosen.append(i)
            boxes.append(box)
    return chosen
