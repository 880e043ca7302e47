"""Seeded synthetic camera arrays with ground truth, and the paper's "camera after shakes" perturbation."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.camera import Intrinsics
from lfgraph.core.geometry import invert_T, make_T, rotation_from_rotvec
from lfgraph.core.grid import ViewGrid
from lfgraph.lenses import DEFAULT_LENS


@dataclass(frozen=True)
class RigConfig:
    """Design values of a camera array and how far each real view strays from them.

    Attributes:
        rows, cols, reference: the grid (row-major views; reference view index).
        pitch_m: distance between adjacent views (metres), the same along rows and columns.
        image_size_px: (width, height) of every view.
        focal_px: design focal length (pixels); fx = fy before jitter.
        k1, k2: design radial distortion shared by all lenses (the lens model's own k1, k2).
        lens: the lens model of every view (``radtan``, ``fisheye`` or ``unified``, see `lfgraph.core.camera`).
        xi: the unified model's design xi (0 for the others).
        focal_jitter_px: std of each view's fx and fy about ``focal_px``.
        principal_jitter_px: std of each view's cx, cy about the image centre.
        distortion_jitter: std of each view's k1 and k2 about the design values.
        rot_jitter_deg: std of each view's misplacement rotation, per axis (degrees).
        trans_jitter_mm: std of each view's misplacement from its grid position, per axis (millimetres).
    """

    rows: int = 4
    cols: int = 4
    reference: int = 0
    pitch_m: float = 0.006
    image_size_px: tuple[int, int] = (960, 960)
    focal_px: float = 850.0
    k1: float = -0.08
    k2: float = 0.02
    focal_jitter_px: float = 4.0
    principal_jitter_px: float = 6.0
    distortion_jitter: float = 0.01
    rot_jitter_deg: float = 0.3
    trans_jitter_mm: float = 0.15
    lens: str = DEFAULT_LENS
    xi: float = 0.0

    def __post_init__(self) -> None:
        ViewGrid(self.rows, self.cols, self.reference)  # validates
        Intrinsics(1.0, 1.0, 0.0, 0.0, xi=self.xi, lens=self.lens)  # validates the lens and xi
        if self.pitch_m <= 0 or self.focal_px <= 0 or min(self.image_size_px) <= 0:
            raise ValueError("pitch, focal length and image size must be positive")

    @property
    def grid(self) -> ViewGrid:
        """The `ViewGrid` of ``rows``, ``cols`` and ``reference``."""
        return ViewGrid(self.rows, self.cols, self.reference)


def ideal_ref_T_view(grid: ViewGrid, pitch_m: float) -> np.ndarray:  # noqa: N802
    """(V, 4, 4) poses of a perfect grid: parallel views, view (r, c) at ((c - c_ref), (r - r_ref), 0) * pitch."""
    poses = np.tile(np.eye(4), (grid.num_views, 1, 1))
    for v in range(grid.num_views):
        dr, dc = grid.offset(v)
        poses[v, :3, 3] = [dc * pitch_m, dr * pitch_m, 0.0]
    return poses


def make_rig(config: RigConfig, rng: np.random.Generator) -> Calibration:
    """Draw a camera array: design values plus per-view jitter (seeded, pure).

    Each view's world pose is its ideal grid pose perturbed by a small rotation and translation; the result is
    expressed relative to the reference view, which is the rig frame (so its own misplacement moves the others).

    Returns:
        The ground-truth `Calibration`.
    """
    grid = config.grid
    w, h = config.image_size_px
    n = grid.num_views
    intrinsics = []
    for _ in range(n):
        fx, fy = config.focal_px + config.focal_jitter_px * rng.standard_normal(2)
        cx = (w - 1) / 2 + config.principal_jitter_px * rng.standard_normal()
        cy = (h - 1) / 2 + config.principal_jitter_px * rng.standard_normal()
        k1, k2 = np.array([config.k1, config.k2]) + config.distortion_jitter * rng.standard_normal(2) * [1.0, 0.5]
        intrinsics.append(Intrinsics(fx, fy, cx, cy, k1, k2, xi=config.xi, lens=config.lens))
    world_T_view = ideal_ref_T_view(grid, config.pitch_m)  # noqa: N806
    for v in range(n):
        rot = rotation_from_rotvec(np.radians(config.rot_jitter_deg) * rng.standard_normal(3))
        world_T_view[v] = world_T_view[v] @ make_T(rot, 1e-3 * config.trans_jitter_mm * rng.standard_normal(3))
    ref_T_world = invert_T(world_T_view[grid.reference])  # noqa: N806
    ref_T_view = np.einsum("ij,vjk->vik", ref_T_world, world_T_view)  # noqa: N806
    ref_T_view[grid.reference] = np.eye(4)
    return Calibration(grid, (w, h), tuple(intrinsics), ref_T_view)


@dataclass(frozen=True)
class ShakeConfig:
    """The paper's "camera after shakes" (Sec. 5.2).

    Attributes:
        rot_deg: each non-reference view turns by an angle drawn uniformly from [-rot_deg, rot_deg].
        trans_mm: each non-reference view moves by a vector whose x, y, z are drawn uniformly from
            [-trans_mm, trans_mm] (millimetres).
        axis: ``"optical"`` turns about each view's optical axis (the paper's choice), ``"any"`` about a random axis.
        intrinsic_drift_px: std of a drift added to fx, fy, cx, cy of every view (pixels); 0 keeps intrinsics.
    """

    rot_deg: float = 0.0
    trans_mm: float = 0.0
    axis: str = "optical"
    intrinsic_drift_px: float = 0.0

    def __post_init__(self) -> None:
        if self.axis not in ("optical", "any"):
            raise ValueError(f"shake axis must be 'optical' or 'any', got {self.axis!r}")
        if self.rot_deg < 0 or self.trans_mm < 0 or self.intrinsic_drift_px < 0:
            raise ValueError("shake magnitudes must be >= 0")


def shake_rig(calibration: Calibration, config: ShakeConfig, rng: np.random.Generator) -> Calibration:
    """A perturbed copy of a rig; the reference view stays the rig frame. Seeded and pure."""
    poses = np.array(calibration.ref_T_view)
    intrinsics = list(calibration.intrinsics)
    for v in range(calibration.num_views):
        if config.intrinsic_drift_px > 0:
            d = config.intrinsic_drift_px * rng.standard_normal(4)
            i = intrinsics[v]
            intrinsics[v] = dataclasses.replace(i, fx=i.fx + d[0], fy=i.fy + d[1], cx=i.cx + d[2], cy=i.cy + d[3])
        if v == calibration.grid.reference:
            continue
        if config.axis == "optical":
            axis = np.array([0.0, 0.0, 1.0])
        else:
            axis = rng.standard_normal(3)
            axis /= np.linalg.norm(axis)
        angle = np.radians(config.rot_deg) * rng.uniform(-1.0, 1.0)
        shift_m = 1e-3 * config.trans_mm * rng.uniform(-1.0, 1.0, 3)
        # Turn about the view's own optical centre and axis, then move it (in the reference frame).
        poses[v] = make_T(np.eye(3), shift_m) @ poses[v] @ make_T(rotation_from_rotvec(angle * axis), np.zeros(3))
    return calibration.replace(intrinsics=tuple(intrinsics), ref_T_view=poses, rectification=None, metrics=None)


def resize_views(calibration: Calibration, size_scale: Sequence[float],
                 focal_scale: Sequence[float] | None = None) -> Calibration:
    """A rig of mixed image sizes: view v imaged at ``size_scale[v]`` times the rig's image size (its principal point
    moved with the pixel grid, ``s (c + 0.5) - 0.5``) and its focal length ``focal_scale[v]`` times (default: the size
    scale, the same field of view; another factor widens or narrows it). A scale of 1 leaves a view as it is."""
    sizes_scale = np.asarray(size_scale, dtype=np.float64)
    focal = sizes_scale if focal_scale is None else np.asarray(focal_scale, dtype=np.float64)
    if sizes_scale.shape != (calibration.num_views,) or focal.shape != (calibration.num_views,):
        raise ValueError(f"need one size and focal scale per view ({calibration.num_views}), got "
                         f"{sizes_scale.shape} and {focal.shape}")
    w, h = calibration.image_size_px
    intr = tuple(dataclasses.replace(i, fx=f * i.fx, fy=f * i.fy, cx=s * (i.cx + 0.5) - 0.5, cy=s * (i.cy + 0.5) - 0.5)
                 for i, s, f in zip(calibration.intrinsics, sizes_scale, focal, strict=True))
    sizes = tuple((round(s * w), round(s * h)) for s in sizes_scale)
    return calibration.replace(intrinsics=intr, view_image_sizes_px=sizes)
