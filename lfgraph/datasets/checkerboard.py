"""Synthetic checkerboard captures of a camera array: board poses, true corners, noisy corners, and the writer of
rendered captures (the renderer itself: `lfgraph.datasets.board_render`)."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics, in_image, transform_points
from lfgraph.core.files import atomic_path
from lfgraph.core.geometry import make_T, rotation_from_rotvec
from lfgraph.core.parallel import run_tasks
from lfgraph.datasets.board_render import CheckerboardConfig, ViewRays, render_checkerboard_view
from lfgraph.detect.board import BoardSpec

OUTLINE_SAMPLES_PER_EDGE = 24  # points per printed-board edge checked for visibility (edges bend under distortion)
MAX_POSE_TRIES = 2000
# Noisy renders compress best unfiltered with Huffman coding alone (sensor noise leaves few repeated strings):
# ~20 % less encoding time than OpenCV's default PNG parameters (SUB filter, RLE) and ~6 % smaller files on
# paper-4x4; noise-free renders (long runs of one grey) keep the default.
NOISY_PNG_PARAMS = (cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE,
                    cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY)


@dataclass(frozen=True)
class CheckerboardTruth:
    """Ground truth of a checkerboard capture.

    Attributes:
        board: the checkerboard.
        ref_T_board: (F, 4, 4) board pose in the reference view's frame per frame.
        corners_px: (V, F, C, 2) true corner projections (NaN behind a camera).
        corner_valid: (V, F, C) corner in front of the view and inside its image.
        board_visible: (V, F) the whole printed board is inside the view (where chessboard detection can work).
    """

    board: BoardSpec
    ref_T_board: np.ndarray
    corners_px: np.ndarray
    corner_valid: np.ndarray
    board_visible: np.ndarray

    def __post_init__(self) -> None:
        f = self.ref_T_board.shape[0]
        if self.ref_T_board.shape != (f, 4, 4):
            raise ValueError(f"ref_T_board must be (F, 4, 4), got {self.ref_T_board.shape}")
        v = self.corners_px.shape[0]
        c = self.board.num_corners
        if self.corners_px.shape != (v, f, c, 2):
            raise ValueError(f"corners_px must be ({v}, {f}, {c}, 2), got {self.corners_px.shape}")
        if self.corner_valid.shape != (v, f, c) or self.board_visible.shape != (v, f):
            raise ValueError(f"corner_valid must be ({v}, {f}, {c}) and board_visible ({v}, {f}), got "
                             f"{self.corner_valid.shape} and {self.board_visible.shape}")

    def save_npz(self, path: str | os.PathLike) -> None:
        """Write to ``.npz`` atomically."""
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, board=np.array([self.board.cols, self.board.rows, self.board.square_m, self.board.margin_squares]),
                ref_T_board=self.ref_T_board, corners_px=self.corners_px, corner_valid=self.corner_valid,
                board_visible=self.board_visible)

    @classmethod
    def load_npz(cls, path: str | os.PathLike) -> CheckerboardTruth:
        """Read what `save_npz` wrote; raises ValueError naming the file on a missing key or bad shape."""
        try:
            with np.load(path) as data:
                missing = {"board", "ref_T_board", "corners_px", "corner_valid", "board_visible"} - set(data.files)
                if missing:
                    raise ValueError(f"{path}: missing arrays {sorted(missing)}")
                b = data["board"]
                if b.shape != (4,):
                    raise ValueError(f"{path}: board must hold 4 numbers (cols, rows, square_m, margin), got {b.shape}")
                board = BoardSpec(int(b[0]), int(b[1]), float(b[2]), float(b[3]))
                return cls(board, data["ref_T_board"], data["corners_px"], data["corner_valid"].astype(bool),
                           data["board_visible"].astype(bool))
        except (OSError, EOFError) as exc:
            raise ValueError(f"{path}: cannot read ground-truth corners ({exc})") from None
        except ValueError as exc:
            if str(exc).startswith(str(path)):
                raise
            raise ValueError(f"{path}: {exc}") from None


# ---------------------------------------------------------------------------------------------- geometry
def _outline_points(board: BoardSpec) -> np.ndarray:
    """(4 * OUTLINE_SAMPLES_PER_EDGE, 3) points along the printed board's outline, board frame."""
    corners = board.outline()
    t = np.linspace(0.0, 1.0, OUTLINE_SAMPLES_PER_EDGE, endpoint=False)[:, None]
    return np.concatenate([corners[i] + t * (corners[(i + 1) % 4] - corners[i]) for i in range(4)])


def _board_faces_view(view_T_board: np.ndarray) -> bool:  # noqa: N803
    # The board's +z points into the board; the camera sees the printed side when that axis points away from it.
    return float(view_T_board[:3, 2] @ view_T_board[:3, 3]) > 0


def board_visible_in_view(intrinsics: Intrinsics, image_size_px: tuple[int, int], view_T_board: np.ndarray,  # noqa: N803
                          board: BoardSpec, margin_px: float) -> bool:
    """True when the whole printed board (outline sampled densely) lies inside the image and faces the view."""
    if not _board_faces_view(view_T_board):
        return False
    px = intrinsics.project(transform_points(view_T_board, _outline_points(board)))
    return bool(np.all(in_image(px, image_size_px, margin_px)))


def make_board_poses(calib: Calibration, config: CheckerboardConfig, rng: np.random.Generator) -> np.ndarray:
    """Board poses spread over the reference view's field of view.

    Frame f aims the board centre at a random point of image cell ``f mod cells^2`` (cells of the reference image),
    at a random distance in ``config.distance_m``, tilted by up to ``max_tilt_deg`` about a random in-plane axis
    and rolled by up to ``max_roll_deg``; poses are redrawn until the whole board is inside the reference view.

    Returns:
        (F, 4, 4) ``ref_T_board``.

    Raises:
        ValueError: no pose keeps the board inside the reference view (board too large for the distance range).
    """
    ref = calib.grid.reference
    intr = calib.intrinsics[ref]
    w, h = calib.image_size_px
    board = config.board
    centre_b = np.array([(board.cols - 1) * board.square_m / 2, (board.rows - 1) * board.square_m / 2, 0.0])
    n = config.coverage_cells
    order = rng.permutation(n * n)
    poses = np.zeros((config.frames, 4, 4))
    for f in range(config.frames):
        cell = order[f % (n * n)]
        cy_cell, cx_cell = divmod(int(cell), n)
        for attempt in range(MAX_POSE_TRIES):
            # After many failures (a corner cell the board cannot reach at this distance) widen towards the centre.
            shrink = min(1.0, attempt / 200.0)
            u = (cx_cell + rng.uniform(0.1, 0.9)) / n * w
            v = (cy_cell + rng.uniform(0.1, 0.9)) / n * h
            u, v = u + shrink * ((w - 1) / 2 - u), v + shrink * ((h - 1) / 2 - v)
            ray = intr.undistort(np.array([[u, v]]))[0]
            if not np.all(np.isfinite(ray)):
                continue
            z = rng.uniform(*config.distance_m)
            roll = np.radians(rng.uniform(-config.max_roll_deg, config.max_roll_deg))
            axis_angle = rng.uniform(0, 2 * np.pi)
            tilt = np.radians(config.max_tilt_deg) * np.sqrt(rng.uniform(0, 1))
            R = (rotation_from_rotvec(tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0]))  # noqa: N806
                 @ rotation_from_rotvec([0.0, 0.0, roll]))
            centre = z * np.array([ray[0], ray[1], 1.0])
            ref_T_board = make_T(R, centre - R @ centre_b)  # noqa: N806
            if board_visible_in_view(intr, (w, h), ref_T_board, board, config.margin_px):
                poses[f] = ref_T_board
                break
        else:
            raise ValueError(f"could not place the {board} board inside the reference view at "
                             f"{config.distance_m} m; move it further away or use a smaller board")
    return poses


def make_checkerboard_truth(calib: Calibration, config: CheckerboardConfig, rng: np.random.Generator,
                            ref_T_board: np.ndarray | None = None) -> CheckerboardTruth:  # noqa: N803
    """Board poses (drawn unless given) and the true corner projections in every view. Seeded and pure."""
    poses = make_board_poses(calib, config, rng) if ref_T_board is None else np.asarray(ref_T_board, dtype=float)
    board = config.board
    obj = board.object_points()
    n_views, n_frames = calib.num_views, poses.shape[0]
    corners = np.full((n_views, n_frames, board.num_corners, 2), np.nan)
    visible = np.zeros((n_views, n_frames), dtype=bool)
    for v in range(n_views):
        view_T_ref = calib.view_T_ref(v)  # noqa: N806
        for f in range(n_frames):
            view_T_board = view_T_ref @ poses[f]  # noqa: N806
            if _board_faces_view(view_T_board):
                corners[v, f] = calib.intrinsics[v].project(transform_points(view_T_board, obj))
                visible[v, f] = board_visible_in_view(calib.intrinsics[v], calib.image_size(v), view_T_board, board,
                                                      config.margin_px)
    valid = np.stack([in_image(corners[v], calib.image_size(v)) for v in range(n_views)])
    return CheckerboardTruth(board, poses, corners, valid, visible)


def make_corner_observations(truth: CheckerboardTruth, sigma_px: float, rng: np.random.Generator,
                             full_boards_only: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The corner-only variant: true projections plus Gaussian noise (for fast tests and Monte-Carlo studies).

    Args:
        truth: ground truth.
        sigma_px: noise std per coordinate, pixels.
        rng: random generator.
        full_boards_only: keep only view-frames where the whole board is visible (as chessboard detection does).

    Returns:
        corners_px (V, F, C, 2) with NaN where invalid, and valid (V, F, C).
    """
    valid = truth.corner_valid & (truth.board_visible[..., None] if full_boards_only else True)
    noisy = truth.corners_px + sigma_px * rng.standard_normal(truth.corners_px.shape)
    noisy[~valid] = np.nan
    return noisy, valid


def iter_view_images(calib: Calibration, truth: CheckerboardTruth, config: CheckerboardConfig, seed: int,
                     view: int, frames: range | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(frame, image)`` for one view, reusing its rays. Noise is seeded by (seed, frame, view)."""
    intr = calib.intrinsics[view]
    rays = ViewRays.compute(intr, calib.image_size(view))
    view_T_ref = calib.view_T_ref(view)  # noqa: N806
    for f in frames if frames is not None else range(truth.ref_T_board.shape[0]):
        rng = np.random.default_rng([seed, f, view])
        yield f, render_checkerboard_view(intr, calib.image_size(view), view_T_ref @ truth.ref_T_board[f], truth.board,
                                          config, rng, rays)


def png_params(config: CheckerboardConfig) -> list[int]:
    """``cv2.imwrite`` parameters for the PNGs of renders made with ``config``."""
    return list(NOISY_PNG_PARAMS) if config.noise_sigma > 0 else []


def frame_name(frame: int) -> str:
    """The folder name of frame ``frame`` in a written capture (``000``, ``001``, ...)."""
    return f"{frame:03d}"


def _render_view_task(args: tuple) -> int:
    calib_json, truth_path, config, seed, view, out_dir = args
    import json

    calib = Calibration.from_dict(json.loads(calib_json))
    truth = CheckerboardTruth.load_npz(truth_path)
    name = calib.grid.name(view)
    for f, img in iter_view_images(calib, truth, config, seed, view):
        path = Path(out_dir) / frame_name(f) / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), img, png_params(config)):
                raise OSError(f"could not write {path}")
    return view


def write_checkerboard_dataset(out_dir: str | os.PathLike, calib: Calibration, truth: CheckerboardTruth,
                               config: CheckerboardConfig, seed: int, layout: str = "folders", jobs: int | None = None,
                               progress: bool = True) -> None:
    """Render every view of every frame to ``out_dir`` with ``truth.json`` and ``truth_corners.npz``.

    Layouts: ``folders`` writes ``OUT/<frame>/rRR_cCC.png``; ``mosaic`` writes ``OUT/<frame>.png`` with the views
    tiled row-major. Images are rendered view by view in a process pool (each worker keeps one view's rays), every
    file is written atomically, and no more than one image per worker is held in memory (mosaics are assembled
    from per-view files afterwards). Output is identical for any ``jobs``.
    """
    if layout not in ("folders", "mosaic"):
        raise ValueError(f"layout must be 'folders' or 'mosaic', got {layout!r}")
    if layout == "mosaic" and calib.view_image_sizes_px is not None:
        raise ValueError("a rig of mixed image sizes cannot be tiled into a mosaic; use the folders layout")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    truth_path = out / "truth_corners.npz"
    truth.save_npz(truth_path)
    render_dir = out if layout == "folders" else Path(tempfile.mkdtemp(prefix=".render-", dir=out))
    tasks = [(calib.to_json(), str(truth_path), config, seed, v, str(render_dir)) for v in range(calib.num_views)]
    try:
        run_tasks(_render_view_task, tasks, jobs, "rendering views", "view", progress)
        if layout == "mosaic":
            rows, cols = calib.grid.rows, calib.grid.cols
            w, h = calib.image_size_px
            for f in range(truth.ref_T_board.shape[0]):
                mosaic = np.zeros((rows * h, cols * w), dtype=np.uint8)
                for v in range(calib.num_views):
                    r, c = calib.grid.position(v)
                    mosaic[r * h : (r + 1) * h, c * w : (c + 1) * w] = cv2.imread(
                        str(render_dir / frame_name(f) / f"{calib.grid.name(v)}.png"), cv2.IMREAD_GRAYSCALE)
                with atomic_path(out / f"{frame_name(f)}.png") as tmp:
                    cv2.imwrite(str(tmp), mosaic, png_params(config))
    finally:
        if render_dir != out:
            shutil.rmtree(render_dir, ignore_errors=True)
    calib.save(out / "truth.json")
