"""Whether a calibration can be rectified at all (`check_rectifiable`: views at distinct positions, lens models that
do not fold over inside the image) and whether it describes a capture (`check_compatible`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.errors import RectificationError
from lfgraph.core.grid import ViewGrid
from lfgraph.core.grid_design import grid_problems

MIN_SEPARATION_REL = 0.05  # two views closer than this fraction of the median neighbour distance are one position
MIN_LENS_SLOPE = 0.0  # d(distorted radius)/d(radius) inside the image: below it the lens model folds over
LENS_SCALE_RANGE = (0.2, 5.0)  # distorted / ideal radius at the image corner outside this: no real lens


def check_rectifiable(calib: Calibration) -> None:
    """Refuse a calibration whose rectification would be meaningless: two views at one position (no baseline between
    them: the grid and its directions are undefined), or a lens model that folds over inside the image (its
    undistortion is undefined there, e.g. k1 = 50).

    Raises:
        RectificationError: naming the views or the view and its coefficients; a free arrangement (a ring: no rows
            and columns to line up).
    """
    grid = calib.grid
    if grid.is_free:
        raise RectificationError(f"rectification lines up rows and columns of a grid; these {grid.num_views} views "
                                 f"are a free arrangement (a ring, a dome or a loose set): check and refine work on "
                                 f"them, rectify does not")
    centres = calib.ref_T_view[:, :3, 3]
    gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    neighbours = [gaps[a, b] for a in range(grid.num_views) for b in range(a + 1, grid.num_views)
                  if sum(abs(x - y) for x, y in zip(grid.position(a), grid.position(b), strict=True)) == 1]
    scale = float(np.median(neighbours)) if neighbours else float(np.max(gaps))
    for a in range(grid.num_views):
        for b in range(a + 1, grid.num_views):
            if not gaps[a, b] > MIN_SEPARATION_REL * scale:
                raise RectificationError(
                    f"views {grid.name(a)} and {grid.name(b)} are at one position ({1e3 * gaps[a, b]:.3f} mm apart, "
                    f"neighbours are {1e3 * scale:.1f} mm): the grid's directions are undefined; check the calibration")
    errors, _ = grid_problems(grid, calib.ref_T_view)  # swapped views would be rectified ~30 deg off (issue 42)
    if errors:
        raise RectificationError("the calibration contradicts its grid: " + "; ".join(errors))
    for v, intr in enumerate(calib.intrinsics):
        w, h = calib.image_size(v)
        if intr.model.wide:  # their field may end inside the image; the crop keeps what maps
            centre = intr.undistort(np.array([[intr.cx, intr.cy], [(w - 1) / 2.0, (h - 1) / 2.0]]))
            if not np.all(np.isfinite(centre)):
                raise RectificationError(f"view {grid.name(v)}: its {intr.lens} lens model maps no ray to the image "
                                         f"centre; check the calibration")
            continue
        r_max = float(np.hypot(max(intr.cx, w - 1 - intr.cx) / intr.fx, max(intr.cy, h - 1 - intr.cy) / intr.fy))
        with np.errstate(over="ignore", invalid="ignore"):
            r2 = np.linspace(0.0, np.square(r_max), 64)
            slope = 1 + 3 * intr.k1 * r2 + 5 * intr.k2 * r2**2
            factor = 1 + intr.k1 * r2 + intr.k2 * r2**2
        if not np.isfinite(r_max) or not np.all(np.isfinite(factor)):
            raise RectificationError(f"view {grid.name(v)}: its focal length (fx {intr.fx:g}, fy {intr.fy:g} px) puts "
                                     f"the image corners at infinite angles; check the calibration")
        if not LENS_SCALE_RANGE[0] <= factor[-1] <= LENS_SCALE_RANGE[1]:
            raise RectificationError(
                f"view {grid.name(v)}: its lens model (k1 {intr.k1:g}, k2 {intr.k2:g}) scales the image corner's "
                f"radius by {factor[-1]:.3g}, which no real lens does; check the calibration")
        if np.any(slope < MIN_LENS_SLOPE):
            raise RectificationError(
                f"view {grid.name(v)}: its lens model (k1 {intr.k1:g}, k2 {intr.k2:g}) folds over inside the image "
                f"(the distortion is not monotonic out to the corners), so it cannot be undistorted there; check the "
                f"calibration")


def check_compatible(calib: Calibration, grid: ViewGrid,
                     image_size_px: tuple[int, int] | Sequence[tuple[int, int]], source: str) -> None:
    """Refuse a capture the calibration does not describe (grid, image sizes). ``image_size_px``: the capture's one
    (width, height) or (V,) per-view sizes (`CaptureSet.image_sizes`), px."""
    if (calib.grid.rows, calib.grid.cols) != (grid.rows, grid.cols):
        raise RectificationError(f"{source}: the capture is a {grid} grid but the calibration is {calib.grid}")
    sizes = np.broadcast_to(np.asarray(image_size_px, dtype=np.int64).reshape(-1, 2), (grid.num_views, 2))
    for v, (w, h) in enumerate(sizes.tolist()):
        want = calib.image_size(v)
        if (w, h) != tuple(want):
            where = "views are" if calib.view_image_sizes_px is None and len(set(map(tuple, sizes.tolist()))) == 1 \
                else f"view {grid.name(v)} is"
            raise RectificationError(f"{source}: {where} {w}x{h} px but the calibration is for {want[0]}x{want[1]} px")
