"""``lfgraph study shake|calibration`` and ``lfgraph depth-error``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lfgraph.cli.args import (
    EXIT_OK,
    UsageError,
    add_rerun_args,
    check_output_file,
    check_rerun,
    check_side_outputs,
    floats,
    ints,
    jobs_default,
    json_text,
    non_negative,
    positive_float,
    positive_int,
    reports_to_stderr,
    rerun_session,
)

MAX_STUDY_SIGMA_PX = 10.0  # corner noise of a calibration study
PLOT_DEPTHS = 100  # depths sampled for the --plot curve (the table has --steps)


def cmd_depth_error(args: argparse.Namespace) -> int:
    """``lfgraph depth-error``: the depth error (m) a reprojection error (px) causes over a range of depths, as a table
    or JSON, and with ``--plot`` as a PNG and PDF figure; returns 0."""

    import numpy as np

    from lfgraph.cli.tables import format_table
    from lfgraph.judge.depth import depth_error_m

    near, far = args.range_m
    if not 0 < near <= far:
        raise UsageError(f"--range-m needs 0 < NEAR <= FAR, got {near} {far}")
    if args.plot is not None:  # the figure goes to PLOT.png and PLOT.pdf: both follow -o's rule, before any work
        for sfx in FIGURE_SUFFIXES:
            check_output_file(args.plot.with_suffix(sfx), flag="--plot")
    depths = np.linspace(near, far, args.steps)
    errors = depth_error_m(args.focal_px, args.baseline_m, args.error_px, depths)
    if args.json:
        print(json_text({"focal_px": args.focal_px, "baseline_m": args.baseline_m, "error_px": args.error_px,
                          "depth_m": depths.tolist(),
                          "depth_error_m": [None if not np.isfinite(e) else float(e) for e in errors]}))
    else:
        print(f"depth error for f = {args.focal_px:g} px, b = {args.baseline_m:g} m, reprojection error "
              f"{args.error_px:g} px (half the spread of the depths at disparity d - E and d + E):")
        print(format_table(["depth_m", "disparity_px", "depth_error_m", "relative_%"],
                           [[f"{z:.3f}", f"{args.focal_px * args.baseline_m / z:.3f}", f"{e:.4f}",
                             f"{100 * e / z:.2f}"] for z, e in zip(depths, errors, strict=True)]))
    if args.plot is not None:
        from lfgraph.viz.figures import depth_error_figure

        plot_depths = np.linspace(near, far, PLOT_DEPTHS)
        written = depth_error_figure(plot_depths, depth_error_m(args.focal_px, args.baseline_m, args.error_px,
                                                                plot_depths),
                                     args.focal_px, args.baseline_m, args.error_px, args.plot.with_suffix(""))
        if not args.json:
            print(f"plot: {', '.join(str(p) for p in written)}")
    return EXIT_OK


FIGURE_SUFFIXES = (".png", ".pdf")  # the study figures beside the CSV


def _study_common(args: argparse.Namespace) -> None:
    from lfgraph.core.executor import parse_executor

    try:
        parse_executor(args.executor)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not args.output.parent.exists():
        raise UsageError(f"-o {args.output}: folder {args.output.parent} does not exist")
    if args.output.suffix.lower() in FIGURE_SUFFIXES:
        raise UsageError(f"-o {args.output}: the study writes a CSV there and its figures beside it as "
                         f"{args.output.stem}.png and .pdf; give the CSV a .csv name")
    figures = [args.output.with_name(args.output.stem + sfx) for sfx in FIGURE_SUFFIXES]
    for path in (args.output, *figures):
        check_output_file(path)
    check_side_outputs(args, outputs=[args.output, *figures])


def cmd_study_shake(args: argparse.Namespace) -> int:
    """``lfgraph study shake``: refine shaken rigs for every shake level, stage schedule and kernel, write the rows and
    plots and print the mean over seeds; returns 0."""
    with reports_to_stderr(args):
        return _study_shake(args)


def _study_shake(args: argparse.Namespace) -> int:
    from lfgraph.apps.study import (
        SHAKE_COLUMNS,
        make_shake_trials,
        run_shake_trial,
        run_study,
        shake_plots,
        shake_row_key,
        shake_trial_rows,
    )
    from lfgraph.datasets.scenes import get_scene
    from lfgraph.factors.noise import RobustKernel
    from lfgraph.refinement import parse_stages

    _study_common(args)
    try:
        get_scene(args.scene)
        stages = [s.strip().replace("+", ",") for s in args.stages.split(",")]  # points+poses: one schedule
        for name in stages:
            parse_stages(name)
        robust = [r.strip() for r in args.robust.split(",")]
        for r in robust:
            RobustKernel.parse(r)
        trials = make_shake_trials(args.scene, args.rot_deg, args.trans_mm, args.trials, args.frames, stages,
                                   robust, args.seed)
        if args.outliers is not None:
            trials = _with_outliers(trials, args.outliers)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    logging = check_rerun(args)
    print(f"shake study on {args.scene}: {len(trials)} trials ({len(trials) // args.trials} levels x {args.trials} "
          f"seeds), {len(trials[0].configs) if trials else 0} configurations each, executor {args.executor}")
    with rerun_session(args, None, logging, "study") as logger:
        rows = run_study(trials, run_shake_trial, args.output, SHAKE_COLUMNS, shake_trial_rows, shake_row_key,
                         args.executor, args.jobs, progress=not args.quiet,
                         on_rows=None if logger is None else logger.study_rows)
    plots = shake_plots(rows, args.output)
    print(_shake_summary(rows, by_config=args.outliers is not None))
    print(f"wrote {args.output} and {', '.join(str(p) for p in plots)}")
    return EXIT_OK


def _with_outliers(trials: list, spec: str) -> list:
    """The trials with every configuration repeated for each share of wrong matches in ``spec`` (``0.05:2-8`` or a
    comma list ``0:2-8,0.05:2-8``; share 0 keeps the plain tracker), labelled ``STAGES / ROBUST / outliers SPEC``.

    Raises:
        ValueError: a spec `OutlierTracker.parse` refuses.
    """
    import dataclasses

    from lfgraph.refinement.tracks import OutlierTracker

    outliers = [OutlierTracker.parse(s.strip()) for s in spec.split(",") if s.strip()]
    if not outliers:
        raise ValueError("--outliers needs at least one SHARE:MIN-MAX")
    configs = tuple((f"{label} / outliers {o}", dataclasses.replace(config, tracker=dataclasses.replace(
        o, inner=config.tracker))) for label, config in trials[0].configs for o in outliers) if trials else ()
    return [dataclasses.replace(t, configs=configs) for t in trials]


def _shake_summary(rows, by_config: bool = False) -> str:
    """The mean over seeds per schedule and kernel (``by_config``: per configuration label, which then names the
    wrong matches too) and shake level."""
    from lfgraph.apps.study import summarise
    from lfgraph.cli.tables import format_table

    metrics = ["transfer_before_px", "transfer_px", "rot_err_deg", "rms_after_px"]
    group = ("config",) if by_config else ("stages", "robust")
    summary = summarise(rows, group, "rot_deg", metrics)
    table = []
    for key, d in sorted(summary.items()):
        for i, x in enumerate(d["rot_deg"]):
            table.append([*key, f"{x:g}", *(f"{d[m][i]:.4f}" for m in metrics)])
    return "mean over seeds:\n" + format_table([*group, "rot_shake_deg", "transfer_before_px", "transfer_after_px",
                                                 "rot_err_deg", "rms_after_px"], table)


def cmd_study_calibration(args: argparse.Namespace) -> int:
    """``lfgraph study calibration``: calibration accuracy against frame count and corner noise, write the rows and
    plots and print the RMS over seeds; returns 0."""
    import numpy as np

    from lfgraph.apps.study import (
        CALIBRATION_COLUMNS,
        CalibrationTrial,
        calibration_plots,
        calibration_row_key,
        calibration_trial_rows,
        run_calibration_trial,
        run_study,
        summarise,
    )
    from lfgraph.cli.tables import format_table
    from lfgraph.datasets.scenes import get_scene

    _study_common(args)
    try:
        named = get_scene(args.scene)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if max(args.frames) > named.checkerboard.frames:
        raise UsageError(f"--frames up to {named.checkerboard.frames} for {args.scene}, got {max(args.frames)}")
    if max(args.sigma_px) > MAX_STUDY_SIGMA_PX:
        raise UsageError(f"--sigma-px up to {MAX_STUDY_SIGMA_PX:g} px (corner noise beyond it hides the board), got "
                         f"{max(args.sigma_px):g}")
    trials = [CalibrationTrial(args.scene, f, s, args.seed + i) for f in args.frames for s in args.sigma_px
              for i in range(args.trials)]
    print(f"calibration study on {args.scene}: {len(trials)} trials, executor {args.executor}")
    rows = run_study(trials, run_calibration_trial, args.output, CALIBRATION_COLUMNS, calibration_trial_rows,
                     calibration_row_key, args.executor, args.jobs, progress=not args.quiet)
    plots = calibration_plots(rows, args.output)
    metrics = ["fx_err_px", "pos_err_mm", "rot_err_deg"]
    sq = [{**r, **{m: float(r[m]) ** 2 for m in metrics}} for r in rows]
    table = []
    for (method, sigma), d in sorted(summarise(sq, ("method", "sigma_px"), "frames", metrics).items()):
        for i, f in enumerate(d["frames"]):
            table.append([method, sigma, int(f), *(f"{np.sqrt(d[m][i]):.4g}" for m in metrics)])
    print("RMS over seeds:")
    print(format_table(["method", "sigma_px", "frames", "fx_err_px", "pos_err_mm", "rot_err_deg"], table))
    print(f"wrote {args.output} and {len(plots)} plots ({plots[0].parent if plots else ''})")
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    """Add this module's commands to the ``lfgraph`` subparsers."""
    de = sub.add_parser("depth-error", help="the depth error a reprojection error causes (paper Section 5.1)")
    de.add_argument("--focal-px", type=positive_float, required=True, help="focal length in pixels")
    de.add_argument("--baseline-m", type=positive_float, required=True, help="baseline in metres")
    de.add_argument("--error-px", type=non_negative, required=True, help="reprojection (disparity) error, px")
    de.add_argument("--range-m", type=positive_float, nargs=2, metavar=("NEAR", "FAR"), default=(0.5, 2.0),
                    help="depth range in metres (default 0.5 2.0)")
    de.add_argument("--steps", type=positive_int, default=7, help="depths in the table (default 7)")
    de.add_argument("--json", action="store_true", help="print JSON instead of a table")
    de.add_argument("--plot", type=Path, help="write the depth-error figure here (PNG, and a PDF beside it)")
    de.set_defaults(func=cmd_depth_error)

    st = sub.add_parser("study", help="studies: the paper's shake experiment, calibration accuracy vs frames")
    st_sub = st.add_subparsers(dest="study_command", required=True)

    def common_study(p: argparse.ArgumentParser, default_scene: str, default_out: str) -> None:
        p.add_argument("--scene", default=default_scene, help=f"named scene (default {default_scene})")
        p.add_argument("--trials", type=positive_int, default=3, help="seeded trials per level (default 3)")
        p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
        p.add_argument("--executor", default="local",
                       help="local (process pool, default), dask-local (a LocalCluster) or dask://HOST:PORT")
        p.add_argument("--jobs", type=positive_int, default=jobs_default(), help="processes / Dask workers")
        p.add_argument("-o", "--output", type=Path, default=Path(default_out),
                       help=f"tidy CSV (default {default_out}); a re-run skips trials already in it")
        p.add_argument("--quiet", action="store_true", help="no progress bar")

    ss = st_sub.add_parser("shake", help="refine shaken rigs (the paper's Fig. avg_synth)")
    common_study(ss, "paper-5x5", "shake_study.csv")
    ss.add_argument("--rot-deg", type=floats, default=[0.0, 0.25, 0.5, 1.0],
                    help="rotation shake levels about each optical axis, deg (default 0,0.25,0.5,1)")
    ss.add_argument("--trans-mm", type=floats, default=[0.0, 1.0, 2.0, 5.0],
                    help="translation shake levels paired with --rot-deg, mm per axis (default 0,1,2,5)")
    ss.add_argument("--frames", type=positive_int, default=1, help="scene frames per trial (default 1)")
    ss.add_argument("--stages", default="paper,default",
                    help="schedules to compare (default paper,default); a schedule of its own joins its stages with "
                         "+, e.g. default,points+poses")
    ss.add_argument("--robust", default="none",
                    help="robust kernels to compare (thresholds in px, or Ksigma), e.g. none,huber,cauchy:0.2")
    ss.add_argument("--outliers", metavar="SHARE:MIN-MAX[,...]",
                    help="wrong matches as a study variable: every configuration with SHARE of the non-reference "
                         "observations moved by MIN-MAX px, e.g. 0:2-8,0.05:2-8 (share 0: none)")
    add_rerun_args(ss)
    ss.set_defaults(func=cmd_study_shake)

    sc2 = st_sub.add_parser("calibration", help="calibration accuracy vs frames and corner noise, three methods")
    common_study(sc2, "paper-4x4", "calibration_study.csv")
    sc2.add_argument("--frames", type=ints, default=[5, 10, 20, 30, 40], help="frame counts (default 5,...,40)")
    sc2.add_argument("--sigma-px", type=floats, default=[0.1, 0.3], help="corner noise levels (default 0.1,0.3)")
    sc2.set_defaults(func=cmd_study_calibration)
