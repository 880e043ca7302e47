"""The array's view grid: row-major indices, neighbours and the paper's chain order (paper Sec. 4.1, Fig. 5).

A rig that is not a grid (a converging ring or dome, a loose set of cameras on a robot) is a grid of arrangement
``"free"``: its views keep row-major indices and names (one row of N views in file order, or any rows x cols the
capture's files are named by), but their neighbourhood comes from their poses (`free_grid`: each view linked to the
views it sees the scene most alike with, by the angle between optical axes and the distance between centres), and
the chain the trackers follow is a tree over those links from the reference. Rows and columns, and with them
rectification, belong to ``"grid"`` alone.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

_GRID_RE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


MAX_VIEWS = 1_000_000  # more views than any camera array: a typing mistake (and memory for every per-view array)
ARRANGEMENTS = ("grid", "free")  # rows and columns of near-parallel views; views whose neighbourhood is their poses'
FREE_LINKS = 2  # a free arrangement links each view to its this many nearest views (and whatever keeps it connected)
FREE_DISTANCE_DEG = 10.0  # the link score: the angle between optical axes (deg) + this x distance / largest distance


def parse_grid(text: str) -> tuple[int, int]:
    """Parse ``"ROWSxCOLS"`` (e.g. ``"4x4"``, ``"1x2"``) into ``(rows, cols)``.

    Raises:
        ValueError: not of that form, or a dimension is 0. (A 1x1 "grid" is one camera: it can be calibrated, not
            rectified.)
    """
    m = _GRID_RE.match(text)
    if not m:
        raise ValueError(f"grid must be ROWSxCOLS such as 4x4 or 1x2, got {text!r}")
    rows, cols = int(m.group(1)), int(m.group(2))
    if rows < 1 or cols < 1:
        raise ValueError(f"a grid needs at least 1x1 views, got {rows}x{cols}")
    if rows * cols > MAX_VIEWS:
        raise ValueError(f"a {rows}x{cols} grid has more than {MAX_VIEWS} views; check --grid")
    return rows, cols


@dataclass(frozen=True)
class ViewGrid:
    """A ``rows x cols`` camera array; view ``v`` sits at ``(v // cols, v % cols)``.

    Row index grows downwards (+y of the camera frame), column index to the right (+x).

    ``arrangement`` is ``"grid"`` (rows and columns of near-parallel views: the paper's arrays) or ``"free"`` (a
    ring, a dome, a loose set: rows and columns only number the views; ``links`` are the neighbour pairs their poses
    give, ``link_deg`` the angle between each pair's optical axes — build one with `free_grid`). Links and angles are
    derived from the poses and take no part in comparing grids.
    """

    rows: int
    cols: int
    reference: int = 0
    arrangement: str = "grid"
    links: tuple[tuple[int, int], ...] = field(default=(), compare=False)
    link_deg: tuple[float, ...] = field(default=(), compare=False)

    def __post_init__(self) -> None:
        for name in ("rows", "cols", "reference"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"grid {name} must be a whole number, got {value!r}")
        if self.arrangement not in ARRANGEMENTS:
            raise ValueError(f"grid arrangement must be one of {', '.join(ARRANGEMENTS)}, got {self.arrangement!r}")
        self._check_links()
        if self.rows * self.cols > MAX_VIEWS:
            raise ValueError(f"a {self.rows}x{self.cols} grid has more than {MAX_VIEWS} views")
        if self.rows < 1 or self.cols < 1:
            raise ValueError(f"grid dimensions must be >= 1, got {self.rows}x{self.cols}")
        if not 0 <= self.reference < self.rows * self.cols:
            raise ValueError(f"reference view {self.reference} is outside a {self.rows}x{self.cols} grid "
                             f"(0..{self.rows * self.cols - 1})")

    def _check_links(self) -> None:
        if self.arrangement == "grid" and (self.links or self.link_deg):
            raise ValueError("a grid's neighbours are its rows and columns: links belong to a free arrangement")
        n = self.rows * self.cols
        for pair in self.links:
            if len(pair) != 2 or not all(0 <= int(x) < n for x in pair) or pair[0] == pair[1]:
                raise ValueError(f"link {pair!r}: must join two different views of the {n} views")
        if self.link_deg and len(self.link_deg) != len(self.links):
            raise ValueError(f"{len(self.link_deg)} link angles for {len(self.links)} links")

    @property
    def is_free(self) -> bool:
        """Whether the views are a free arrangement (neighbours from their poses), not rows and columns."""
        return self.arrangement == "free"

    def require_rows_and_columns(self, what: str) -> None:
        """A ValueError naming ``what`` when the views are not rows and columns (a free arrangement)."""
        if self.is_free:
            raise ValueError(f"{what} needs a grid of rows and columns; these {self.num_views} views are a free "
                             f"arrangement (a ring, a dome or a loose set: their neighbours come from their poses)")

    @property
    def num_views(self) -> int:
        """rows x cols."""
        return self.rows * self.cols

    def as_dict(self) -> dict[str, object]:
        """``grid`` of ``calibration.json``: rows, cols, reference, and ``arrangement`` when it is not a grid (the
        links are not stored: they follow from the poses)."""
        return {"rows": self.rows, "cols": self.cols, "reference": self.reference,
                **({"arrangement": self.arrangement} if self.is_free else {})}

    def __str__(self) -> str:
        return f"{self.rows}x{self.cols}" + (" free" if self.is_free else "")

    def index(self, row: int, col: int) -> int:
        """The row-major index of the view at (row, col); a ValueError outside the grid."""
        if not (0 <= row < self.rows and 0 <= col < self.cols):
            raise ValueError(f"(row {row}, col {col}) is outside a {self} grid")
        return row * self.cols + col

    def position(self, view: int) -> tuple[int, int]:
        """(row, col) of a view."""
        if not 0 <= view < self.num_views:
            raise ValueError(f"view {view} is outside a {self} grid (0..{self.num_views - 1})")
        return divmod(view, self.cols)

    def name(self, view: int) -> str:
        """File-style name of a view, ``r{row:02d}_c{col:02d}``."""
        r, c = self.position(view)
        return f"r{r:02d}_c{c:02d}"

    def find(self, key: object, what: str, error: type[ValueError] = ValueError) -> int:
        """The index of a view given by name (``r01_c02``) or index; ``error`` (a ValueError) naming ``what`` it was
        for."""
        if isinstance(key, int) and not isinstance(key, bool):
            v = key
        else:
            v = next((i for i in range(self.num_views) if self.name(i) == str(key)), None)
        if v is None or not 0 <= v < self.num_views:
            raise error(f"{what} for {key!r}: no such view in the {self} grid (views are named like "
                             f"{self.name(0)})")
        return v

    def offset(self, view: int) -> tuple[int, int]:
        """(d_row, d_col) of a view from the reference, in grid steps."""
        r, c = self.position(view)
        r0, c0 = self.position(self.reference)
        return r - r0, c - c0

    def neighbours(self, view: int) -> list[int]:
        """4-neighbours of a view (left, right, up, down where present); in a free arrangement the views it is
        linked to."""
        if self.is_free:
            self.position(view)  # ValueError naming the range
            return sorted({b if a == view else a for a, b in self.links if view in (a, b)})
        r, c = self.position(view)
        out = []
        for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
            if 0 <= r + dr < self.rows and 0 <= c + dc < self.cols:
                out.append(self.index(r + dr, c + dc))
        return out

    def horizontal_pairs(self) -> list[tuple[int, int]]:
        """(left, right) pairs of horizontally adjacent views."""
        self.require_rows_and_columns("rows of views")
        return [(self.index(r, c), self.index(r, c + 1)) for r in range(self.rows) for c in range(self.cols - 1)]

    def vertical_pairs(self) -> list[tuple[int, int]]:
        """(upper, lower) pairs of vertically adjacent views."""
        self.require_rows_and_columns("columns of views")
        return [(self.index(r, c), self.index(r + 1, c)) for r in range(self.rows - 1) for c in range(self.cols)]

    def chain(self) -> list[tuple[int, int]]:
        """Edges ``(from_view, to_view)`` along which features are tracked, in tracking order.

        With the reference at a corner this is the paper's chain (Sec. 4.1, Fig. 5): along the reference's row to
        its end, up (or down) into the next row, back along it, and so on — a snake through the grid. With the
        reference elsewhere no single snake covers the grid, so the chain becomes a tree that keeps the paper's
        rule "along a row, then into the next row": outwards along the reference row, then each further row is
        entered at the reference column and walked outwards. Every view except the reference appears exactly
        once as ``to_view``, after its ``from_view`` has been reached.

        In a free arrangement the chain is a tree over the links grown from the reference (`free_chain`): each step
        the closest link (smallest angle between optical axes) from a reached view to a new one.
        """
        if self.is_free:
            return free_chain(self)
        r0, c0 = self.position(self.reference)
        corner_col = c0 in (0, self.cols - 1)
        corner_row = r0 in (0, self.rows - 1)
        edges: list[tuple[int, int]] = []
        if corner_col and corner_row:
            row_step = 1 if r0 == 0 else -1
            col_dir = 1 if c0 == 0 else -1
            r, c = r0, c0
            for k in range(self.rows):
                if k > 0:
                    edges.append((self.index(r, c), self.index(r + row_step, c)))
                    r += row_step
                    col_dir = -col_dir
                for _ in range(self.cols - 1):
                    edges.append((self.index(r, c), self.index(r, c + col_dir)))
                    c += col_dir
            return edges

        def walk_row(r: int) -> None:
            for direction in (1, -1):
                c = c0
                while 0 <= c + direction < self.cols:
                    edges.append((self.index(r, c), self.index(r, c + direction)))
                    c += direction

        walk_row(r0)
        for direction in (1, -1):
            r = r0
            while 0 <= r + direction < self.rows:
                edges.append((self.index(r, c0), self.index(r + direction, c0)))
                r += direction
                walk_row(r)
        return edges

    def chain_order(self) -> list[int]:
        """Views in tracking order, starting with the reference."""
        return [self.reference] + [b for _, b in self.chain()]


def free_chain(grid: ViewGrid) -> list[tuple[int, int]]:
    """Edges ``(from_view, to_view)`` of a free arrangement's tracking tree: grown from the reference by the link of
    smallest angle (then of smallest link index) between a reached view and a new one (Prim's rule). Views no link
    reaches are left out."""
    deg = grid.link_deg or tuple(float(k) for k in range(len(grid.links)))
    order = sorted(range(len(grid.links)), key=lambda k: (deg[k], k))
    reached, edges = {grid.reference}, []
    grew = True
    while grew:
        grew = False
        for k in order:
            a, b = grid.links[k]
            if (a in reached) != (b in reached):
                edge = (a, b) if a in reached else (b, a)
                edges.append(edge)
                reached.add(edge[1])
                grew = True
                break
    return edges


def free_grid(ref_T_view: np.ndarray, reference: int = 0, rows: int = 1,  # noqa: N803
              links: int = FREE_LINKS) -> ViewGrid:
    """A free arrangement of the (V, 4, 4) ``ref_T_view`` poses: ``rows`` x V/rows views (one row by default), each
    linked to its ``links`` nearest views and by the minimum spanning tree (so every view is reached), nearness
    scored as the angle between optical axes (deg) plus `FREE_DISTANCE_DEG` x centre distance / the largest one.

    Raises:
        ValueError: poses that are not (V, 4, 4), or V not a multiple of ``rows``.
    """
    poses = np.asarray(ref_T_view, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"ref_T_view must be (V, 4, 4), got {list(poses.shape)}")
    n = len(poses)
    if n % rows:
        raise ValueError(f"{n} views do not make {rows} rows")
    axes, centres = poses[:, :3, 2], poses[:, :3, 3]
    angle = np.degrees(np.arccos(np.clip(axes @ axes.T, -1.0, 1.0)))
    dist = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    score = angle + FREE_DISTANCE_DEG * dist / max(float(dist.max()), 1e-12)
    np.fill_diagonal(score, np.inf)
    pairs = {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in np.argsort(score[i])[:min(links, n - 1)]}
    best, via, out = score[0].copy(), np.zeros(n, dtype=int), np.ones(n, dtype=bool)
    out[0] = False
    for _ in range(n - 1):  # Prim's minimum spanning tree: no view left unlinked
        b = int(np.argmin(np.where(out, best, np.inf)))
        pairs.add((min(b, int(via[b])), max(b, int(via[b]))))
        out[b] = False
        closer = score[b] < best
        best, via = np.where(closer, score[b], best), np.where(closer, b, via)
    ordered = tuple(sorted(pairs))
    return ViewGrid(rows, n // rows, int(reference), "free", ordered, tuple(float(angle[a, b]) for a, b in ordered))
