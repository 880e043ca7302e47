"""The array's view grid: row-major indices, neighbours and the paper's chain order (paper Sec. 4.1, Fig. 5)."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

_GRID_RE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


MAX_VIEWS = 1_000_000  # more views than any camera array: a typing mistake (and memory for every per-view array)


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
    """

    rows: int
    cols: int
    reference: int = 0

    def __post_init__(self) -> None:
        for name in ("rows", "cols", "reference"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"grid {name} must be a whole number, got {value!r}")
        if self.rows * self.cols > MAX_VIEWS:
            raise ValueError(f"a {self.rows}x{self.cols} grid has more than {MAX_VIEWS} views")
        if self.rows < 1 or self.cols < 1:
            raise ValueError(f"grid dimensions must be >= 1, got {self.rows}x{self.cols}")
        if not 0 <= self.reference < self.rows * self.cols:
            raise ValueError(f"reference view {self.reference} is outside a {self.rows}x{self.cols} grid "
                             f"(0..{self.rows * self.cols - 1})")

    @property
    def num_views(self) -> int:
        """rows x cols."""
        return self.rows * self.cols

    def __str__(self) -> str:
        return f"{self.rows}x{self.cols}"

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
        """4-neighbours of a view (left, right, up, down where present)."""
        r, c = self.position(view)
        out = []
        for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
            if 0 <= r + dr < self.rows and 0 <= c + dc < self.cols:
                out.append(self.index(r + dr, c + dc))
        return out

    def horizontal_pairs(self) -> list[tuple[int, int]]:
        """(left, right) pairs of horizontally adjacent views."""
        return [(self.index(r, c), self.index(r, c + 1)) for r in range(self.rows) for c in range(self.cols - 1)]

    def vertical_pairs(self) -> list[tuple[int, int]]:
        """(upper, lower) pairs of vertically adjacent views."""
        return [(self.index(r, c), self.index(r + 1, c)) for r in range(self.rows - 1) for c in range(self.cols)]

    def chain(self) -> list[tuple[int, int]]:
        """Edges ``(from_view, to_view)`` along which features are tracked, in tracking order.

        With the reference at a corner this is the paper's chain (Sec. 4.1, Fig. 5): along the reference's row to
        its end, up (or down) into the next row, back along it, and so on — a snake through the grid. With the
        reference elsewhere no single snake covers the grid, so the chain becomes a tree that keeps the paper's
        rule "along a row, then into the next row": outwards along the reference row, then each further row is
        entered at the reference column and walked outwards. Every view except the reference appears exactly
        once as ``to_view``, after its ``from_view`` has been reached.
        """
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
