"""How well rectified views line up: at infinity, as seen, and with the rig's own off-grid parallax removed.

Physics first: a real array's views sit off the ideal grid by fractions of a millimetre, and no rectification can
remove the parallax this causes at finite depth (f·Δ/Z). So three figures:

- *at infinity*: directions projected through each view's camera (the true one when known) and mapped through the
  rectification; rows of horizontal neighbours and columns of vertical neighbours must agree, and the disparity
  must be zero. This is what rectification guarantees, and what far scene content shows.
- *as seen*: matched points (corners, features) in rectified coordinates: RMS row misalignment |Δy| of horizontal
  neighbours, column misalignment |Δx| of vertical neighbours, and the disparity-proportionality error (each point
  fitted as ``q_i = a - s g_i`` with ``g_i`` the ideal grid offset of view i in pixels per unit inverse depth).
- *parallax-compensated*: the same after subtracting, per point, the off-grid parallax that the calibration itself
  predicts for the triangulated point — what is left is calibration error, not rig geometry.

All figures are RMS over pairs (or views) and points, in pixels of the rectified images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.grid import ViewGrid
from lfgraph.engine.triangulate import triangulate_dlt
from lfgraph.judge.evaluation import INFINITY_SAMPLES, transfer_error_at_infinity  # noqa: F401  (re-exported: its home before)
from lfgraph.rectification.rectify import Rectification, rectify_points


@dataclass(frozen=True)
class Alignment:
    """Row / column misalignment and disparity-proportionality error (px RMS), and how many values each holds."""

    row_px: float
    col_px: float
    proportionality_px: float
    n_row: int
    n_col: int
    n_points: int

    def as_dict(self) -> dict[str, float | int]:
        """The figures and counts as a JSON-ready dict keyed by the field names."""
        return {"row_px": self.row_px, "col_px": self.col_px, "proportionality_px": self.proportionality_px,
                "n_row": self.n_row, "n_col": self.n_col, "n_points": self.n_points}


def _rms(values: list[np.ndarray]) -> tuple[float, int]:
    v = np.concatenate([np.ravel(x) for x in values]) if values else np.zeros(0)
    v = v[np.isfinite(v)]
    return (float(np.sqrt(np.mean(v**2))) if v.size else float("nan")), int(v.size)


def grid_offsets_px(grid: ViewGrid, rect: Rectification) -> np.ndarray:
    """(V, 2) g_i: ideal rectified displacement of view i per unit inverse depth (pixels * metres)."""
    fx, fy = rect.K_r[0, 0], rect.K_r[1, 1]
    u = rect.rect_R_ref @ rect.grid_u_m
    v = rect.rect_R_ref @ rect.grid_v_m
    off = np.array([grid.offset(i) for i in range(grid.num_views)], dtype=np.float64)  # (dr, dc)
    step = off[:, 1:2] * u[None, :2] + off[:, 0:1] * v[None, :2]
    return step * np.array([fx, fy])


def point_alignment(grid: ViewGrid, rect: Rectification, points_px: np.ndarray, valid: np.ndarray) -> Alignment:
    """Alignment of matched points in rectified coordinates.

    Args:
        grid: the view grid.
        rect: the rectification (for the ideal grid offsets).
        points_px: (V, N, 2) rectified positions of N matched points.
        valid: (V, N) which exist.
    """
    q = np.where(valid[..., None], points_px, np.nan)
    rows = [np.abs(q[a, :, 1] - q[b, :, 1]) for a, b in grid.horizontal_pairs()]
    cols = [np.abs(q[a, :, 0] - q[b, :, 0]) for a, b in grid.vertical_pairs()]
    row_px, n_row = _rms(rows)
    col_px, n_col = _rms(cols)
    # proportionality: per point, least squares of q_i = a - s g_i over its views (unknowns a (2), s)
    g = grid_offsets_px(grid, rect)  # (V, 2)
    m = valid & np.all(np.isfinite(q), axis=-1)
    n_views = m.sum(axis=0)
    use = n_views >= 3  # two views fit exactly; three are needed for a residual
    w = m[:, use].astype(np.float64)  # (V, P)
    qq = np.nan_to_num(q[:, use])
    # normal equations for (ax, ay, s): residual r_i = q_i - a + s g_i
    sw = w.sum(0)
    sg = np.einsum("vp,vc->pc", w, g)  # (P, 2)
    sgg = np.einsum("vp,v->p", w, np.sum(g**2, axis=1))
    sq = np.einsum("vp,vpc->pc", w, qq)  # (P, 2)
    sgq = np.einsum("vp,vc,vpc->p", w, g, qq)
    A = np.zeros((use.sum(), 3, 3))  # noqa: N806
    A[:, 0, 0] = A[:, 1, 1] = sw
    A[:, 0, 2] = A[:, 2, 0] = -sg[:, 0]
    A[:, 1, 2] = A[:, 2, 1] = -sg[:, 1]
    A[:, 2, 2] = sgg
    b = np.stack([sq[:, 0], sq[:, 1], -sgq], axis=1)
    sol = np.linalg.solve(A + 1e-12 * np.eye(3), b[..., None])[..., 0] if use.any() else np.zeros((0, 3))
    fit = sol[None, :, :2] - sol[None, :, 2:3] * g[:, None, :]
    resid = np.where(m[:, use, None], qq - fit, np.nan)
    # unbiased per-coordinate RMS: 2 * views values, 3 unknowns
    dof = 2 * m[:, use].sum() - 3 * use.sum()
    prop = float(np.sqrt(np.nansum(resid**2) / dof)) if dof > 0 else float("nan")
    return Alignment(row_px, col_px, prop, n_row, n_col, int(use.sum()))


def infinity_alignment(calib: Calibration, rect: Rectification, seen_by: Calibration | None = None,
                       samples: int = INFINITY_SAMPLES) -> Alignment:
    """Misalignment at infinity: directions seen by ``seen_by``'s cameras (default ``calib``), rectified with
    ``rect`` built from ``calib``.

    With ``seen_by`` the ground truth this measures the calibration's error as far scene content shows it.
    """
    seen_by = seen_by or calib
    if (seen_by.grid.rows, seen_by.grid.cols) != (calib.grid.rows, calib.grid.cols):
        raise ValueError(f"the cameras seeing the directions form a {seen_by.grid} grid, the calibration {calib.grid}")
    w, h = rect.image_size_px
    inset = 0.05
    xs = np.linspace(inset * (w - 1), (1 - inset) * (w - 1), samples)
    ys = np.linspace(inset * (h - 1), (1 - inset) * (h - 1), samples)
    gx, gy = np.meshgrid(xs, ys)
    rect_px = np.column_stack([gx.ravel(), gy.ravel()])
    K = rect.K_r  # noqa: N806
    rays_rect = np.column_stack([(rect_px[:, 0] - K[0, 2]) / K[0, 0], (rect_px[:, 1] - K[1, 2]) / K[1, 1],
                                 np.ones(len(rect_px))])
    rays_ref = rays_rect @ rect.rect_R_ref  # rect_R_ref.T @ ray
    # the reference frames of the two calibrations coincide up to the reference view's pose in seen_by
    ref_T_ref = np.linalg.inv(seen_by.ref_T_view[calib.grid.reference])
    n_views = calib.num_views
    q = np.full((n_views, len(rect_px), 2), np.nan)
    sw, sh = seen_by.image_size_px
    for i in range(n_views):
        view_R = (ref_T_ref @ seen_by.ref_T_view[i])[:3, :3]  # noqa: N806  seen_by view i in calib's ref frame
        px = seen_by.intrinsics[i].project(rays_ref @ view_R)  # view_R.T @ ray
        inside = (px[:, 0] >= 0) & (px[:, 0] <= sw - 1) & (px[:, 1] >= 0) & (px[:, 1] <= sh - 1)
        px[~inside] = np.nan
        q[i] = rectify_points(calib, rect, i, px)
    valid = np.all(np.isfinite(q), axis=-1)
    grid = calib.grid
    rows = [q[a, :, 1] - q[b, :, 1] for a, b in grid.horizontal_pairs()]
    cols = [q[a, :, 0] - q[b, :, 0] for a, b in grid.vertical_pairs()]
    disp = [q[a, :, 0] - q[b, :, 0] for a, b in grid.horizontal_pairs()] + \
           [q[a, :, 1] - q[b, :, 1] for a, b in grid.vertical_pairs()]
    row_px, n_row = _rms(rows)
    col_px, n_col = _rms(cols)
    disp_px, _ = _rms(disp)  # at infinity the disparity itself is the proportionality error
    return Alignment(row_px, col_px, disp_px, n_row, n_col, int(valid.all(axis=0).sum()))


def off_grid_parallax(calib: Calibration, rect: Rectification, points_ref: np.ndarray) -> np.ndarray:
    """(V, N, 2) rectified position of each point from each view's real centre minus from its ideal grid centre."""
    grid = calib.grid
    off = np.array([grid.offset(i) for i in range(grid.num_views)], dtype=np.float64)
    ideal = rect.grid_origin_m[None] + off[:, 1:2] * rect.grid_u_m[None] + off[:, 0:1] * rect.grid_v_m[None]
    real = calib.ref_T_view[:, :3, 3]
    K = rect.K_r  # noqa: N806

    def project(centres: np.ndarray) -> np.ndarray:
        p = (points_ref[None] - centres[:, None]) @ rect.rect_R_ref.T  # (V, N, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.stack([K[0, 0] * p[..., 0] / p[..., 2] + K[0, 2], K[1, 1] * p[..., 1] / p[..., 2] + K[1, 2]],
                            axis=-1)

    return project(real) - project(ideal)


@dataclass(frozen=True)
class PointAlignmentReport:
    """Alignment of matched points before and after rectification, and with the off-grid parallax removed.

    ``parallax`` is the same figure computed on the predicted off-grid parallax alone: how much of ``after``
    the rig's geometry explains.
    """

    before: Alignment
    after: Alignment
    compensated: Alignment
    parallax: Alignment


def align_points(calib: Calibration, rect: Rectification, pixels: np.ndarray,
                 valid: np.ndarray) -> PointAlignmentReport:
    """The full report for (V, N, 2) matched original pixels (e.g. board corners flattened over frames)."""
    grid = calib.grid
    rect_px = np.full(pixels.shape, np.nan)
    for i in range(calib.num_views):
        m = valid[i]
        if m.any():
            rect_px[i, m] = rectify_points(calib, rect, i, pixels[i, m])
    points = triangulate_dlt(calib, pixels, valid)
    parallax = off_grid_parallax(calib, rect, points)
    ok = valid & np.all(np.isfinite(parallax), axis=-1)
    before = point_alignment(grid, rect, pixels, valid)
    after = point_alignment(grid, rect, rect_px, valid)
    compensated = point_alignment(grid, rect, rect_px - parallax, ok)
    # the parallax alone, laid on the ideal positions: its "misalignment" is what the rig geometry explains
    explained = point_alignment(grid, rect, parallax, ok)
    return PointAlignmentReport(before, after, compensated, explained)
