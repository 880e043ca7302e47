"""Plain-text tables for the command line."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lfgraph.core.calibration import Calibration
from lfgraph.core.geometry import rotation_angle_deg


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
    """Per-view lens model, image size, intrinsics (the model's other coefficients in ``more``) and pose relative to
    the reference (position in mm, rotation angle in degrees)."""
    rows = []
    for v in range(calib.num_views):
        intr = calib.intrinsics[v]
        pose = calib.ref_T_view[v]
        pos_mm = 1e3 * pose[:3, 3]
        more = ", ".join(f"{k}={x:+.4g}" for k, x in intr.distortion.items() if k not in ("k1", "k2") and x != 0.0)
        rows.append([
            v, calib.grid.name(v) + (" *" if v == calib.grid.reference else ""), intr.lens,
            "x".join(map(str, calib.image_size(v))),
            f"{intr.fx:.2f}", f"{intr.fy:.2f}", f"{intr.cx:.2f}", f"{intr.cy:.2f}", f"{intr.k1:+.4f}",
            f"{intr.k2:+.4f}", more or "-", f"{pos_mm[0]:+.3f}", f"{pos_mm[1]:+.3f}", f"{pos_mm[2]:+.3f}",
            f"{float(rotation_angle_deg(pose[:3, :3])):.4f}",
        ])
    return format_table(["view", "name", "lens", "size_px", "fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "more",
                         "x_mm", "y_mm", "z_mm", "rot_deg"], rows)


def calibration_summary(calib: Calibration) -> str:
    """Plain text of a calibration: grid, reference and image size, then one row per view (intrinsics, position in mm
    and rotation in degrees relative to the reference)."""
    w, h = calib.image_size_px
    lines = [
        f"grid {calib.grid} ({calib.num_views} views), reference view {calib.grid.reference} "
        f"({calib.grid.name(calib.grid.reference)}, marked *), image {w}x{h} px"
        + (" (views of other sizes: size_px)" if calib.view_image_sizes_px is not None else ""),
        "positions and rotation angles are relative to the reference view",
        calibration_table(calib),
    ]
    metrics = {k: v for k, v in (calib.metrics or {}).items() if isinstance(v, int | float) and v is not None}
    if metrics:
        lines.append("metrics: " + ", ".join(f"{k} = {v:.4g}" for k, v in metrics.items()))
    lines.append(f"rectification: {'stored' if calib.rectification else 'none'}")
    return "\n".join(lines)


def _pm(value: float, sigma: float | None, fmt: str) -> str:
    return format(value, fmt) if sigma is None else f"{format(value, fmt)} ± {sigma:.2g}"


def calibration_report_text(calib: Calibration, report) -> str:  # report: lfgraph.CalibrationReport
    """The ``lfgraph calibrate`` printout: figures of merit, per-view table with 1-sigma, per-frame RMS, warnings."""
    lines = []
    start = {"paper": " (started from the paper route)", "design": " (started from design values)"}
    head = [f"method {report.method}" + start.get(report.init or "", "")]
    if report.e_mono_px is not None:
        head.append(f"E_mono {report.e_mono_px:.4f} px")
    if report.e_pnp_px is not None:
        head.append(f"E_PnP {report.e_pnp_px:.4f} px")
    head.append(f"rig-consistent RMS {report.rig_rms_px:.4f} px")
    if report.noise_sigma_px is not None:
        head.append(f"corner noise estimate {report.noise_sigma_px:.4f} px per coordinate")
    lines.append(", ".join(head))
    if report.optimization is not None:
        opt = report.optimization
        lines.append(f"optimiser: {opt.iterations} Levenberg-Marquardt iterations, graph error "
                     f"{opt.initial_error:.6g} -> {opt.final_error:.6g}, {opt.seconds:.2f} s")
    rows = []
    for v in range(calib.num_views):
        intr = calib.intrinsics[v]
        s = report.sigmas[v] if report.sigmas else {}
        pos = 1e3 * calib.ref_T_view[v][:3, 3]
        pos_sigma = float(np.linalg.norm(s["position_mm"])) if s else None
        rot_sigma = float(np.linalg.norm(s["rotation_deg"])) if s else None
        rows.append([
            calib.grid.name(v) + (" *" if v == calib.grid.reference else ""), int(report.frames_per_view[v]),
            f"{100 * report.coverage[v]:.0f}",
            None if not np.isfinite(report.view_e_mono_px[v]) else float(report.view_e_mono_px[v]),
            None if not np.isfinite(report.view_e_pnp_px[v]) else float(report.view_e_pnp_px[v]),
            float(report.view_rms_px[v]),
            _pm(intr.fx, s.get("fx_px"), ".2f"), _pm(intr.fy, s.get("fy_px"), ".2f"),
            _pm(intr.cx, s.get("cx_px"), ".2f"), _pm(intr.cy, s.get("cy_px"), ".2f"),
            _pm(intr.k1, s.get("k1"), "+.5f"), _pm(intr.k2, s.get("k2"), "+.5f"),
            _pm(float(np.linalg.norm(pos)), pos_sigma, ".3f"),
            f"{pos[0]:+.3f} {pos[1]:+.3f} {pos[2]:+.3f}",
            _pm(float(rotation_angle_deg(calib.ref_T_view[v][:3, :3])), rot_sigma, ".4f"),
        ])
    lines.append("per view (* reference; ± 1-sigma from the factor graph's marginals; positions relative to the "
                 "reference):")
    lines.append(format_table(["view", "frames", "cover_%", "e_mono_px", "e_pnp_px", "rig_rms_px", "fx_px", "fy_px",
                               "cx_px", "cy_px", "k1", "k2", "dist_mm", "x y z_mm", "rot_deg"], rows))
    frame_rms = report.frame_rms_px
    finite = frame_rms[np.isfinite(frame_rms)]
    if finite.size:
        lines.append(f"per-frame RMS: median {np.median(finite):.4f} px, max {np.max(finite):.4f} px "
                     f"(frame {int(np.nanargmax(frame_rms))}); outlier frames: "
                     f"{', '.join(map(str, report.outlier_frames)) or 'none'}")
    for w in report.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def evaluation_table(errors, truth_name: str = "truth") -> str:  # errors: lfgraph.CalibrationErrors
    """Per-view errors against ground truth and their RMS."""
    rows = []
    for v in range(errors.intrinsics.shape[0]):
        e = errors.intrinsics[v]
        rows.append([v, f"{e[0]:+.4f}", f"{e[1]:+.4f}", f"{e[2]:+.4f}", f"{e[3]:+.4f}", f"{e[4]:+.2e}",
                     f"{e[5]:+.2e}", f"{float(np.linalg.norm(errors.position_mm[v])):.4f}",
                     f"{errors.rotation_deg[v]:.5f}"])
    s = errors.summary()
    rows.append(["rms", f"{s['rms_fx_px']:.4f}", f"{s['rms_fy_px']:.4f}", f"{s['rms_cx_px']:.4f}",
                 f"{s['rms_cy_px']:.4f}", f"{s['rms_k1']:.2e}", f"{s['rms_k2']:.2e}", f"{s['rms_position_mm']:.4f}",
                 f"{s['rms_rotation_deg']:.5f}"])
    return f"error = estimate - {truth_name} (poses relative to the reference view)\n" + format_table(
        ["view", "d_fx_px", "d_fy_px", "d_cx_px", "d_cy_px", "d_k1", "d_k2", "d_pos_mm", "d_rot_deg"], rows)


def rectification_text(calib: Calibration, rect) -> str:  # rect: lfgraph.rectification.rectify.Rectification
    """K_r, crop, pitch and the grid-deviation table (how far the real array is from the ideal one)."""
    k = rect.K_r
    lines = [f"rectified views {rect.image_size_px[0]}x{rect.image_size_px[1]} px (crop {rect.crop}, "
             f"rectangle {rect.crop_rect_px} of the {rect.source_size_px[0]}x{rect.source_size_px[1]} frame); "
             f"K_r fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f} px",
             f"grid pitch: {1e3 * rect.pitch_m[0]:.4f} mm along rows, {1e3 * rect.pitch_m[1]:.4f} mm along columns",
             "grid deviation (view centre minus ideal grid position in the rectified frame; rotation away from the "
             "common one):"]
    rows = []
    for v in range(calib.num_views):
        d = rect.deviation_mm[v]
        rows.append([calib.grid.name(v) + (" *" if v == calib.grid.reference else ""), f"{d[0]:+.4f}",
                     f"{d[1]:+.4f}", f"{d[2]:+.4f}", f"{np.linalg.norm(d):.4f}",
                     f"{rect.rotation_deviation_deg[v]:.4f}"])
    lines.append(format_table(["view", "dx_mm", "dy_mm", "dz_mm", "|d|_mm", "rot_deg"], rows))
    return "\n".join(lines)


def alignment_table(named: Sequence[tuple[str, object]]) -> str:
    """Rows of `lfgraph.judge.alignment.Alignment` figures."""

    def px(x: float, why: str) -> str:
        return f"{x:.4f}" if np.isfinite(x) else why

    # a 1x2 rig has no column pairs, and proportionality needs three views on a line
    rows = [[name, px(a.row_px, "-"), px(a.col_px, "- (no vertical pairs)" if a.n_col == 0 else "-"),
             px(a.proportionality_px, "- (needs 3+ views)"), max(a.n_points, a.n_row, a.n_col)]
            for name, a in named]
    return format_table(["", "row_px", "col_px", "proportionality_px", "points"], rows)


def drift_text(calib: Calibration, report, depths_m=()) -> str:  # report: lfgraph.judge.check.DriftReport
    """Plain text of a drift check (`lfgraph.check`): the tracks after each filter, the reprojection RMS per view, the
    alignment at infinity and each view's verdict (``depths_m``: depths at which to state the depth error the
    misalignment causes)."""
    counts = ", ".join(f"{k} {v}" for k, v in report.counts.items())
    lines = [f"{report.frames} frame(s); tracks after each filter: {counts}"]
    if report.frames_dropped:
        lines.append(f"frames {', '.join(map(str, report.frames_dropped))} dropped: most of their tracks disagree "
                     f"with the other frames' (mismatches on a repeated pattern?)")
    lines += [f"reprojection RMS {report.rms_px:.4f} px (not a drift measure: mismatches raise it too); per view:",
              format_table(["view", "rms_px"], [[calib.grid.name(v), float(report.view_rms_px[v])]
                                                for v in range(calib.num_views)]),
              "alignment of the tracks in rectified views (RMS px):" if report.alignment else
              "alignment: not measured (a free arrangement has no rows and columns to rectify)"]
    if report.alignment:
        lines.append(alignment_table([("original views", report.alignment.before),
                                      ("rectified", report.alignment.after),
                                      ("off-grid parallax alone", report.alignment.parallax),
                                      ("rectified, parallax removed", report.alignment.compensated)]))
    if report.verdicts:
        lines.append(verdict_text(report.verdicts, report.sigma_px, *report.heldout_px))
    lines += list(report.notes)
    depths = list(depths_m)
    if depths:
        errors = report.depth_errors(calib, depths)
        source = ("the calibration's stored marginals, taken as independent: an upper bound"
                  if report.input_sigma_inf_px is not None
                  else "the check's posterior (the calibration stored no sigmas)")
        rows = [[calib.grid.name(v), f"{report.sigma_inf_px(v):.3f}",
                 *("inf" if e is None else f"{1e3 * e:.2f}" for e in errors[calib.grid.name(v)])]
                for v in range(calib.num_views) if calib.grid.name(v) in errors]
        lines.append(f"predicted depth error against the reference view (mm, 1 sigma; disparity error = the 1-sigma "
                     f"transfer at infinity from {source}):")
        lines.append(format_table(["view", "sigma_inf_px", *(f"at {d:g} m" for d in depths)], rows))
    return "\n".join(lines)


def refinement_text(before: Calibration, after: Calibration, report) -> str:  # a RefinementReport
    """Per-frame track counts, per-stage RMS and the per-view changes the refinement made."""
    lines = [f"{report.frames_used} frame(s) used ({report.stop_reason}); reprojection RMS of all kept tracks "
             f"{report.rms_before_px:.4f} px with the input calibration -> {report.rms_after_px:.4f} px refined "
             f"({report.seconds:.1f} s: matching {report.seconds_matching:.1f} s, adjustment "
             f"{report.seconds_adjustment:.1f} s); tracks cover {100 * report.coverage:.0f} % of the reference image"]
    keys = list(report.frame_counts[0]) if report.frame_counts else []
    lines.append("tracks after each filter, per frame:")
    lines.append(format_table(["frame", *keys, "rms_px"],
                              [[f, *(c[k] for k in keys), report.frame_rms_before_px[f]]
                               for f, c in enumerate(report.frame_counts)]))
    lines.append("stages (last pass over all frames):")
    lines.append(format_table(["stage", "landmarks", "observations", "rms_before_px", "rms_after_px", "iterations",
                               "seconds"],
                              [[s.name, s.landmarks, s.observations, s.rms_before_px, s.rms_after_px, s.iterations,
                                s.seconds] for s in report.stages]))
    rows = []
    for v in range(after.num_views):
        a, b = after.intrinsics[v], before.intrinsics[v]
        rot = float(rotation_angle_deg(before.ref_T_view[v][:3, :3].T @ after.ref_T_view[v][:3, :3]))
        pos = 1e3 * (after.ref_T_view[v][:3, 3] - before.ref_T_view[v][:3, 3])
        rows.append([after.grid.name(v) + (" *" if v == after.grid.reference else ""), f"{rot:.4f}",
                     f"{np.linalg.norm(pos):.3f}", f"{pos[0]:+.3f} {pos[1]:+.3f} {pos[2]:+.3f}",
                     f"{a.fx - b.fx:+.3f}", f"{a.fy - b.fy:+.3f}", f"{a.cx - b.cx:+.3f}", f"{a.cy - b.cy:+.3f}"])
    lines.append("changes per view (refined minus input; * reference)"
                 + ("" if report.accepted else " — none: the input calibration was kept") + ":")
    lines.append(format_table(["view", "rot_deg", "move_mm", "dx dy dz_mm", "d_fx_px", "d_fy_px", "d_cx_px",
                               "d_cy_px"], rows))
    if report.verdicts:
        lines.append(verdict_text(report.verdicts, report.sigma_px, report.heldout_before_px,
                                  report.heldout_after_px))
    lines += [f"warning: {w}" for w in report.warnings]
    return "\n".join(lines)


def verdict_table(verdicts) -> str:  # a sequence of lfgraph.refinement.assess.ViewVerdict
    """One row per view: the verdict, the proposed change (pan/tilt, roll, position, at infinity) with its sigma."""
    rows = []
    for v in verdicts:
        pt = float(np.hypot(v.rotation_change_deg[0], v.rotation_change_deg[1]))
        s_pt = float(np.hypot(v.sigma_rotation_deg[0], v.sigma_rotation_deg[1]))
        rows.append([v.name, v.verdict, "yes" if v.applied else "no", f"{v.change_sigma:.1f}",
                     f"{v.rotation_change_deg[2]:+.4f} ± {v.sigma_rotation_deg[2]:.4f}", f"{pt:.4f} ± {s_pt:.4f}",
                     f"{np.linalg.norm(v.position_change_mm):.2f} ± {np.linalg.norm(v.sigma_position_mm):.2f}",
                     f"{v.transfer_change_px:.3f}", f"{v.predicted_transfer_px:.3f}",
                     "/".join(f"{x:.2f}" for x in v.sigma_intrinsics_px), v.observations])
    return format_table(["view", "verdict", "applied", "change_sigma", "roll_deg", "pan_tilt_deg", "position_mm",
                         "change_inf_px", "sigma_inf_px", "sigma_fx/fy/cx/cy_px", "observations"], rows)


def verdict_text(verdicts, sigma_px: float, heldout_before_px: float = float("nan"),
                 heldout_after_px: float = float("nan")) -> str:
    """The per-view verdict table, each view's reason, and what an UNCERTAIN view needs."""
    lines = [f"verdict per view (change proposed by the MAP fit ± posterior 1-sigma; change_sigma: its significance; "
             f"change_inf_px / sigma_inf_px: the change and the 1-sigma at infinity; intrinsics a stage held show "
             f"the input's own sigmas, or 0; measurement sigma {sigma_px:.3f} px):", verdict_table(verdicts)]
    if np.isfinite(heldout_before_px):
        lines.append(f"held-out tracks: RMS {heldout_before_px:.4f} px with the input, {heldout_after_px:.4f} px with "
                     f"refits that did not see them")
    for v in verdicts:
        if v.verdict == "REFERENCE":
            continue
        lines.append(f"{v.name} {v.verdict}: {v.reason}" + (f"; needs {'; '.join(v.needs)}" if v.needs else ""))
    return "\n".join(lines)
