"""Figures with matplotlib (Agg, no display): the studies, the depth error and a calibration report.

Every figure is written as PNG and PDF (atomically). Study curves show the median over seeds with the spread (the
band from the lowest to the highest seed); every series has its own marker and line style so that identical
series stay visible; the legend sits outside the axes; errors that span more than `LOG_SPAN` use log axes.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402

from lfgraph.core.files import atomic_path  # noqa: E402

FORMATS = ("png", "pdf")
DPI = 110  # PNG resolution: small files, readable text
LOG_SPAN = 10.0  # a log axis when the largest positive value is this many times the smallest
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
LINESTYLES = ("-", "--", "-.", ":")
BAND_ALPHA = 0.18
MARKERS_PER_CURVE = 12  # dense curves carry a marker every len/MARKERS_PER_CURVE points
COVERAGE_BINS = (16, 12)  # cells across, down for the coverage and residual maps
ARROW_CELL_SHARE = 0.8  # the longest arrow of the residual and grid-deviation maps spans this much of a cell
METHOD_LABELS = {"cramer-rao": "Cramér–Rao floor (joint's 1σ)", "joint": "joint graph", "paper": "paper route"}
SHAKE_METRICS = {"transfer_px": "transfer error at infinity (px)", "rot_err_deg": "rotation error (deg)",
                 "rms_after_px": "reprojection RMS after (px)"}
CALIBRATION_METRICS = {"fx_err_px": "fx error (px)", "pos_err_mm": "view position error (mm)",
                       "rot_err_deg": "view rotation error (deg)"}


def style(k: int) -> dict[str, Any]:
    """Marker and line style of the k-th series (distinct for the first len(MARKERS) * len(LINESTYLES))."""
    return {"marker": MARKERS[k % len(MARKERS)], "linestyle": LINESTYLES[(k // 2) % len(LINESTYLES)],
            "color": f"C{k % 10}", "markersize": 6, "linewidth": 1.6, "markerfacecolor": "none" if k % 2 else None}


def save(fig: Figure, stem: str | os.PathLike) -> list[Path]:
    """Write ``fig`` as ``stem.png`` and ``stem.pdf`` (atomically) and close it; returns the paths."""
    stem = Path(stem)
    written = []
    for fmt in FORMATS:
        path = stem.with_name(f"{stem.name}.{fmt}")
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=fmt, dpi=DPI, bbox_inches="tight")
        written.append(path)
    plt.close(fig)
    return written


def _plain(value: float, _pos: Any = None) -> str:
    return f"{value:g}"


def _plain_2_5(value: float, _pos: Any = None) -> str:
    """Label the minor log ticks at 2 and 5 times a power of ten only."""
    if value <= 0:
        return ""
    mantissa = value / 10 ** np.floor(np.log10(value) + 1e-9)
    return f"{value:g}" if any(abs(mantissa - m) < 1e-6 for m in (2.0, 5.0)) else ""


def maybe_log(ax: Any, values: np.ndarray, axis: str = "y") -> None:
    """Log scale on ``axis`` when the positive finite values span more than `LOG_SPAN` and none is negative;
    with zeros among them (e.g. no shake) a symmetric log scale, linear below the smallest positive value."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    pos = v[v > 0]
    if not pos.size or np.any(v < 0) or pos.max() / pos.min() <= LOG_SPAN:
        return
    set_scale = ax.set_yscale if axis == "y" else ax.set_xscale
    if np.any(v == 0):
        set_scale("symlog", linthresh=float(pos.min()), linscale=0.5)
    else:
        set_scale("log")
    target = ax.yaxis if axis == "y" else ax.xaxis
    target.set_major_formatter(FuncFormatter(_plain))  # 0.5, 2, 10 rather than 5x10^-1
    target.set_minor_formatter(FuncFormatter(_plain_2_5))


def spread(rows: Sequence[dict[str, Any]], group: Sequence[str], x: str, metric: str
           ) -> dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]]:
    """Per group: x values, median, lowest and highest ``metric`` over the rows (seeds) at each x, and the most
    seeds at one x. NaN (failed trials) are left out."""
    by: dict[tuple, dict[float, list[float]]] = {}
    for r in rows:
        by.setdefault(tuple(str(r[k]) for k in group), {}).setdefault(float(r[x]), []).append(float(r[metric]))
    out = {}
    for g, per_x in sorted(by.items()):
        xs = np.array(sorted(per_x))
        vals = [np.asarray(per_x[v]) for v in xs]
        vals = [v[np.isfinite(v)] for v in vals]
        med = np.array([np.median(v) if v.size else np.nan for v in vals])
        lo = np.array([v.min() if v.size else np.nan for v in vals])
        hi = np.array([v.max() if v.size else np.nan for v in vals])
        out[g] = (xs, med, lo, hi, max(len(per_x[v]) for v in xs))
    return out


def _series(ax: Any, k: int, label: str, xs: np.ndarray, med: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    st = style(k)
    ax.plot(xs, med, label=label, **st)
    if np.any(hi > lo):
        ax.fill_between(xs, lo, hi, color=st["color"], alpha=BAND_ALPHA, linewidth=0)


def _legend_outside(fig: Figure, axes: Sequence[Any], title: str) -> None:
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.0, 0.95), title=title, frameon=False)


def shake_figure(rows: Sequence[dict[str, Any]], stem: str | os.PathLike) -> list[Path]:
    """`make_shake_figure` written as ``stem.png`` and ``stem.pdf``; returns the paths."""
    return save(make_shake_figure(rows), stem)


def make_shake_figure(rows: Sequence[dict[str, Any]]) -> Figure:
    """The shake study: transfer error, rotation error and reprojection RMS against the shake, one series per
    configuration (median over seeds, band: lowest to highest seed), with the shake itself for reference."""
    fig, axes = plt.subplots(1, len(SHAKE_METRICS), figsize=(13, 3.8), constrained_layout=True)
    seeds = 0
    for ax, (metric, label) in zip(axes, SHAKE_METRICS.items(), strict=True):
        values = []
        if metric in ("transfer_px", "rot_err_deg"):
            before = metric.replace("_px", "_before_px") if metric == "transfer_px" else "rot_err_before_deg"
            for xs, med, lo, hi, _ in spread(rows, (), "rot_deg", before).values():
                ax.plot(xs, med, color="0.45", linestyle=":", marker="x", label="before refinement (the shake)")
                ax.fill_between(xs, lo, hi, color="0.45", alpha=BAND_ALPHA / 2, linewidth=0)
                values.append(med)
        for k, ((config,), (xs, med, lo, hi, n)) in enumerate(spread(rows, ("config",), "rot_deg", metric).items()):
            _series(ax, k, config, xs, med, lo, hi)
            values += [lo, hi]
            seeds = max(seeds, n)
        maybe_log(ax, np.concatenate(values) if values else np.array([]))
        ax.set_xlabel("rotation shake level (deg; translation paired)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"shake study: median over {seeds} seed(s), band = lowest to highest seed")
    _legend_outside(fig, axes, "configuration")
    return fig


def calibration_figure(rows: Sequence[dict[str, Any]], stem: str | os.PathLike) -> list[Path]:
    """`make_calibration_figure` written as ``stem.png`` and ``stem.pdf``; returns the paths."""
    return save(make_calibration_figure(rows), stem)


def make_calibration_figure(rows: Sequence[dict[str, Any]]) -> Figure:
    """The calibration study: one row per corner noise, one column per metric, error against frames, one series
    per method (median over seeds, band: lowest to highest seed; ``cramer-rao`` is the joint route's predicted
    1-sigma, a floor rather than an error)."""
    sigmas = sorted({float(r["sigma_px"]) for r in rows})
    fig, axes = plt.subplots(len(sigmas), len(CALIBRATION_METRICS), figsize=(13, 3.6 * len(sigmas)),
                             constrained_layout=True, squeeze=False)
    seeds = 0
    for i, sigma in enumerate(sigmas):
        sel = [r for r in rows if float(r["sigma_px"]) == sigma]
        for ax, (metric, label) in zip(axes[i], CALIBRATION_METRICS.items(), strict=True):
            values = []
            for k, ((method,), (xs, med, lo, hi, n)) in enumerate(spread(sel, ("method",), "frames", metric).items()):
                _series(ax, k, METHOD_LABELS.get(method, method), xs, med, lo, hi)
                values += [lo, hi]
                seeds = max(seeds, n)
            maybe_log(ax, np.concatenate(values))
            ax.set_xlabel("frames")
            ax.set_ylabel(label)
            ax.set_title(f"corner noise {sigma:g} px", fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"calibration study: median over {seeds} seed(s), band = lowest to highest seed")
    _legend_outside(fig, axes[0], "method")
    return fig


def depth_error_figure(depth_m: np.ndarray, error_m: np.ndarray, focal_px: float, baseline_m: float,
                       error_px: float, stem: str | os.PathLike) -> list[Path]:
    """`make_depth_error_figure` written as ``stem.png`` and ``stem.pdf``; returns the paths."""
    return save(make_depth_error_figure(depth_m, error_m, focal_px, baseline_m, error_px), stem)


def make_depth_error_figure(depth_m: np.ndarray, error_m: np.ndarray, focal_px: float, baseline_m: float,
                            error_px: float) -> Figure:
    """Depth error (mm) against depth (m), with the first-order approximation Z^2 E / (f b) for comparison."""
    fig, ax = plt.subplots(figsize=(7.5, 4.2), constrained_layout=True)
    z = np.asarray(depth_m, dtype=float)
    e_mm = 1e3 * np.asarray(error_m, dtype=float)
    first_mm = 1e3 * z**2 * error_px / (focal_px * baseline_m)
    every = max(1, len(z) // MARKERS_PER_CURVE)
    ax.plot(z, e_mm, label=f"depth error, E = {error_px:g} px", markevery=every, **style(0))
    ax.plot(z, first_mm, label="first order: Z² E / (f b)", markevery=(every // 2, every), **style(3))
    maybe_log(ax, np.concatenate([e_mm, first_mm]))
    ax.set_xlabel("depth Z (m)")
    ax.set_ylabel("depth error (mm)")
    ax.set_title(f"f = {focal_px:g} px, baseline b = {baseline_m:g} m", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    _legend_outside(fig, [ax], "")
    return fig


# --------------------------------------------------------------------------------------------- calibration report
def _grid_axes(grid: Any, title: str, size_in: float = 2.6) -> tuple[Figure, np.ndarray]:
    fig, axes = plt.subplots(grid.rows, grid.cols, figsize=(size_in * grid.cols + 1.2, size_in * grid.rows * 0.85),
                             constrained_layout=True, squeeze=False)
    if title:
        fig.suptitle(title)
    return fig, axes


def _nice_scale(longest: float, target: float) -> float:
    """A round factor (1, 2 or 5 x 10^k) that draws an arrow of length ``longest`` at most ``target`` long."""
    if not np.isfinite(longest) or longest <= 0:
        return 1.0
    raw = target / longest
    k = np.floor(np.log10(raw))
    for m in (5.0, 2.0, 1.0):
        if m * 10**k <= raw:
            return float(m * 10**k)
    return float(10**k)


def coverage_figure(obs: Any, stem: str | os.PathLike) -> list[Path]:
    """Per view (in the array's layout): detected corners per image cell."""
    fig, axes = _grid_axes(obs.grid, "coverage: detected corners per image cell (white: none)")
    counts = []
    for v in range(obs.num_views):
        w, h = obs.image_size(v)
        px = obs.corners_px[v][obs.valid[v]]
        c, _, _ = np.histogram2d(px[:, 0], px[:, 1], bins=COVERAGE_BINS, range=[[0, w], [0, h]])
        counts.append(c.T)
    vmax = max(1.0, max(float(c.max()) for c in counts))
    for v in range(obs.num_views):
        r, c = obs.grid.position(v)
        ax = axes[r, c]
        shown = np.ma.masked_equal(counts[v], 0)  # white: no corner in that cell
        w, h = obs.image_size(v)
        im = ax.imshow(shown, extent=(0, w, h, 0), cmap="viridis", vmin=1, vmax=vmax, interpolation="nearest")
        ax.set_title(obs.grid.name(v), fontsize=9)
        ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=axes, label="corners per cell", shrink=0.8)
    fig.supxlabel("x (px)")
    fig.supylabel("y (px)")
    return save(fig, stem)


def residual_figure(obs: Any, residuals_px: np.ndarray, stem: str | os.PathLike) -> list[Path]:
    """Per view: mean residual magnitude per image cell (colour) and the mean residual vector (arrows)."""
    nx, ny = COVERAGE_BINS
    fig, axes = _grid_axes(obs.grid, "")
    maps = []
    sizes = [obs.image_size(v) for v in range(obs.num_views)]  # (width, height) per view, px
    for v, (w, h) in enumerate(sizes):
        m = obs.valid[v] & np.all(np.isfinite(residuals_px[v]), axis=-1)
        px, res = obs.corners_px[v][m], residuals_px[v][m]
        ix = np.clip((px[:, 0] / w * nx).astype(int), 0, nx - 1)
        iy = np.clip((px[:, 1] / h * ny).astype(int), 0, ny - 1)
        n = np.zeros((ny, nx))
        np.add.at(n, (iy, ix), 1)
        mag, dx, dy = (np.zeros((ny, nx)) for _ in range(3))
        np.add.at(mag, (iy, ix), np.linalg.norm(res, axis=1))
        np.add.at(dx, (iy, ix), res[:, 0])
        np.add.at(dy, (iy, ix), res[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            maps.append((mag / n, dx / n, dy / n))
    vmax = max([float(np.nanmax(m[0])) for m in maps if np.isfinite(m[0]).any()] + [1e-3])
    longest = max([float(np.nanmax(np.hypot(m[1], m[2]))) for m in maps if np.isfinite(m[1]).any()] + [0.0])
    scale = _nice_scale(longest, ARROW_CELL_SHARE * min(min(w / nx, h / ny) for w, h in sizes))
    fig.suptitle(f"residuals over the image: mean |r| per cell (colour), mean residual (arrows, drawn {scale:g}x)")
    for v in range(obs.num_views):
        r, c = obs.grid.position(v)
        ax = axes[r, c]
        mag, dx, dy = maps[v]
        w, h = sizes[v]
        gx, gy = np.meshgrid((np.arange(nx) + 0.5) * w / nx, (np.arange(ny) + 0.5) * h / ny)
        im = ax.imshow(mag, extent=(0, w, h, 0), cmap="magma", vmin=0, vmax=vmax, interpolation="nearest")
        ok = np.isfinite(dx)
        ax.quiver(gx[ok], gy[ok], dx[ok] * scale, dy[ok] * scale, color="cyan",
                  angles="xy", scale_units="xy", scale=1, width=0.006)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_title(obs.grid.name(v), fontsize=9)
        ax.tick_params(labelsize=7)
    fig.colorbar(im, ax=axes, label="mean |residual| (px)", shrink=0.8)
    fig.supxlabel("x (px)")
    fig.supylabel("y (px)")
    return save(fig, stem)


def frame_rms_figure(obs: Any, residuals_px: np.ndarray, frame_rms_px: np.ndarray, outlier_frames: Sequence[int],
                     stem: str | os.PathLike) -> list[Path]:
    """RMS reprojection error per frame (bars; outlier frames in red) and per view and frame (markers)."""
    n_frames = len(frame_rms_px)
    fig, ax = plt.subplots(figsize=(max(7.0, 0.22 * n_frames + 3), 4.0), constrained_layout=True)
    frames = np.arange(n_frames)
    colours = ["tab:red" if f in set(outlier_frames) else "0.7" for f in frames]
    ax.bar(frames, frame_rms_px, color=colours, label="all views (red: outlier frame)")
    sq = np.where(obs.valid, np.sum(residuals_px**2, axis=-1), np.nan)
    with np.errstate(invalid="ignore"):
        per_view = np.sqrt(np.nanmean(sq, axis=2))  # (V, F)
    for v in range(obs.num_views):
        st = style(v)
        ax.plot(frames, per_view[v], linestyle="none", marker=st["marker"], color=st["color"], markersize=4,
                markerfacecolor=st["markerfacecolor"], label=obs.grid.name(v))
    ax.set_xlabel("frame")
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("per-frame RMS")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False, fontsize=8,
              ncol=1 + obs.num_views // 16)
    return save(fig, stem)


def grid_deviation_figure(calib: Any, stem: str | os.PathLike) -> list[Path]:
    """Each view's centre minus its ideal grid position (rectified frame): in-plane arrows on the grid, depth and
    rotation deviation as labels."""
    from lfgraph.rectification.rectify import compute_rectification

    rect = compute_rectification(calib)
    dev = np.asarray(rect.deviation_mm)
    rot = np.asarray(rect.rotation_deviation_deg)
    grid = calib.grid
    fig, ax = plt.subplots(figsize=(1.8 * grid.cols + 2.5, 1.6 * grid.rows + 1.5), constrained_layout=True)
    pos = np.array([grid.position(v)[::-1] for v in range(calib.num_views)], dtype=float)  # (col, row)
    ax.scatter(pos[:, 0], pos[:, 1], marker="+", color="0.4", s=80, label="ideal grid position")
    cells_per_mm = _nice_scale(float(np.max(np.linalg.norm(dev[:, :2], axis=1))), ARROW_CELL_SHARE / 2)
    ax.quiver(pos[:, 0], pos[:, 1], dev[:, 0] * cells_per_mm, dev[:, 1] * cells_per_mm,
              angles="xy", scale_units="xy", scale=1, color="tab:blue", width=0.006,
              label=f"in-plane deviation (1 grid cell = {1 / cells_per_mm:.3g} mm)")
    for v in range(calib.num_views):
        ax.annotate(f"{grid.name(v)}\n|d| {np.linalg.norm(dev[v]):.2f} mm\nz {dev[v, 2]:+.2f} mm\n"
                    f"rot {rot[v]:.3f}°", pos[v], xytext=(4, 6), textcoords="offset points", fontsize=7)
    ax.set_xlim(-0.6, grid.cols - 0.2)
    ax.set_ylim(grid.rows - 0.3, -0.7)
    ax.set_xticks(range(grid.cols))
    ax.set_yticks(range(grid.rows))
    ax.set_xlabel("column (x right)")
    ax.set_ylabel("row (y down)")
    ax.set_title("grid deviation: view centre minus ideal grid position")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False, fontsize=8)
    return save(fig, stem)


def calibration_report_figures(calib: Any, obs: Any, report: Any, out_dir: str | os.PathLike) -> list[Path]:
    """`lfgraph calibrate --plots DIR`: coverage, residuals over the image, per-frame RMS and grid deviation.

    Args:
        calib: the calibration; obs: its observations; report: its `CalibrationReport`.
        out_dir: folder (created if missing).

    Returns:
        the files written (PNG and PDF of each figure).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = coverage_figure(obs, out / "coverage")
    if report.residuals_px is not None:
        written += residual_figure(obs, report.residuals_px, out / "residuals")
        written += frame_rms_figure(obs, report.residuals_px, np.asarray(report.frame_rms_px),
                                    report.outlier_frames, out / "frame_rms")
    if calib.num_views > 1:
        written += grid_deviation_figure(calib, out / "grid_deviation")
    return written
