"""The peer we compare against: OpenCV 5's ``cv2.calibrateMultiview`` on the same corners.

OpenCV 5.0 facts: objects in metres (float32, one array per frame), image points per camera per frame with unseen
boards filled with -1, a (V, F) uint8 detection mask, per-camera models (CALIB_MODEL_PINHOLE) and intrinsics flags;
``Rs`` come back as rotation vectors and ``[R|T]`` is ``view_T_ref`` of camera 0's frame; intrinsics are frozen in
its joint stage. It misbehaves with partially visible boards, so give it full boards only.
"""

from __future__ import annotations

import cv2
import numpy as np

from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.detect.detections import BoardObservations
from lfgraph.pattern.lenses import MONO_FLAGS


def calibrate_multiview(obs: BoardObservations) -> tuple[tuple[Intrinsics, ...], np.ndarray]:
    """Run ``cv2.calibrateMultiview``; returns per-view intrinsics and ``ref_T_view`` (V, 4, 4) relative to
    ``obs.grid.reference``. Views must see full boards (partial ones are dropped from the mask)."""
    n_views, n_frames = obs.num_views, obs.num_frames
    full = obs.valid.all(axis=2)
    mask = full.astype(np.uint8)
    obj = [obs.board.object_points().astype(np.float32)] * n_frames
    img = [[obs.corners_px[v, f].astype(np.float32) if full[v, f]
            else np.full((obs.board.num_corners, 2), -1, np.float32) for f in range(n_frames)]
           for v in range(n_views)]
    models = np.full((n_views, 1), cv2.CALIB_MODEL_PINHOLE, np.uint8)
    flags = np.full((n_views, 1), MONO_FLAGS, np.int32)
    out = cv2.calibrateMultiview(obj, img, [obs.image_size_px] * n_views, mask, models, None, None, None, None,
                                 flagsForIntrinsics=flags)
    _, Ks, dists, Rs, Ts = out[:5]  # noqa: N806
    intr = tuple(Intrinsics.from_opencv(K, np.concatenate([np.ravel(d)[:4], [0.0]]))
                 for K, d in zip(Ks, dists, strict=True))
    view_T_ref0 = [make_T(rotation_from_rotvec(np.ravel(R)) if np.size(R) == 3 else np.asarray(R), np.ravel(T))  # noqa: N806
                   for R, T in zip(Rs, Ts, strict=True)]
    poses = np.stack([invert_T(T) for T in view_T_ref0])
    ref = obs.grid.reference
    poses = invert_T(poses[ref])[None] @ poses
    poses[ref] = np.eye(4)
    return intr, poses
