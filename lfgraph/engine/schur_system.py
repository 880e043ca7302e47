"""The reduced camera system of a GTSAM graph: its whitened sparse Jacobian (``sparseJacobian_``) split into 3x3
landmark blocks and the camera block, in numpy (`lfgraph.engine.schur` solves it inside Levenberg–Marquardt)."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np


@dataclass(frozen=True)
class SchurLayout:
    """Column layout of a graph's whitened Jacobian in GTSAM's sorted-key order.

    ``keys``: sorted keys; ``offsets``/``dims``: their columns; ``landmark``: (K,) bool, keys eliminated by the
    Schur complement (3-D points); ``n``: columns; ``col_lm``: (n,) landmark index of each column (-1 for cameras);
    ``col_comp``: (n,) component 0..2 within the landmark; ``col_cam``: (n,) camera column (-1 for landmarks)."""

    keys: np.ndarray
    offsets: np.ndarray
    dims: np.ndarray
    landmark: np.ndarray
    n: int
    n_landmarks: int
    n_camera: int
    col_lm: np.ndarray
    col_comp: np.ndarray
    col_cam: np.ndarray


def schur_layout(values: gtsam.Values, landmark_char: str, landmark_dim: int = 3) -> SchurLayout:
    """The column layout of ``values`` (sorted keys, as `GaussianFactorGraph.sparseJacobian_` orders them); the
    landmarks are the keys of ``landmark_char`` with ``landmark_dim`` columns (3-D points; a calibration's board
    poses: 6)."""
    keys = np.array(sorted(values.keys()), dtype=np.uint64)
    zero = values.zeroVectors()
    dims = np.array([zero.at(int(k)).shape[0] for k in keys], dtype=np.int64)
    chars = keys >> np.uint64(56)
    landmark = (chars == np.uint64(ord(landmark_char))) & (dims == landmark_dim)
    offsets = np.concatenate([[0], np.cumsum(dims)[:-1]]).astype(np.int64)
    n = int(dims.sum())
    col_key = np.repeat(np.arange(len(keys)), dims)
    col_within = np.arange(n) - offsets[col_key]
    lm_index = np.cumsum(landmark) - 1
    col_lm = np.where(landmark[col_key], lm_index[col_key], -1)
    col_comp = np.where(landmark[col_key], col_within, -1)
    cam_cols = ~landmark[col_key]
    col_cam = np.full(n, -1, dtype=np.int64)
    col_cam[cam_cols] = np.arange(int(cam_cols.sum()))
    return SchurLayout(keys, offsets, dims, landmark, n, int(landmark.sum()), int(cam_cols.sum()), col_lm, col_comp,
                       col_cam)


def sparse_jacobian(lin: gtsam.GaussianFactorGraph, layout: SchurLayout) -> tuple[np.ndarray, ...]:
    """(rows, cols, vals, b-row mask) of ``lin``'s whitened Jacobian with its columns in ``layout``'s order.

    `sparseJacobian_` numbers the columns over the keys the graph's factors touch (sorted), not over every key of the
    values: a variable no factor of ``lin`` touches (e.g. a view without a prior) has no columns there. Its last
    column is the right-hand side b, returned as ``is_b`` (column index ``layout.n``)."""
    rows, cols, vals = (np.asarray(a) for a in lin.sparseJacobian_())
    rows, cols = rows.astype(np.int64) - 1, cols.astype(np.int64) - 1
    keys = np.array(sorted(lin.keys()), dtype=np.uint64)
    where = np.searchsorted(layout.keys, keys)
    if np.any(where >= len(layout.keys)) or np.any(layout.keys[np.minimum(where, len(layout.keys) - 1)] != keys):
        raise NotReducible("the graph has a key the values do not")
    dims = layout.dims[where]
    n_graph = int(dims.sum())
    col_map = np.concatenate([np.arange(o, o + d) for o, d in zip(layout.offsets[where], dims, strict=True)]
                             + [np.array([layout.n])]).astype(np.int64)
    if cols.size and cols.max() > n_graph:
        raise NotReducible("the graph's Jacobian has more columns than its keys")
    cols = col_map[cols]
    return rows, cols, vals, cols == layout.n


@dataclass
class ReducedSystem:
    """The normal equations J^T J d = -J^T e in Schur form (undamped): per landmark V (N,3,3), W (N,3,C) and g_l
    (N,3); the cameras' H (C,C) and g_c (C,)."""

    V: np.ndarray  # noqa: N815
    W: np.ndarray  # noqa: N815
    g_l: np.ndarray
    H: np.ndarray  # noqa: N815
    g_c: np.ndarray


class NotReducible(ValueError):
    """The graph has a structure the Schur solver does not handle (a row on two landmarks)."""


def landmark_blocks(lin: gtsam.GaussianFactorGraph, layout: SchurLayout) -> tuple[np.ndarray, ...]:
    """The whitened Jacobian's rows split by landmark: (rows, cols, vals) of its non-b entries, b (m,), the landmark
    of every row (-1: none), the landmark columns per row (m, 3), and the landmark blocks V (N, 3, 3), g_l (N, 3)."""
    rows, cols, vals, is_b = sparse_jacobian(lin, layout)
    m = int(rows.max()) + 1 if rows.size else 0
    b = np.zeros(m)
    b[rows[is_b]] = vals[is_b]
    rows, cols, vals = rows[~is_b], cols[~is_b], vals[~is_b]
    n_lm = layout.n_landmarks
    lm = layout.col_lm[cols]
    is_l = lm >= 0
    # each row may touch one landmark at most
    row_lm = np.full(m, -1, dtype=np.int64)
    row_lm[rows[is_l]] = lm[is_l]
    if np.any(row_lm[rows[is_l]] != lm[is_l]):
        raise NotReducible("a factor row touches two landmarks")
    al = np.zeros((m, 3))
    al[rows[is_l], layout.col_comp[cols[is_l]]] = vals[is_l]
    r_l = np.nonzero(row_lm >= 0)[0]
    V = np.zeros((n_lm, 3, 3))  # noqa: N806
    g_l = np.zeros((n_lm, 3))
    for a in range(3):
        g_l[:, a] = np.bincount(row_lm[r_l], weights=al[r_l, a] * b[r_l], minlength=n_lm)
        for c in range(a, 3):
            V[:, a, c] = V[:, c, a] = np.bincount(row_lm[r_l], weights=al[r_l, a] * al[r_l, c], minlength=n_lm)
    return rows, cols, vals, b, row_lm, al, V, g_l


def reduced_system(lin: gtsam.GaussianFactorGraph, layout: SchurLayout) -> ReducedSystem:
    """The normal equations of a linearised graph ``lin`` with the landmarks of ``layout`` in 3x3 blocks: V (N, 3, 3),
    W (N, 3, C), the landmark and camera gradients and the camera block H (C, C) (`ReducedSystem`)."""
    rows, cols, vals, b, row_lm, al, V, g_l = landmark_blocks(lin, layout)  # noqa: N806
    m, n_lm, n_c = len(b), layout.n_landmarks, layout.n_camera
    is_l = layout.col_lm[cols] >= 0
    # camera entries, contiguous per row and sorted by column within it
    c_rows, c_cols, c_vals = rows[~is_l], layout.col_cam[cols[~is_l]], vals[~is_l]
    sort_key = c_rows * max(n_c, 1) + c_cols
    if sort_key.size and not np.all(sort_key[1:] > sort_key[:-1]):  # factors on several camera keys
        order = np.argsort(sort_key, kind="stable")
        c_rows, c_cols, c_vals = c_rows[order], c_cols[order], c_vals[order]
    g_c = np.bincount(c_cols, weights=c_vals * b[c_rows], minlength=n_c)
    count = np.bincount(c_rows, minlength=m)
    start = np.cumsum(count) - count
    H = np.zeros((n_c, n_c))  # noqa: N806
    W = np.zeros((n_lm, 3, n_c))  # noqa: N806
    # rows with the same camera columns (e.g. one view's projections) form one dense block: H += A^T A, and W
    # gathers al x A per landmark
    weights = np.random.default_rng(0).integers(1, 2**40, size=64)
    for k in np.unique(count[count > 0]):
        rk = np.nonzero(count == k)[0]
        idx = start[rk][:, None] + np.arange(k)
        ck, vk = c_cols[idx], c_vals[idx]
        sig = ck @ weights[:k] if k <= len(weights) else ck[:, 0]
        groups, inverse = np.unique(sig, return_inverse=True)
        first = np.zeros(len(groups), dtype=np.int64)
        first[inverse[::-1]] = np.arange(len(rk))[::-1]
        if np.any(ck != ck[first][inverse]):
            raise NotReducible("rows with different camera columns share a signature")
        for g in range(len(groups)):
            sel = inverse == g
            cg, ag = ck[first[g]], vk[sel]
            H[np.ix_(cg, cg)] += ag.T @ ag
            lm_g = row_lm[rk[sel]]
            has = lm_g >= 0
            if has.any():
                lm_h, al_h, ag_h = lm_g[has], al[rk[sel]][has], ag[has]
                for a in range(3):
                    prod = al_h[:, a:a + 1] * ag_h
                    for j, col in enumerate(cg):
                        W[:, a, col] += np.bincount(lm_h, weights=prod[:, j], minlength=n_lm)
    return ReducedSystem(V, W, g_l, H, g_c)


def inv3(V: np.ndarray, strict: bool = True) -> np.ndarray:  # noqa: N803
    """Batched inverse of symmetric positive-definite 3x3 blocks (closed form); a block that is not SPD raises
    LinAlgError, or with ``strict=False`` gets a zero inverse (its landmark does not move)."""
    a, b, c = V[:, 0, 0], V[:, 0, 1], V[:, 0, 2]
    d, e, f = V[:, 1, 1], V[:, 1, 2], V[:, 2, 2]
    m1 = a * d - b * b
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * c00 + b * c01 + c * c02
    spd = (a > 0) & (m1 > 0) & (det > 0)
    if strict and not np.all(spd):
        raise np.linalg.LinAlgError("a landmark block is not positive definite")
    c11, c12, c22 = a * f - c * c, b * c - a * e, m1
    inv = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], axis=1).reshape(-1, 3, 3)
    return np.where(spd[:, None, None], inv / np.where(spd, det, 1.0)[:, None, None], 0.0)


def chol3_inv(V: np.ndarray) -> np.ndarray:  # noqa: N803
    """Batched inverse ``L^-1`` of the lower Cholesky factors ``L`` (``V = L L^T``) of symmetric 3x3 blocks (closed
    form), so that ``V^-1 = L^-T L^-1``; a block that is not positive definite raises LinAlgError."""
    a, b, c = V[:, 0, 0], V[:, 0, 1], V[:, 0, 2]
    d, e, f = V[:, 1, 1], V[:, 1, 2], V[:, 2, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = np.sqrt(a)
        l10, l20 = b / l00, c / l00
        l11 = np.sqrt(d - l10 * l10)
        l21 = (e - l20 * l10) / l11
        l22 = np.sqrt(f - l20 * l20 - l21 * l21)
        i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
        i10 = -l10 * i00 * i11
        i21 = -l21 * i11 * i22
        i20 = -(l20 * i00 + l21 * i10) * i22
    if not (np.all(a > 0) and np.all(l11 > 0) and np.all(l22 > 0)):  # NaN (a negative pivot) fails too
        raise np.linalg.LinAlgError("a landmark block is not positive definite")
    zero = np.zeros_like(a)
    return np.stack([i00, zero, zero, i10, i11, zero, i20, i21, i22], axis=1).reshape(-1, 3, 3)


def full_step(layout: SchurLayout, dl: np.ndarray, dc: np.ndarray) -> np.ndarray:
    """The (n,) step of every variable in the graph's column order from a landmark step ``dl`` (N, 3) and a camera step
    ``dc`` (C,)."""
    delta = np.empty(layout.n)
    is_l = layout.col_lm >= 0
    delta[is_l] = dl[layout.col_lm[is_l], layout.col_comp[is_l]]
    delta[~is_l] = dc[layout.col_cam[~is_l]]
    return delta


def vector_values(layout: SchurLayout, delta: np.ndarray) -> gtsam.VectorValues:
    """``delta`` (n,) in the graph's column order as GTSAM `VectorValues` (what ``Values.retract`` takes)."""
    vv = gtsam.VectorValues()
    for k, o, d in zip(layout.keys.tolist(), layout.offsets.tolist(), layout.dims.tolist(), strict=True):
        vv.insert(k, delta[o:o + d])
    return vv


def camera_block(layout: SchurLayout, key: int) -> slice:
    """The camera-column slice of a non-landmark key in `marginal_covariance`'s matrix."""
    i = int(np.searchsorted(layout.keys, np.uint64(key)))
    if i >= len(layout.keys) or int(layout.keys[i]) != key or layout.landmark[i]:
        raise KeyError(key)
    first = int(layout.col_cam[layout.offsets[i]])
    return slice(first, first + int(layout.dims[i]))
