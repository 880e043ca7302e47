"""A calibration held against the grid it claims to be (issue 42): the views' positions fitted as a lattice
``o + col u + row v`` (least squares over every view). Refused, with the likely cause: two views at one place (a
stream duplicated), two views each at the other's place (streams swapped), a view more than `OFF_GRID_SHARE` of the
pitch off the lattice, positions that run across the grid (a horizontal pair given as 2x1). Said: views up to that far
off, a lattice whose columns run to -x (rows to -y: the grid numbered the other way round). Rigs whose views are not
near-parallel (more than `PARALLEL_DEG` between optical axes: tripods around a scene) are no grid design and are not
judged, nor is a free arrangement (`lfgraph.core.grid.free_grid`: a ring, a dome, a loose set). `calibrate`
(`lfgraph.pattern.design_check`) and every import (`lfgraph.interop`) ask it."""

from __future__ import annotations

import dataclasses

import numpy as np

LATTICE_SHARE = 0.35  # a view farther than this share of the pitch from its lattice place is off the grid (a note) ...
OFF_GRID_SHARE = 1.0  # ... and refused when farther than this (a corrupted frame in a least-squares fit: 0.39)
DUPLICATE_SHARE = 0.1  # two views closer than this share of the pitch are at one place
PARALLEL_DEG = 15.0  # the largest angle between the reference's optical axis and a view's for a grid design


def axis_spread_deg(ref_T_view: np.ndarray) -> float:  # noqa: N803
    """The largest angle (deg) between the reference's optical axis and a view's."""
    z = np.asarray(ref_T_view)[:, :3, 2]  # each view's optical axis in the reference frame
    return float(np.max(np.degrees(np.arccos(np.clip(z[:, 2], -1.0, 1.0)))))


def _parallel(ref_T_view: np.ndarray) -> bool:  # noqa: N803
    return axis_spread_deg(ref_T_view) <= PARALLEL_DEG


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


def grid_problems(grid, ref_T_view: np.ndarray, strict: bool = False) -> tuple[list[str], list[str]]:  # noqa: N803
    """(errors, notes) of a calibration's view poses (``ref_T_view``) held against its grid (module docstring):
    errors name the views and the likely cause — two views at one place, two views each at the other's place, a
    view more than `OFF_GRID_SHARE` of the pitch off the lattice; notes say what is consistent but unusual (views up
    to that far off the lattice, the grid numbered the other way round, a rig that is no grid design). ``strict``
    (poses read from a file, not fitted: no bad frame can have bent them) refuses a view more than `LATTICE_SHARE`
    of the pitch off."""
    positions = ref_T_view[:, :3, 3]
    if grid.num_views < 2:
        return [], []
    if getattr(grid, "is_free", False):  # no lattice to hold it against; one viewpoint captured twice is a ring's
        return [], []
    spacing = _neighbour_spacing(grid, positions)
    errors = _duplicates(grid, positions, max(spacing, 1e-12))
    if errors:
        return errors, []
    if not _parallel(ref_T_view):
        return [], [f"the views are not near-parallel (more than {PARALLEL_DEG:g} deg between optical axes): the "
                    f"calibration is not held against the grid's order and spacing"]
    _, u, v = _lattice(grid, positions)
    if (grid.cols > 1 and abs(u[1]) > abs(u[0])) or (grid.rows > 1 and abs(v[0]) > abs(v[1])):
        return [f"the views' positions run across the {grid.rows}x{grid.cols} grid (its rows run along x, its "
                f"columns along y): the grid given the wrong way round (a horizontal pair as 2x1)? Give it as "
                f"{grid.cols}x{grid.rows}"], []
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
        if strict or max(err[i] for i in off) > OFF_GRID_SHARE * pitch:
            return [f"{what}: views out of order, or no grid? Name the true order with --view-order"], []
        return [], [f"{what}: a rig built off its design, or a poor fit (see the residuals)"]
    _, u, v = _lattice(grid, positions)
    notes = [f"the grid is numbered the other way round along its {what} ({name} {1e3 * abs(step[axis]):.1f} mm "
             f"towards -{'x' if axis == 0 else 'y'}, where lfgraph's grid runs to +{'x' if axis == 0 else 'y'})"
             for what, name, step, axis, n in (("rows", "each column", u, 0, grid.cols),
                                               ("columns", "each row", v, 1, grid.rows))
             if n > 1 and step[axis] < 0]
    return [], notes


def free_when_not_parallel(calib):  # a Calibration (lfgraph.core.calibration imports this package's grid)
    """``(calib, note)``: a calibration stored as a grid whose views are not near-parallel (more than `PARALLEL_DEG`
    between the reference's optical axis and a view's: a ring imported as one row) as a free arrangement, with a note
    saying so; otherwise ``(calib, None)``. What ``refine``, ``check`` and ``fleet`` track with."""
    if calib.grid.is_free or calib.num_views < 2:
        return calib, None
    spread = axis_spread_deg(calib.ref_T_view)
    if spread <= PARALLEL_DEG:
        return calib, None
    free = calib.replace(grid=dataclasses.replace(calib.grid, arrangement="free"))
    return free, (f"the views are not near-parallel (up to {spread:.0f} deg between the reference's optical axis and "
                  f"a view's, a grid's are within {PARALLEL_DEG:g}): taken as a free arrangement, neighbours from the "
                  f"poses (the file can say so: \"arrangement\": \"free\" in its grid)")
