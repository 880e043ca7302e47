"""Plain-text tables for the command line."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lfgraph.calibration import Calibration
from lfgraph.geometry import rotation_angle_deg


def format_table(headers: Sequence[str], rows: Sequence[Sequence[object]], floatfmt: str = ".4g") -> str:
    """Right-aligned text table; floats formatted with ``floatfmt``, None as ``-``."""

    def cell(x: object) -> str:
        if x is None:
            return "-"
        if isinstance(x, float | np.floating):
            return format(float(x), floatfmt)
        return str(x)

    body = [[cell(x) for x in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in body)) if body else len(h) for i, h in enumerate(headers)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in body]
    return "\n".join(lines)


def calibration_table(calib: Calibration) -> str:
    """Per-view intrinsics and pose relative to the reference (position in mm, rotation angle in degrees)."""
    rows = []
    for v in range(calib.num_views):
        intr = calib.intrinsics[v]
        pose = calib.ref_T_view[v]
        pos_mm = 1e3 * pose[:3, 3]
        rows.append([
            v, calib.grid.name(v) + (" *" if v == calib.grid.reference else ""),
            f"{intr.fx:.2f}", f"{intr.fy:.2f}", f"{intr.cx:.2f}", f"{intr.cy:.2f}", f"{intr.k1:+.4f}",
            f"{intr.k2:+.4f}", f"{pos_mm[0]:+.3f}", f"{pos_mm[1]:+.3f}", f"{pos_mm[2]:+.3f}",
            f"{float(rotation_angle_deg(pose[:3, :3])):.4f}",
        ])
    return format_table(
        ["view", "name", "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "x_mm", "y_mm", "z_mm", "rot_deg"], rows)


def calibration_summary(calib: Calibration) -> str:
    w, h = calib.image_size_px
    lines = [
        f"grid {calib.grid} ({calib.num_views} views), reference view {calib.grid.reference} "
        f"({calib.grid.name(calib.grid.reference)}, marked *), image {w}x{h} px",
        "positions and rotation angles are relative to the reference view",
        calibration_table(calib),
    ]
    metrics = {k: v for k, v in (calib.metrics or {}).items() if isinstance(v, int | float) and v is not None}
    if metrics:
        lines.append("metrics: " + ", ".join(f"{k} = {v:.4g}" for k, v in metrics.items()))
    lines.append(f"rectification: {'stored' if calib.rectification else 'none'}")
    return "\n".join(lines)
