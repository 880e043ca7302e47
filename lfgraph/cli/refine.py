"""``lfgraph refine``: auto-refinement from ordinary scene captures."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lfgraph.cli.args import (
    EXIT_OK,
    LAYOUT_CHOICES,
    UsageError,
    add_rerun_args,
    check_output_file,
    check_rerun,
    check_side_outputs,
    cli_observer,
    json_text,
    non_negative,
    note,
    positive_float,
    positive_int,
    reports_to_stderr,
    rerun_session,
)


def cmd_refine(args: argparse.Namespace) -> int:
    """``lfgraph refine``: refine a calibration from a textured scene capture and save the result; returns 0 (the
    report goes to stderr when ``--stdout`` carries a rerun recording)."""
    with reports_to_stderr(args):
        return _refine(args)


def _refine(args: argparse.Namespace) -> int:
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    from lfgraph.cli.tables import refinement_text
    from lfgraph.core.calibration import Calibration
    from lfgraph.core.grid_design import free_when_not_parallel
    from lfgraph.factors.noise import describe_noise
    from lfgraph.io.capture import open_capture
    from lfgraph.rectification.checks import check_compatible
    from lfgraph.refinement import RefineConfig, refine, with_reference
    from lfgraph.refinement.config import DriftModel, schedule_name
    from lfgraph.refinement.trackers import DEFAULT_TRACKER, tracker_by_name
    from lfgraph.refinement.tracks import OutlierTracker

    try:
        chosen = None if args.tracker == DEFAULT_TRACKER else tracker_by_name(args.tracker)
        tracker = chosen if args.outliers is None else OutlierTracker.parse(args.outliers, inner=chosen,
                                                                            seed=args.outliers_seed)
        config = RefineConfig(stages=args.stages, robust=args.robust, max_frames=args.max_frames,
                              target_rms_px=args.target_rms, triangulation_filter=args.triangulation_filter,
                              drift=DriftModel.parse(args.drift), priors=not args.free, folds=args.folds,
                              significance_sigma=args.significance, tolerance_px=args.tolerance_px, tracker=tracker)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    check_output_file(args.output, overwritable=[args.calibration], overwrite=args.overwrite)
    logging = check_rerun(args)
    calib, arranged = free_when_not_parallel(Calibration.load(args.calibration))
    if arranged:
        note(args, arranged)
    if args.reference is not None:
        if not 0 <= args.reference < calib.num_views:
            raise UsageError(f"--reference {args.reference} is not a view of the {calib.grid} grid")
        calib = with_reference(calib, args.reference)
    capture = open_capture(args.input, calib.grid, args.layout)
    for text in capture.notes:
        note(args, text)
    check_output_file(args.output, inputs=capture.all_paths())
    check_side_outputs(args, inputs=[args.calibration, *capture.all_paths()], outputs=[args.output])
    check_compatible(calib, capture.grid, capture.image_sizes, str(args.input))
    n = len(capture) if args.max_frames is None else min(len(capture), args.max_frames)
    if not args.json:
        print(f"{args.input}: {capture.layout} layout, {len(capture)} frames; stages {schedule_name(config.stages)}, "
              f"triangulation filter {config.triangulation_filter}, robust {describe_noise(config.noise)}")
        if isinstance(tracker, OutlierTracker):
            print(f"note: wrong matches injected (a study): {100 * tracker.share:g} % of the non-reference "
                  f"observations moved by {tracker.min_px:g}-{tracker.max_px:g} px (seed {tracker.seed})")
    frames = (capture.load_frame(f) for f in range(n))
    bar = tqdm(frames, total=n, desc="refining", unit="frame", disable=args.quiet)
    with rerun_session(args, calib.grid, logging, "refine") as logger, logging_redirect_tqdm():
        # a recording hears the input rig, the stages and the result through the observer (run_start, run_end)
        refined, report = refine(calib, bar, config, cli_observer(logger))
        refined.save(args.output)
    if args.json:
        print(json_text({"calibration": str(args.calibration), "capture": str(args.input), "output": str(args.output),
                          **report.metrics()}, indent=1))
        return EXIT_OK
    print(refinement_text(calib, refined, report))
    counts = report.verdict_counts()
    summary = ", ".join(f"{counts[k]} {k}" for k in ("DRIFTED", "OK", "UNCERTAIN") if k in counts)
    written = sum(v.applied for v in report.verdicts)
    print(f"verdict: {summary}; " + (f"{written} views written (applied: yes above)" if report.accepted else
                                     "nothing was changed (see the reasons above)"))
    print(f"wrote {args.output}")
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    """Add this module's commands to the ``lfgraph`` subparsers."""
    rf = sub.add_parser("refine", help="auto-refine a calibration from ordinary scene captures (paper Section 4)")
    rf.add_argument("calibration", type=Path, help="calibration.json to refine")
    rf.add_argument("input", type=Path, help="capture folder of a textured scene")
    rf.add_argument("-o", "--output", type=Path, required=True, help="refined calibration.json to write")
    rf.add_argument("--stages", default="default",
                    help="schedule: default (points,poses,clean), paper (points,intrinsics,all) or a comma list of "
                         "points, intrinsics, poses, all, clean")
    rf.add_argument("--robust", default="none", help="robust kernel NAME[:THRESHOLD] in px, or NAME:Ksigma in "
                                                     "measurement sigmas; a bare NAME takes its usual constant in "
                                                     "sigmas (none, huber, cauchy:0.2, tukey:0.5, gm, dcs, ...)")
    rf.add_argument("--triangulation-filter", choices=("median", "worst", "none"),
                    help="median: the paper's (default with --stages paper); worst: drop outlying tracks (default)")
    rf.add_argument("--max-frames", type=positive_int, help="use at most this many frames")
    rf.add_argument("--target-rms", type=positive_float,
                    help="stop adding frames once a new frame fits the calibration at this RMS (px)")
    rf.add_argument("--drift", default="",
                    help="drift model: prior sigmas centred on the input, e.g. roll_deg=1,pan_tilt_deg=0.5,"
                         "position_mm=5,focal_px=3,principal_px=3 (those are the defaults)")
    rf.add_argument("--free", action="store_true",
                    help="no drift priors: the paper's free fit (still judged by significance and held-out tracks)")
    rf.add_argument("--folds", type=int, default=3,
                    help="held-out folds (whole frames when there are several; 0: no held-out test; default 3)")
    rf.add_argument("--significance", type=positive_float, default=3.0,
                    help="a view's change must exceed this many posterior sigmas to be applied (default 3)")
    rf.add_argument("--tolerance-px", type=non_negative, default=0.1,
                    help="a view is DRIFTED (and changed) only when its change is significant and moves its transfer "
                         "at infinity by more than this (px, default 0.1; 0: apply every significant change)")
    rf.add_argument("--tracker", default="auto", metavar="NAME",
                    help="what tracks features: auto (default: chain on a grid; on a ring or other free arrangement "
                         "chain or sift by the angle between its views), chain (KLT along the grid or the views' "
                         "links) or sift (SIFT between neighbours, for steps too wide for KLT)")
    rf.add_argument("--outliers", metavar="SHARE:MIN-MAX",
                    help="a study: make SHARE of the non-reference track observations wrong matches, moved by MIN-MAX "
                         "px in random directions (e.g. 0.05:2-8), to see the robust kernels at work")
    rf.add_argument("--outliers-seed", type=int, default=0, help="seed of --outliers (default 0)")
    rf.add_argument("--json", action="store_true", help="print the report (verdicts, sigmas) as JSON")
    rf.add_argument("--reference", type=int, help="re-express the calibration relative to this view first")
    rf.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto", help="input layout (default: detect)")
    rf.add_argument("--overwrite", action="store_true", help="allow -o to be the input calibration (replaced in place)")
    rf.add_argument("--quiet", action="store_true", help="no progress bar")
    add_rerun_args(rf)
    rf.set_defaults(func=cmd_refine)
