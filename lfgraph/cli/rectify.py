"""``lfgraph rectify`` and ``lfgraph check`` (the drift check)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lfgraph.cli.args import (
    EXIT_DRIFT,
    EXIT_OK,
    LAYOUT_CHOICES,
    UsageError,
    add_rerun_args,
    check_output_folder,
    check_rerun,
    check_side_outputs,
    jobs_default,
    json_text,
    non_negative,
    note,
    positive_int,
    reports_to_stderr,
    rerun_session,
)


def _rectify_frame_task(task: tuple) -> int:
    capture, frame, calib_json, crop, out_dir, out_layout = task
    from lfgraph.core.calibration import Calibration
    from lfgraph.io.capture import write_frame
    from lfgraph.rectification.rectify import build_maps, remap_views, stored_rectification

    calib = Calibration.from_dict(calib_json)
    maps = build_maps(calib, stored_rectification(calib))
    images = capture.load_frame(frame, grayscale=False)
    write_frame(out_dir, capture.frame_names[frame], remap_views(images, maps), capture.grid, out_layout)
    return frame


def cmd_rectify(args: argparse.Namespace) -> int:
    """``lfgraph rectify``: rectify every frame of a capture into a new folder, with the calibration and its
    rectification; returns 0 (the report goes to stderr when ``--stdout`` carries a rerun recording)."""
    with reports_to_stderr(args):
        return _rectify(args)


def _rectify(args: argparse.Namespace) -> int:
    from lfgraph.cli.tables import rectification_text
    from lfgraph.core.calibration import Calibration
    from lfgraph.core.files import staged_folder
    from lfgraph.core.parallel import run_tasks
    from lfgraph.io.capture import open_capture
    from lfgraph.rectification.checks import check_compatible
    from lfgraph.rectification.rectify import attach, compute_rectification

    out = args.output
    check_output_folder(out, args.input)
    calib = Calibration.load(args.calibration)
    capture = open_capture(args.input, calib.grid, args.layout)
    for text in capture.notes:
        note(args, text)
    check_compatible(calib, capture.grid, capture.image_sizes, str(args.input))
    logging = check_rerun(args)
    check_side_outputs(args, inputs=[args.calibration, *capture.all_paths()], outputs=[out])
    rect = compute_rectification(calib, args.crop)
    rectified = attach(calib, rect)
    print(rectification_text(calib, rect))
    with rerun_session(args, calib.grid, logging, "rectify") as logger:
        if logger is not None:
            from lfgraph.rectification.rectify import build_maps, remap_views

            logger.rig(calib)
            logger.rectified(calib, remap_views(capture.load_frame(0, grayscale=False), build_maps(calib, rect)))
    out_layout = "folders" if capture.layout in ("pairs", "middlebury", "views", "video") else capture.layout
    with staged_folder(out) as tmp:  # the folder appears complete or not at all
        tasks = [(capture, f, rectified.to_dict(), args.crop, tmp, out_layout) for f in range(len(capture))]
        run_tasks(_rectify_frame_task, tasks, args.jobs, desc="rectifying", unit="frame", progress=not args.quiet)
        rectified.save(tmp / "calibration.json")
    print(f"wrote {len(capture)} rectified frames ({out_layout}) and {out / 'calibration.json'} "
          f"(with the rectification) to {out}")
    return EXIT_OK


def cmd_check(args: argparse.Namespace) -> int:
    """``lfgraph check``: does the calibration still fit a capture? Prints the figures and a verdict (MISMATCH, DRIFTED,
    UNCERTAIN or OK; ``--json``: as JSON).

    Returns 3 (`EXIT_DRIFT`) when a view drifted or the calibration does not fit the camera, else 0. Bad ``--depths``,
    ``--drift`` or ``--tolerance-px`` values are a `UsageError`.
    """
    from lfgraph.cli.tables import drift_text
    from lfgraph.core.calibration import Calibration
    from lfgraph.core.grid_design import free_when_not_parallel
    from lfgraph.core.verdict import Verdict
    from lfgraph.io.capture import open_capture
    from lfgraph.judge.check import check
    from lfgraph.rectification.checks import check_compatible
    from lfgraph.refinement.config import DriftModel, RefineConfig
    from lfgraph.refinement.trackers import DEFAULT_TRACKER, tracker_by_name

    try:
        depths = [float(x) for x in args.depths.split(",") if x.strip()] if args.depths else []
        if any(not d > 0 for d in depths):
            raise ValueError("depths must be positive")
        config = RefineConfig(drift=DriftModel.parse(args.drift), tolerance_px=args.tolerance_px,
                              **({} if args.tracker == DEFAULT_TRACKER else {"tracker": tracker_by_name(args.tracker)}))
    except ValueError as exc:
        raise UsageError(f"{exc}") from None
    calib, arranged = free_when_not_parallel(Calibration.load(args.calibration))
    if arranged:
        note(args, arranged)
    capture = open_capture(args.input, calib.grid, args.layout)
    for text in capture.notes:
        note(args, text)
    check_compatible(calib, capture.grid, capture.image_sizes, str(args.input))
    report = check(calib, capture.frames(args.max_frames), config=config)
    verdict = report.verdict
    if args.json:
        print(json_text({"calibration": str(args.calibration), "capture": str(args.input),
                         "tolerance_px": args.tolerance_px, **report.to_dict(calib),
                         "depth_error_m": {"depths_m": depths, "per_view": report.depth_errors(calib, depths)}},
                        indent=1))
        return EXIT_DRIFT if verdict in (Verdict.DRIFTED, Verdict.MISMATCH) else EXIT_OK
    print(drift_text(calib, report, depths))
    if verdict == Verdict.MISMATCH:
        mismatch = report.intrinsics_mismatch_px
        print(f"MISMATCH: this calibration does not fit this camera: other intrinsics explain the tracks far better "
              f"than any poses ({mismatch[0]:.3f} px RMS with the poses alone, {mismatch[1]:.3f} px with the "
              f"intrinsics free); is it another camera's? Re-calibrate")
        return EXIT_DRIFT
    if verdict == Verdict.DRIFTED:
        names = ", ".join(f"{v.name} ({v.transfer_change_px:.2f} px at infinity, {v.change_sigma:.1f} sigma)"
                          for v in report.drifted())
        print(f"DRIFTED: {names} moved by more than --tolerance-px {args.tolerance_px:g} px; run lfgraph refine "
              "(or re-calibrate)")
        return EXIT_DRIFT
    if verdict == Verdict.UNCERTAIN:
        print("UNCERTAIN: the frames cannot tell whether any view drifted (no view could be confirmed OK); check with "
              "more textured frames, or check that this calibration belongs to this camera")
        return EXIT_OK
    uncertain = [v.name for v in report.verdicts if v.verdict == Verdict.UNCERTAIN]
    print(f"OK: no view drifted by more than --tolerance-px {args.tolerance_px:g} px at infinity"
          + (f" (UNCERTAIN, the frames cannot tell: {', '.join(uncertain)})" if uncertain else ""))
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    """Add this module's commands to the ``lfgraph`` subparsers."""
    rc = sub.add_parser("rectify", help="rectify a capture with a calibration (paper Section 3.3)")
    rc.add_argument("calibration", type=Path, help="calibration.json")
    rc.add_argument("input", type=Path, help="capture folder")
    rc.add_argument("-o", "--output", type=Path, required=True, help="new folder for the rectified capture")
    rc.add_argument("--crop", choices=("valid", "full"), default="valid",
                    help="valid: the rectangle every view fills (default); full: keep the source size")
    rc.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto", help="input layout (default: detect)")
    rc.add_argument("--jobs", type=positive_int, default=jobs_default(), help="worker processes")
    rc.add_argument("--quiet", action="store_true", help="no progress bar")
    add_rerun_args(rc)
    rc.set_defaults(func=cmd_rectify)

    ck = sub.add_parser("check", help="drift check: does the calibration still fit an ordinary capture? "
                                      "(exit 3 when a view drifted or the calibration does not fit the camera; "
                                      "prints UNCERTAIN, exit 0, when no view can be confirmed OK)")
    ck.add_argument("calibration", type=Path, help="calibration.json")
    ck.add_argument("input", type=Path, help="capture folder of any textured scene")
    ck.add_argument("--tolerance-px", "--max-px", dest="tolerance_px", type=non_negative, default=0.1,
                    help="a view fails the check when its change is significant and moves its transfer at infinity "
                         "by more than this (px; default 0.1, as refine's --tolerance-px)")
    ck.add_argument("--depths", default="1,2,5",
                    help="ranges (m, comma list) for the predicted depth error per view (default 1,2,5)")
    ck.add_argument("--drift", default="",
                    help="drift model sigmas, e.g. roll_deg=1,pan_tilt_deg=0.5,position_mm=5 (see RefineConfig)")
    ck.add_argument("--max-frames", type=positive_int, default=3, help="frames to use (default 3)")
    ck.add_argument("--tracker", default="auto", metavar="NAME",
                    help="what tracks features: auto (default: chain on a grid; on a ring or other free arrangement "
                         "chain or sift by the angle between its views), chain (KLT along the grid or the views' "
                         "links) or sift (SIFT between neighbours, for steps too wide for KLT)")
    ck.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto", help="input layout (default: detect)")
    ck.add_argument("--json", action="store_true", help="print the figures and the verdict as JSON")
    ck.set_defaults(func=cmd_check)
