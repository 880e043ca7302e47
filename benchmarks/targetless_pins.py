"""The pins of `benchmarks/targetless.py`: one board frame, or one known distance, added to a self-calibration.

- Board: one frame of the rig's checkerboard (the peer's board) held as `calibrate-scene`'s manual tells a user to:
  tilted `MIN_TILT_DEG`-`MAX_TILT_DEG` about a random in-plane axis (a board facing the array squarely sees the
  scale, which the pitch fixes, not the zoom: the zoom comes from its perspective alone), rolled as the peer's boards
  are, its centre on the array's central axis, as near as every view still sees it whole (the nearest of the peer's
  distances that does: the perspective, and with it what the frame says of the zoom, grows with the board's size in
  the image); corners = true projections + `CORNER_SIGMA_PX` Gaussian noise, seen by every view that sees it whole;
  its corner noise is left for the pin to measure. Two boards: that frame and a second one tilted about the
  perpendicular in-plane axis (one tilted plane leaves the focal length confounded with the principal point across its
  tilt axis; a second tilt about the other axis separates them, as in Zhang's method).
- Distance: two points marked in the reference view of one rendered frame (Shi–Tomasi corners on flat texture, the
  pair about `DISTANCE_M` apart with the most depth between them, among the marks the KLT follows into every view),
  their true positions from the exact depth of the rendered scene, their distance measured with a 1-sigma of
  `SIGMA_PER_M` per metre; the marks are followed into the other views by `DistancePin.followed` as
  `calibrate_scene` does.
- One view's intrinsics from an earlier calibration (a factory's, or the user's own): OpenCV's `calibrateCamera` of
  that view alone (a seeded view) on `VIEW_BOARDS` boards of the peer's kind, corners = true projections +
  `CORNER_SIGMA_PX` Gaussian noise, k1 and k2 free; its sigmas are OpenCV's (`calibrateCameraExtended`'s standard
  deviations): an independent calibration, not lfgraph's own.
- Distance on a plane of known depth: two marks on the background wall (a plane facing the array) of a frame of the
  nearest depth band, as far apart as the marks every view sees allow, their distance and the wall's depth each
  measured with a 1-sigma of `SIGMA_PER_M` per metre.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import targetless_data as data

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.datasets.checkerboard import make_checkerboard_truth, make_corner_observations
from lfgraph.datasets.scene import make_scene, render_scene_depth
from lfgraph.engine.triangulate import triangulate_dlt
from lfgraph.io.capture import open_capture
from lfgraph.selfcal import BoardPin, DistancePin, ViewPin
from lfgraph.selfcal.pins import follow_marks

CORNER_SIGMA_PX = 0.1  # the pin board's corner noise (as the checkerboard peer's)
MIN_TILT_DEG = 30.0  # the pin board is held this tilted to the reference view (the manual's 30-45 deg)
MAX_TILT_DEG = 45.0
BOARD_DISTANCES = 41  # the pin board's distance: the nearest of this many steps over the peer's range every view sees
DISTANCE_M = 1.0  # the known distance: about 1 m ...
SIGMA_PER_M = 1e-3  # ... measured to 1 mm per metre (1 sigma)
MISMEASURED = 0.05  # the refusal case: a distance 5 % wrong
FLAT_WINDOW_PX = 9  # a marked point's depth varies by less than FLAT_DEPTH of itself over this window
FLAT_DEPTH = 0.01
MARK_CANDIDATES = 400
WALL_DEPTH = 1e-3  # a mark on the wall: its true depth within this share of the wall's
WALL_SPAN = 0.25  # the wall's marks lie at least this share of its depth apart (a user marks them far apart)
VIEW_BOARDS = 10  # boards of the pinned view's own earlier calibration
FOLLOWED_DEPTH = 0.01  # a mark whose followed pixels triangulate (true cameras) further off its true depth is dropped


def tilt_deg(ref_T_board: np.ndarray) -> float:  # noqa: N803
    """Angle between the board's normal and the reference view's optical axis."""
    return float(np.degrees(np.arccos(min(1.0, abs(ref_T_board[2, 2])))))


def _held_frame(truth: Calibration, cfg, tilt: float, axis: float, roll: float, rng: np.random.Generator):
    """A board tilted ``tilt`` (rad) about the in-plane direction ``axis`` (rad), rolled ``roll`` (rad), centred on the
    array's axis at the nearest of `BOARD_DISTANCES` steps over the peer's range from which every view sees it whole
    (else the one most views see): (its `CheckerboardTruth`, distance m)."""
    turn = cv2.Rodrigues(tilt * np.array([np.cos(axis), np.sin(axis), 0.0]))[0] @ \
        cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0]
    obj = cfg.board.object_points()
    axis_xy = truth.ref_T_view[:, :2, 3].mean(axis=0)  # the array's central axis, in the reference view's frame
    best = None
    for dist in np.linspace(*cfg.distance_m, BOARD_DISTANCES):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = turn, np.array([*axis_xy, dist]) - turn @ obj.mean(axis=0)
        board = make_checkerboard_truth(truth, cfg, rng, ref_T_board=pose[None])
        seen = int(board.board_visible[:, 0].sum())
        if best is None or seen > best[0]:
            best = (seen, dist, board)
        if seen == truth.num_views:
            break
    return best[2], float(best[1])


def board_pin(rig: str, truth: Calibration, seed: int, frames: int = 1) -> BoardPin:
    """One tilted board frame of the rig's checkerboard (seeded), held as the manual says (module docstring); with
    ``frames=2`` a second one tilted about the perpendicular in-plane axis (its own tilt and roll drawn the same way;
    the first frame is the one-frame pin's)."""
    cfg = dataclasses.replace(data.base_scene(rig).checkerboard, frames=1)
    rng = np.random.default_rng([seed, 43])
    tilt = np.radians(rng.uniform(MIN_TILT_DEG, MAX_TILT_DEG))
    axis = rng.uniform(0, 2 * np.pi)
    roll = np.radians(rng.uniform(-cfg.max_roll_deg, cfg.max_roll_deg))
    board, dist = _held_frame(truth, cfg, tilt, axis, roll, rng)
    corners, valid = make_corner_observations(board, CORNER_SIGMA_PX, np.random.default_rng([seed, 47]))
    name = f"1 board frame (tilt {tilt_deg(board.ref_T_board[0]):.0f} deg, {dist:.2f} m, seed {seed})"
    if frames == 2:
        rng = np.random.default_rng([seed, 61])
        tilt2 = np.radians(rng.uniform(MIN_TILT_DEG, MAX_TILT_DEG))
        roll2 = np.radians(rng.uniform(-cfg.max_roll_deg, cfg.max_roll_deg))
        board2, dist2 = _held_frame(truth, cfg, tilt2, axis + np.pi / 2, roll2, rng)
        corners2, valid2 = make_corner_observations(board2, CORNER_SIGMA_PX, np.random.default_rng([seed, 67]))
        corners, valid = np.concatenate([corners, corners2], axis=1), np.concatenate([valid, valid2], axis=1)
        name = (f"2 board frames (tilts {tilt_deg(board.ref_T_board[0]):.0f} and "
                f"{tilt_deg(board2.ref_T_board[0]):.0f} deg about perpendicular axes, {dist:.2f} and {dist2:.2f} m, "
                f"seed {seed})")
    elif frames != 1:
        raise ValueError(f"frames must be 1 or 2, got {frames}")
    return BoardPin(corners, valid, cfg.board.object_points(), name=name)


def _marks(image: np.ndarray, depth: np.ndarray, truth: Calibration,
           wall_m: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Shi–Tomasi corners of the reference image on flat surfaces (on the wall ``wall_m`` deep when given) and their
    true 3-D points (reference frame)."""
    mask = None if wall_m is None else (np.abs(depth / wall_m - 1.0) < WALL_DEPTH).astype(np.uint8)
    feats = cv2.goodFeaturesToTrack(image, MARK_CANDIDATES, 0.01, 8, mask=mask)
    feats = np.zeros((0, 2), np.float32) if feats is None else feats.reshape(-1, 2)
    r = FLAT_WINDOW_PX // 2
    h, w = depth.shape
    ok = []
    for u, v in np.rint(feats).astype(int):
        win = depth[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1]
        ok.append(u >= r and v >= r and u < w - r and v < h - r and np.all(np.isfinite(win))
                  and np.ptp(win) < FLAT_DEPTH * np.nanmedian(win))
    feats = feats[np.array(ok, dtype=bool)]
    inv = cv2.remap((1.0 / depth).astype(np.float32), feats[:, 0].astype(np.float32),
                    feats[:, 1].astype(np.float32), cv2.INTER_LINEAR).ravel()  # inverse depth is linear on a plane
    ref = truth.grid.reference
    xy = truth.intrinsics[ref].undistort(feats)
    return feats, np.column_stack([xy, np.ones(len(xy))]) / inv[:, None]


def _frame_marks(rig: str, truth: Calibration, rig_seed: int, frame: int, wall_m: float | None = None):
    """A frame's images, its marks every view sees (on the wall ``wall_m`` deep when given) and their true points."""
    root = data.dataset_dir(rig, rig_seed)
    scene = make_scene(data.frame_scene_config(rig, frame), np.random.default_rng([rig_seed, 23, frame]))
    ref = truth.grid.reference
    depth = render_scene_depth(scene, truth.intrinsics[ref], truth.image_size_px, truth.view_T_ref(ref))
    images = open_capture(root, truth.grid).load_frame(frame)
    feats, points = _marks(images[ref], depth, truth, wall_m)
    pixels, valid = follow_marks(images, truth.grid, ref, feats)
    seen = valid.all(axis=0)  # marks every view sees (not occluded) ...
    # ... and followed onto their own surface: through the true cameras they triangulate near their true depth (a
    # mark beside a depth edge is followed on the nearer surface; a user marks points that are clearly one thing)
    tri = triangulate_dlt(truth, pixels, valid)
    seen &= np.abs(tri[:, 2] / points[:, 2] - 1.0) < FOLLOWED_DEPTH
    return images, feats[seen], points[seen]


def plane_pin(rig: str, truth: Calibration, frames: int, rig_seed: int, seed: int, error: float = 0.0) -> DistancePin:
    """Two marks on the background wall of a near frame, their distance (``error``: relative mistake added) and the
    wall's depth measured, followed into every view."""
    rng = np.random.default_rng([seed, 59])
    near = np.arange(0, frames, data.DEPTH_BANDS)  # frames of the nearest band: the wall nearest the array
    first = int(rng.integers(len(near)))
    best = None  # the seeded near frame, else the next whose wall shows marks far apart, else the widest
    for f in np.roll(near, -first):
        wall_m = data.frame_scene_config(rig, int(f)).background_depth_m
        images, feats, points = _frame_marks(rig, truth, rig_seed, int(f), wall_m)
        span = float(np.ptp(points[:, :2], axis=0).max()) / wall_m if len(feats) >= 2 else 0.0
        if best is None or span > best[0]:
            best = (span, int(f), wall_m, images, feats, points)
        if span >= WALL_SPAN:
            break
    _, frame, wall_m, images, feats, points = best
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    a, b = np.unravel_index(int(np.argmax(d)), d.shape)
    true_m = float(d[a, b])
    noise = rng.standard_normal(2) * SIGMA_PER_M
    measured = true_m * (1.0 + error) + (true_m * noise[0] if error == 0.0 else 0.0)
    pin = DistancePin(measured, SIGMA_PER_M * true_m, view=truth.grid.reference, frame=frame,
                      marked_px=feats[[a, b]], depth_m=wall_m * (1.0 + noise[1]), depth_sigma_m=SIGMA_PER_M * wall_m,
                      name=f"{true_m:.3f} m on a wall {wall_m:.2f} m deep{f' {100 * error:+.0f} %' if error else ''} "
                           f"(seed {seed})")
    return pin.followed(images, truth.grid)


def distance_pin(rig: str, truth: Calibration, frames: int, rig_seed: int, seed: int,
                 error: float = 0.0) -> DistancePin:
    """Two marked points about `DISTANCE_M` apart in one frame, their distance measured (``error``: relative
    mistake added), followed into every view."""
    rng = np.random.default_rng([seed, 53])
    frame = int(rng.integers(frames))
    ref = truth.grid.reference
    images, feats, points = _frame_marks(rig, truth, rig_seed, frame)
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    dz = np.abs(points[:, None, 2] - points[None, :, 2])
    score = np.where(np.abs(d / DISTANCE_M - 1.0) < 0.2, dz / np.maximum(d, 1e-9), -np.abs(d - DISTANCE_M))
    a, b = np.unravel_index(int(np.argmax(np.triu(score, 1) + np.tril(np.full_like(score, -np.inf)))), d.shape)
    true_m = float(d[a, b])
    sigma = SIGMA_PER_M * true_m
    measured = true_m * (1.0 + error) + (sigma * float(rng.standard_normal()) if error == 0.0 else 0.0)
    pin = DistancePin(measured, sigma, view=ref, frame=frame, marked_px=feats[[a, b]],
                      name=f"distance {true_m:.3f} m{f' {100 * error:+.0f} %' if error else ''} (seed {seed})")
    return pin.followed(images, truth.grid)


def view_pin(rig: str, truth: Calibration, seed: int) -> ViewPin:
    """One view (seeded) pinned to its own earlier calibration: OpenCV's ``calibrateCamera`` on `VIEW_BOARDS` board
    frames that view sees whole (module docstring), with OpenCV's standard deviations as the pin's sigmas."""
    rng = np.random.default_rng([seed, 71])
    view = int(rng.integers(truth.num_views))
    cfg = dataclasses.replace(data.base_scene(rig).checkerboard, frames=4 * VIEW_BOARDS)
    board = make_checkerboard_truth(truth, cfg, rng)
    corners, valid = make_corner_observations(board, CORNER_SIGMA_PX, np.random.default_rng([seed, 73]))
    frames = np.flatnonzero(valid[view].all(axis=1))[:VIEW_BOARDS]
    if len(frames) < VIEW_BOARDS:
        raise ValueError(f"view {view} sees only {len(frames)} whole boards of {cfg.frames}")
    obj = cfg.board.object_points().astype(np.float32)
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    _, k, dist, *_, std, _, _ = cv2.calibrateCameraExtended(
        [obj] * len(frames), [corners[view, f].astype(np.float32) for f in frames], truth.image_size_px, None, None,
        flags=flags)
    std = std.ravel()  # fx, fy, cx, cy, k1, k2, p1, p2, k3, ...
    lens = truth.intrinsics[view].lens
    est = Intrinsics(fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], k1=dist[0, 0], k2=dist[0, 1], lens=lens)
    return ViewPin(view, est, tuple(std[:6]), name=f"view {truth.grid.name(view)} from {len(frames)} boards of its "
                                                   f"own (seed {seed})")
