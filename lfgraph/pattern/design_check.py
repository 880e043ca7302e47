"""The grid as a checked design (issue 42): a rig whose streams are wrong calibrates without a word unless the
result is held against the grid it claims to be.

- **Mirrored views** (a camera's flip option), after the per-view fits: a checkerboard has no handedness the detector
  could see (it labels a mirrored board by its own rule), so a mirrored view's per-frame pose relative to the
  reference scatters by degrees over the frames where a rigid rig's agrees to hundredths; flipping its corners back
  (x -> width - 1 - x, each row's labels reversed) and fitting it alone again must remove the scatter.
- **The lattice** (swapped cables, a duplicated stream, a grid given the wrong way round), after the fit:
  `lfgraph.core.grid_design.grid_problems`, which imports ask too.

`view_order` re-labels the streams (``--view-order``): the fix when the cables are known to be swapped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import cv2
import numpy as np

from lfgraph.core.grid_design import grid_problems  # noqa: F401  (calibrate's check, re-exported)
from lfgraph.detect.detections import BoardObservations

MIRROR_SCATTER_DEG = 1.0  # a view whose per-frame relative pose to the reference scatters by more is suspect ...
MIRROR_GAIN = 10.0  # ... and mirrored when its un-mirrored corners scatter this many times less
MIRROR_MIN_FRAMES = 2  # frames shared with the reference, at the least, to judge


def _relative_scatter_deg(view_T_board: np.ndarray, ref: int, v: int) -> float:  # noqa: N803
    """The median angle (deg) between the per-frame estimates of ``ref_T_view`` (PnP in both views) and their medoid:
    a few hundredths of a degree for a rigid rig, degrees when one view's boards are mirrored (NaN: < 2 frames)."""
    have = [f for f in range(view_T_board.shape[1])
            if np.all(np.isfinite(view_T_board[ref, f])) and np.all(np.isfinite(view_T_board[v, f]))]
    if len(have) < MIRROR_MIN_FRAMES:
        return float("nan")
    rot = np.stack([view_T_board[ref, f][:3, :3] @ view_T_board[v, f][:3, :3].T for f in have])
    cos = (np.einsum("aji,bji->ab", rot, rot) - 1.0) / 2.0  # trace(R_a^T R_b)
    angles = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return float(np.median(angles[np.argmin(np.median(angles, axis=1))]))


def _mirrored(obs: BoardObservations, v: int) -> BoardObservations:
    """View ``v``'s corners as the un-mirrored image shows them: x -> width - 1 - x, and each board row's labels
    reversed (the detector labelled the mirrored board by its own rule)."""
    w = obs.image_size(v)[0]
    cols, rows = obs.board.cols, obs.board.rows
    order = (np.arange(rows)[:, None] * cols + (cols - 1 - np.arange(cols))[None]).ravel()
    corners, valid = obs.corners_px.copy(), obs.valid.copy()
    corners[v] = corners[v][:, order]
    corners[v, ..., 0] = (w - 1) - corners[v, ..., 0]
    valid[v] = valid[v][:, order]
    return dataclasses.replace(obs, corners_px=corners, valid=valid)


def mirrored_views(obs: BoardObservations, view_T_board: np.ndarray, lenses: Sequence[str]) -> list[str]:  # noqa: N803
    """One message per view whose images are mirrored (a camera's flip option): its relative pose to the reference
    scatters by more than `MIRROR_SCATTER_DEG` over the frames (``view_T_board``: the paper route's PnP poses) and
    its own fit of the un-mirrored corners scatters `MIRROR_GAIN` times less. Checkerboards only (a mirrored
    ChArUco marker is no marker: such a board is not detected at all)."""
    from lfgraph.pattern.lenses import fit_mono

    if getattr(obs.board, "kind", None) != "chessboard":
        return []
    ref = obs.grid.reference
    scatter = {v: _relative_scatter_deg(view_T_board, ref, v) for v in range(obs.num_views) if v != ref}
    suspects = [v for v, s in scatter.items() if s > MIRROR_SCATTER_DEG]
    out = []
    for v in suspects:
        try:
            fit = fit_mono(_mirrored(obs, v), v, lenses[v])
        except (cv2.error, RuntimeError, ValueError):
            continue
        poses = view_T_board.copy()
        poses[v] = np.nan
        for f, pose in fit.view_T_board.items():
            poses[v, f] = pose
        after = _relative_scatter_deg(poses, ref, v)
        if after * MIRROR_GAIN < scatter[v]:
            out.append(f"{obs.describe(v)}: its images are mirrored (its board poses scatter by {scatter[v]:.1f} deg "
                       f"against the reference's over the frames, {after:.3f} deg once its images are flipped back): "
                       f"a camera's flip or mirror option? Turn it off or un-mirror the images, then calibrate again")
    return out


def order_permutation(grid, names: Sequence[str]) -> list[int]:
    """For each grid position (row-major), the index of the stream captured under ``names[i]``; ValueError unless
    ``names`` names every view of ``grid`` once."""
    known = [grid.name(i) for i in range(grid.num_views)]
    names = [str(n).strip() for n in names]
    if sorted(names) != sorted(known):
        raise ValueError(f"--view-order must name every view of the {grid.rows}x{grid.cols} grid once ("
                         f"{', '.join(known)}), got {', '.join(names)}")
    return [known.index(n) for n in names]


def view_order(obs: BoardObservations, names: Sequence[str]) -> BoardObservations:
    """The observations with their streams re-labelled: ``names[i]`` is the name under which grid position ``i``'s
    stream was captured (every view once), e.g. ``["r00_c01", "r00_c00", "r01_c00", "r01_c01"]`` for a 2x2 whose
    first two cables were swapped."""
    perm = order_permutation(obs.grid, names)
    sizes = None if obs.view_image_sizes_px is None else tuple(obs.view_image_sizes_px[p] for p in perm)
    sources = tuple(tuple(s[p] for p in perm) if len(s) == obs.num_views else s for s in obs.sources)
    return dataclasses.replace(obs, corners_px=obs.corners_px[perm], valid=obs.valid[perm], view_image_sizes_px=sizes,
                               sources=sources)
