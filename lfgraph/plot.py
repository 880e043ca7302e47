"""Minimal line plots as PNG drawn with OpenCV (no plotting dependency): axes, ticks, labelled curves."""

from __future__ import annotations

import os
from collections.abc import Sequence

import cv2
import numpy as np

from lfgraph.io_utils import atomic_path

WIDTH_PX, HEIGHT_PX = 900, 600
MARGIN = (90, 40, 30, 70)  # left, right, top, bottom
COLOURS = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (127, 127, 127)]  # BGR, matplotlib's tab10


def _ticks(lo: float, hi: float, n: int = 6) -> np.ndarray:
    span = hi - lo if hi > lo else 1.0
    step = 10 ** np.floor(np.log10(span / n))
    for mult in (1, 2, 5, 10):
        if span / (step * mult) <= n:
            step *= mult
            break
    return np.arange(np.ceil(lo / step) * step, hi + 1e-12, step)


def line_plot(path: str | os.PathLike, series: Sequence[tuple[str, np.ndarray, np.ndarray]], title: str,
              xlabel: str, ylabel: str) -> None:
    """Write a PNG with one polyline per (label, x, y) series; NaN/inf points are skipped. Atomic."""
    img = np.full((HEIGHT_PX, WIDTH_PX, 3), 255, np.uint8)
    left, right, top, bottom = MARGIN
    xs = np.concatenate([np.asarray(x, float) for _, x, _ in series])
    ys = np.concatenate([np.asarray(y, float) for _, _, y in series])
    ok = np.isfinite(xs) & np.isfinite(ys)
    if not ok.any():
        raise ValueError(f"nothing finite to plot for {title!r}")
    x0, x1 = float(xs[ok].min()), float(xs[ok].max())
    y0, y1 = min(0.0, float(ys[ok].min())), float(ys[ok].max())
    x1 = x1 if x1 > x0 else x0 + 1.0
    y1 = y1 * 1.05 if y1 > y0 else y0 + 1.0
    pw, ph = WIDTH_PX - left - right, HEIGHT_PX - top - bottom

    def to_px(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.stack([left + (x - x0) / (x1 - x0) * pw, top + ph - (y - y0) / (y1 - y0) * ph], axis=-1)

    font = cv2.FONT_HERSHEY_SIMPLEX
    for t in _ticks(x0, x1):
        px = int(round(to_px(np.array([t]), np.array([y0]))[0, 0]))
        cv2.line(img, (px, top), (px, top + ph), (235, 235, 235), 1)
        cv2.putText(img, f"{t:g}", (px - 15, top + ph + 20), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for t in _ticks(y0, y1):
        py = int(round(to_px(np.array([x0]), np.array([t]))[0, 1]))
        cv2.line(img, (left, py), (left + pw, py), (235, 235, 235), 1)
        cv2.putText(img, f"{t:.3g}", (5, py + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
    for k, (label, x, y) in enumerate(series):
        colour = COLOURS[k % len(COLOURS)]
        x, y = np.asarray(x, float), np.asarray(y, float)
        good = np.isfinite(x) & np.isfinite(y)
        pts = to_px(x[good], y[good]).round().astype(np.int32)
        if len(pts) > 1:
            cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, tuple(int(c) for c in p), 3, colour, -1, cv2.LINE_AA)
        cv2.line(img, (left + 15, top + 20 + 22 * k), (left + 45, top + 20 + 22 * k), colour, 2)
        cv2.putText(img, label, (left + 52, top + 25 + 22 * k), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, title, (left + 170, top - 10 if top > 20 else 15), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, (left + pw // 2 - 60, HEIGHT_PX - 20), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (5, top - 10 if top > 20 else 15), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise OSError(f"could not write {path}")
