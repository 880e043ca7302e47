"""``lfgraph calibrate``, ``evaluate`` and ``info``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from lfgraph.cli.args import (
    EXIT_OK,
    LAYOUT_CHOICES,
    UsageError,
    add_rerun_args,
    check_rerun,
    cli_observer,
    grid_size,
    jobs_default,
    positive_float,
    positive_int,
    reports_to_stderr,
    rerun_session,
)


def cmd_info(args: argparse.Namespace) -> int:
    from lfgraph.calibration import Calibration
    from lfgraph.report import calibration_summary

    calib = Calibration.load(args.calibration)
    print(f"{args.calibration}:")
    print(calibration_summary(calib))
    return EXIT_OK




def cmd_calibrate(args: argparse.Namespace) -> int:
    with reports_to_stderr(args):
        return _calibrate(args)


def _calibrate(args: argparse.Namespace) -> int:
    from lfgraph.board import BoardSpec
    from lfgraph.capture import open_capture
    from lfgraph.detections import detect_capture
    from lfgraph.grid import ViewGrid
    from lfgraph.pattern import CalibrateConfig, calibrate
    from lfgraph.report import calibration_report_text

    try:
        board = BoardSpec.parse(args.board, args.square_mm)
        grid = ViewGrid(args.grid[0], args.grid[1], args.reference)
        config = CalibrateConfig(method=args.method, init=args.init, focal_px=args.focal_px, pitch_mm=args.pitch_mm,
                                 robust=args.robust, tangential=args.tangential, board_sigma_mm=args.board_sigma_mm)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.output.exists() and args.output.is_dir():
        raise UsageError(f"-o {args.output} is a folder; give the calibration file's path")
    if not args.output.parent.exists():
        raise UsageError(f"-o {args.output}: folder {args.output.parent} does not exist")
    if args.plots is not None and args.plots.exists() and not args.plots.is_dir():
        raise UsageError(f"--plots {args.plots} is a file; give a folder for the report figures")
    logging = check_rerun(args)
    start = time.perf_counter()
    capture = open_capture(args.input, grid, args.layout)
    print(f"{args.input}: {capture.layout} layout, {len(capture)} frames x {grid.num_views} views of "
          f"{capture.image_size_px[0]}x{capture.image_size_px[1]} px; board {board}")
    obs, cached = detect_capture(capture, board, jobs=args.jobs, progress=not args.quiet, cache=not args.no_cache)
    seen = obs.seen
    print(f"detections{' (from the cache)' if cached else ''}: board found in {seen.sum()} of {seen.size} images "
          f"({time.perf_counter() - start:.1f} s)")
    with rerun_session(args, grid, logging, "calibrate") as logger:
        if logger is not None:
            logger.set_measurements(obs.num_observations)
        calib, report = calibrate(obs, config, cli_observer(logger))
        calib.save(args.output)
        if logger is not None:
            logger.calibration_result(calib, obs, report, capture.load_frame)
    print(calibration_report_text(calib, report))
    if args.plots is not None:
        from lfgraph.viz.figures import calibration_report_figures

        for path in calibration_report_figures(calib, obs, report, args.plots):
            print(f"figure: {path}")
    print(f"wrote {args.output} ({time.perf_counter() - start:.1f} s in all)")
    return EXIT_OK


def cmd_evaluate(args: argparse.Namespace) -> int:
    import json

    from lfgraph.calibration import Calibration
    from lfgraph.evaluation import evaluate_calibration
    from lfgraph.report import evaluation_table

    estimate = Calibration.load(args.calibration)
    truth = Calibration.load(args.truth)
    errors = evaluate_calibration(estimate, truth)
    if args.json:
        print(json.dumps(errors.summary(), indent=1))
    else:
        print(f"{args.calibration} against {args.truth}:")
        print(evaluation_table(errors, "truth"))
    return EXIT_OK




def add_parsers(sub: Any) -> None:
    """Add this module's commands to the ``lfgraph`` subparsers."""
    info = sub.add_parser("info", help="print a calibration file as a table")
    info.add_argument("calibration", type=Path)
    info.set_defaults(func=cmd_info)

    cal = sub.add_parser("calibrate", help="calibrate the array from checkerboard captures (paper Section 3.2)")
    cal.add_argument("input", type=Path, help="capture folder (see --layout)")
    cal.add_argument("--grid", type=grid_size, required=True, help="ROWSxCOLS of the array, e.g. 4x4")
    cal.add_argument("--board", required=True, help="inner corners COLSxROWS (OpenCV patternSize), e.g. 11x8")
    cal.add_argument("--square-mm", type=positive_float, required=True, help="square side in millimetres")
    cal.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto", help="input layout (default: detect)")
    cal.add_argument("--reference", type=int, default=0, help="reference view, row-major index (default 0)")
    cal.add_argument("--method", choices=("joint", "paper"), default="joint",
                     help="joint: one GTSAM graph over all views and frames (default); paper: per-view Zhang + "
                          "relative PnP/LM as in the paper")
    cal.add_argument("--init", choices=("paper", "design"), default="paper",
                     help="start of the joint route: the paper route (default) or design values")
    cal.add_argument("--robust", default="none",
                     help="robust kernel NAME[:THRESHOLD_PX]: none, huber:1.0, cauchy:..., tukey:..., gm, dcs, ...")
    cal.add_argument("--tangential", action="store_true", help="estimate p1, p2 (held at 0 by default)")
    cal.add_argument("--board-sigma-mm", type=positive_float,
                     help="board flatness tolerance: estimate the corners' positions within it (default: rigid)")
    cal.add_argument("--focal-px", type=positive_float, help="design focal length for --init design")
    cal.add_argument("--pitch-mm", type=positive_float, help="design grid pitch for --init design")
    cal.add_argument("--jobs", type=positive_int, default=jobs_default(), help="detection processes")
    cal.add_argument("--no-cache", action="store_true", help="re-detect even if INPUT/.lfgraph-detections.npz is valid")
    cal.add_argument("--quiet", action="store_true", help="no progress bar")
    cal.add_argument("-o", "--output", type=Path, required=True, help="calibration.json to write")
    cal.add_argument("--plots", type=Path, metavar="DIR",
                     help="write the calibration report figures (coverage, residuals, per-frame RMS, grid deviation) "
                          "as PNG and PDF to this folder")
    add_rerun_args(cal)
    cal.set_defaults(func=cmd_calibrate)

    ev = sub.add_parser("evaluate", help="compare a calibration with ground truth (e.g. a synthetic truth.json)")
    ev.add_argument("calibration", type=Path)
    ev.add_argument("--truth", type=Path, required=True, help="ground-truth calibration.json")
    ev.add_argument("--json", action="store_true", help="print the RMS errors as JSON")
    ev.set_defaults(func=cmd_evaluate)
