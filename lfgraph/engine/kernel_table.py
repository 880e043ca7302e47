"""A robust kernel known only as scalar callbacks (a GTSAM ``mEstimator.Custom`` made from Python functions of one
distance), evaluated on arrays from a table of its values.

GTSAM calls such a kernel once per residual; the bulk solvers (`lfgraph.engine.bulk_noise`) reweight tens of thousands
of residuals per iteration, where a Python call each cost 3x the Gaussian's time on the kernel table
(`benchmarks/refine.py --kernels-only`). A `KernelTable` samples the function once, at nodes `CORE_STEP` apart
within `CORE_REACH` whitened sigmas either side of 0 and, beyond, `OUTER_STEP` apart in ``asinh(d)`` (0.5 % of the
distance) out to `OUTER_REACH`, and interpolates with the cubic through the four nearest nodes. Each cell between
two nodes is checked at its midpoint — where a smooth function's cubic error peaks — against the function itself
and used only when it agrees to `TABLE_RTOL`; distances in cells that do not (a kink: a threshold like Huber's or
Tukey's, a jump), beyond the reach, or not finite are passed to the function one by one. The kernel is assumed to
be a function of the distance alone, as GTSAM assumes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

CORE_REACH = 32.0  # whitened distances within +-this (nearly every residual) are tabulated at even steps of
CORE_STEP = 0.005  # this many sigmas,
OUTER_REACH = 1e6  # and further out, up to +-this, at even steps of
OUTER_STEP = 0.005  # this in asinh(d) (0.5 % of the distance)
TABLE_RTOL = 1e-9  # a cell is used when the cubic matches the function at its midpoint to this, relative to the
# function's value there plus its size at one sigma (near a zero of the function no relative match is possible)


def _cubic_coefficients(values: np.ndarray) -> np.ndarray:
    """(n, 4) per cell i: the power-basis coefficients in u (0..1 across the cell from node i to i+1) of the cubic
    through nodes i-1 .. i+2 (rows without four nodes are zero)."""
    out = np.zeros((len(values), 4))
    a, b, c, d = values[:-3], values[1:-2], values[2:-1], values[3:]
    out[1:-2] = np.stack([b, c - a / 3.0 - b / 2.0 - d / 6.0, (a + c) / 2.0 - b,
                          (d - a) / 6.0 + (b - c) / 2.0], axis=1)
    return out


def _horner(columns: list[np.ndarray], i: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The cubics of cells ``i`` at fractions ``u`` (per-column gathers: ~10x faster than gathering rows)."""
    c0, c1, c2, c3 = columns
    return ((c3.take(i) * u + c2.take(i)) * u + c1.take(i)) * u + c0.take(i)


class _Segment:
    """Nodes evenly spaced in ``t = to_t(d)`` over [-reach, reach] and which cells match ``f`` at their midpoints."""

    def __init__(self, f, reach: float, step: float, to_t, to_d, scale: float):
        self.to_t, self.step = to_t, step
        n = int(np.ceil(2.0 * to_t(reach) / step)) + 3  # one node beyond each end for the outer cells' cubics
        self.t0 = -to_t(reach) - step
        nodes = self.t0 + step * np.arange(n)
        self.values = f(to_d(nodes))
        if not np.all(np.isfinite(self.values)):
            raise ValueError("the kernel is not finite at every tabulated distance")
        cells = np.arange(1, n - 2)  # cells with a node on either side of their two
        mid = f(to_d(nodes[cells] + 0.5 * step))
        self.columns = [np.ascontiguousarray(c) for c in _cubic_coefficients(self.values).T]
        fit = _horner(self.columns, cells, np.full(len(cells), 0.5))
        self.usable = np.zeros(n, dtype=bool)
        self.usable[cells] = np.abs(fit - mid) <= TABLE_RTOL * (np.abs(mid) + scale)
        self.coverage = float(np.mean(self.usable[cells]))

    def __call__(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The interpolated values at the distances ``d`` (within the reach) whose cells are usable, and that mask."""
        x = (self.to_t(d) - self.t0) / self.step
        i = x.astype(np.int64)  # within the reach 1 <= x < n - 2: truncation is the floor, every cell has its nodes
        ok = self.usable.take(i)
        if ok.all():
            return _horner(self.columns, i, x - i), ok
        return _horner(self.columns, i[ok], x[ok] - i[ok]), ok


class KernelTable:
    """``f`` of whitened distances (scalar in, float out) as a function of arrays, to `TABLE_RTOL` (module docstring).

    Args:
        f: the kernel's weight or loss, one distance at a time.

    Attributes:
        coverage: the fraction of the core's cells in use (1.0 for a smooth function).

    Raises:
        ValueError: the function gives a non-finite value at a node (nothing to interpolate).
    """

    def __init__(self, f: Callable[[float], float]):
        scalar = np.frompyfunc(f, 1, 1)
        self.f = lambda d: np.asarray(scalar(d), dtype=np.float64) if d.size else np.zeros(d.shape)
        scale = float(np.max(np.abs(self.f(np.array([-1.0, 1.0])))))
        self.core = _Segment(self.f, CORE_REACH, CORE_STEP, lambda d: d, lambda t: t, scale)
        self.outer = _Segment(self.f, OUTER_REACH, OUTER_STEP, np.arcsinh, np.sinh, scale)
        self.coverage = self.core.coverage

    def __call__(self, d: np.ndarray) -> np.ndarray:
        """f at every distance of the array ``d`` (float64, same shape)."""
        d = np.asarray(d, dtype=np.float64)
        shape = d.shape
        d = d.ravel()
        near = np.abs(d) <= CORE_REACH
        if near.all():  # nearly always: one pass over the core table, the callback only where a cell is not usable
            values, ok = self.core(d)
            if ok.all():
                return values.reshape(shape)
            out = np.empty(d.shape)
            out[ok] = values
            out[~ok] = self.f(d[~ok])
            return out.reshape(shape)
        out = np.empty(d.shape)
        done = np.zeros(d.shape, dtype=bool)
        for segment, where in ((self.core, near), (self.outer, ~near & (np.abs(d) <= OUTER_REACH))):
            idx = np.flatnonzero(where)
            values, ok = segment(d[idx])
            out[idx[ok]] = values
            done[idx[ok]] = True
        out[~done] = self.f(d[~done])
        return out.reshape(shape)
