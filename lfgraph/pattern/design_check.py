"""The grid as a checked design (issue 42): a rig whose streams are wrong calibrates without a word unless the
result is held against the grid it claims to be.

- **Mirrored views** (a camera's flip option), after the per-view fits: a checkerboard has no handedness the detector
  could see (it labels a mirrored board by its own rule), so a mirrored view's per-frame pose relative to the
  reference scatters by degrees over the frames where a rigid rig's agrees to hundredths; flipping its corners back
  (x -> width - 1 - x, each row's labels reversed) and fitting it alone again must remove the scatter.
- **The lattice** (swapped cables, a duplicated stream), after the fit: the views' positions fitted as a lattice
  ``o + col u + row v`` (least squares over every view); a view farther than `LATTICE_SHARE` of the pitch from its
  lattice place is not where the grid says. The cause is named: two views at one place (a stream duplicated), two
  views each at the other's place (streams swapped), or views out of order. A lattice whose columns run to -x (rows
  to -y) is the grid numbered the other way round: said, not refused. Rigs whose views are not near-parallel (more
  than `PARALLEL_DEG` between optical axes: rigs on tripods around a scene) are no grid design and are not judged.

`view_order` re-labels the streams (``--view-order``): the fix when the cables are known to be swapped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import cv2
import numpy as np

from lfgraph.detect.detections import BoardObservations

MIRROR_SCATTER_DEG = 1.0  # a view whose per-frame relative pose to the reference scatters by more is suspect ...
MIRROR_GAIN = 10.0  # ... and mirrored when its un-mirrored corners scatter this many times less
MIRROR_MIN_FRAMES = 2  # frames shared with the reference, at the least, to judge
LATTICE_SHARE = 0.35  # a view farther than this share of the pitch from its lattice place is off the grid (a note) ...
OFF_GRID_SHARE = 1.0  # ... and refused when farther than this (a corrupted frame in a least-squares fit: 0.39)
DUPLICATE_SHARE = 0.1  # two views closer than this share of the pitch are at one place
PARALLEL_DEG = 15.0  # the largest angle between the reference's optical axis and a view's for a grid design


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
    w = obs.size_of(v)[0]
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


def _parallel(ref_T_view: np.ndarray) -> bool:  # noqa: N803
    z = ref_T_view[:, :3, 2]  # each view's optical axis in the reference frame
    return bool(np.all(np.degrees(np.arccos(np.clip(z[:, 2], -1.0, 1.0))) <= PARALLEL_DEG))


def _lattice(grid, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares lattice ``o + col u + row v`` of (V, 3) positions: (o, u, v); u or v zero where the grid has one
    column or one row."""
    rc = np.array([grid.position(i) for i in range(grid.num_views)], dtype=float)
    design = np.column_stack([np.ones(len(rc)), rc[:, 1], rc[:, 0]])
    keep = [0] + [k for k, n in ((1, grid.cols), (2, grid.rows)) if n > 1]
    coef, *_ = np.linalg.lstsq(design[:, keep], positions, rcond=None)
    full = np.zeros((3, 3))
    full[keep] = coef
    return full[0], full[1], full[2]


def _lattice_error(grid, positions: np.ndarray) -> np.ndarray:
    """(V,) each view's distance from its place on the least-squares lattice."""
    o, u, v = _lattice(grid, positions)
    rc = np.array([grid.position(i) for i in range(grid.num_views)], dtype=float)
    return np.linalg.norm(positions - (o + rc[:, 1:2] * u + rc[:, 0:1] * v), axis=1)


def _swap_explains(grid, positions: np.ndarray, a: int, b: int, pitch: float) -> tuple[bool, bool]:
    """(whether the lattice fits once views a and b trade places, whether that lattice runs to +x and +y)."""
    swapped = positions.copy()
    swapped[[a, b]] = swapped[[b, a]]
    _, u, v = _lattice(grid, swapped)
    return bool(np.max(_lattice_error(grid, swapped)) <= LATTICE_SHARE * pitch), bool(u[0] >= 0 and v[1] >= 0)


def _duplicates(grid, positions: np.ndarray, spacing: float) -> list[str]:
    out = []
    gaps = np.linalg.norm(positions[:, None] - positions[None], axis=2)
    pairs = [gaps[a, b] for a in range(grid.num_views) for b in grid.neighbours(a) if a < b]
    pitch = float(np.median(pairs)) if pairs else spacing  # for the message: every neighbour pair, duplicates too
    for a, b in zip(*np.nonzero(np.triu(gaps < DUPLICATE_SHARE * spacing, k=1)), strict=True):
        out.append(f"views {grid.name(a)} and {grid.name(b)} are calibrated at one place ({1e3 * gaps[a, b]:.3f} mm "
                   f"apart; neighbours are {1e3 * pitch:.1f} mm apart): one stream duplicated (the same camera's "
                   f"images under two names)?")
    return out


def _neighbour_spacing(grid, positions: np.ndarray) -> float:
    """The median over views of the distance to the nearest grid neighbour: the pitch, robust to a view calibrated
    far off (a mirrored stream put one view 1.3 m from a 6 mm rig)."""
    nearest = [min(np.linalg.norm(positions[a] - positions[b]) for b in grid.neighbours(a))
               for a in range(grid.num_views) if grid.neighbours(a)]
    return float(np.median(nearest)) if nearest else 0.0


def grid_problems(grid, ref_T_view: np.ndarray) -> tuple[list[str], list[str]]:  # noqa: N803
    """(errors, notes) of a calibration's view poses (``ref_T_view``) held against its grid (module docstring):
    errors name the views and the likely cause — two views at one place, two views each at the other's place, a
    view more than `OFF_GRID_SHARE` of the pitch off the lattice; notes say what is consistent but unusual (views up
    to that far off the lattice, the grid numbered the other way round, a rig that is no grid design)."""
    positions = ref_T_view[:, :3, 3]
    if grid.num_views < 2:
        return [], []
    spacing = _neighbour_spacing(grid, positions)
    errors = _duplicates(grid, positions, max(spacing, 1e-12))
    if errors:
        return errors, []
    if not _parallel(ref_T_view):
        return [], [f"the views are not near-parallel (more than {PARALLEL_DEG:g} deg between optical axes): the "
                    f"calibration is not held against the grid's order and spacing"]
    err, pitch = _lattice_error(grid, positions), spacing
    off = [int(i) for i in np.nonzero(err > LATTICE_SHARE * pitch)[0]]
    if off:
        fits = [((a, b), _swap_explains(grid, positions, a, b, pitch)) for i, a in enumerate(off) for b in off[i + 1:]]
        fits = [(pair, forward) for pair, (fit, forward) in fits if fit]  # a swap that the grid's direction keeps first
        if fits:
            a, b = max(fits, key=lambda x: x[1])[0]
            return [f"views {grid.name(a)} and {grid.name(b)} are each calibrated where the grid puts the other "
                    f"({1e3 * err[a]:.1f} and {1e3 * err[b]:.1f} mm off a {1e3 * pitch:.1f} mm pitch): swapped cables "
                    f"(each stream under the other's name)? Name the true order with --view-order (Python: "
                    f"lfgraph.pattern.design_check.view_order)"], []
        what = (f"views {', '.join(grid.name(i) for i in off)} are not where the grid puts them (up to "
                f"{1e3 * max(err[i] for i in off):.1f} mm off the lattice the rig forms, pitch {1e3 * pitch:.1f} mm)")
        if max(err[i] for i in off) > OFF_GRID_SHARE * pitch:
            return [f"{what}: views out of order, or no grid? Name the true order with --view-order"], []
        return [], [f"{what}: a rig built off its design, or a poor fit (see the residuals)"]
    _, u, v = _lattice(grid, positions)
    notes = [f"the grid is numbered the other way round along its {what} ({name} {1e3 * abs(step[axis]):.1f} mm "
             f"towards -{'x' if axis == 0 else 'y'}, where lfgraph's grid runs to +{'x' if axis == 0 else 'y'})"
             for what, name, step, axis, n in (("rows", "each column", u, 0, grid.cols),
                                               ("columns", "each row", v, 1, grid.rows))
             if n > 1 and step[axis] < 0]
    return [], notes


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
    sizes = None if obs.view_sizes_px is None else tuple(obs.view_sizes_px[p] for p in perm)
    sources = tuple(tuple(s[p] for p in perm) if len(s) == obs.num_views else s for s in obs.sources)
    return dataclasses.replace(obs, corners_px=obs.corners_px[perm], valid=obs.valid[perm], view_sizes_px=sizes,
                               sources=sources)
