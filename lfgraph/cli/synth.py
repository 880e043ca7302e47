"""``lfgraph synth checkerboard|scene``, ``lfgraph demo``: synthetic light fields with ground truth."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from lfgraph.cli.args import EXIT_OK, UsageError, grid_size, image_size, jobs_default, non_negative, positive_int
from lfgraph.core.files import staged_folder


def _synth_rig(args: argparse.Namespace, named):
    """The named scene's rig with the command line's overrides."""
    import dataclasses

    rig = named.rig
    changes = {}
    if args.grid is not None:
        changes.update(rows=args.grid[0], cols=args.grid[1])
    if args.image_size is not None:
        changes["image_size_px"] = args.image_size
    if args.reference is not None:
        changes["reference"] = args.reference
    if changes:
        try:
            rig = dataclasses.replace(rig, **changes)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    return rig


# what a synthetic set holds besides its frame folders (000, 001, ...): --overwrite removes only these
SYNTH_FILES = frozenset({"truth.json", "truth_corners.npz", "original.json", ".lfgraph-detections.npz"})


def _prepare_out(args: argparse.Namespace) -> bool:
    """Refuse, before rendering, an output that exists and is not an empty folder: rendering into an old capture
    kept its other frames and files (a mix of two data sets). ``--overwrite`` lets a folder that holds an earlier
    synthetic set (its ``truth.json`` says so) be replaced once the new one is complete; any other folder is never
    replaced. Returns whether ``args.out`` is such a set to replace."""
    out = Path(args.out)
    if not out.exists():
        return False
    if not out.is_dir():
        raise UsageError(f"{out} is a file; give a folder for the synthetic set")
    if not any(out.iterdir()):
        return False
    if not args.overwrite:
        raise UsageError(f"{out} exists and is not empty; rendering into it would mix two data sets. Choose a new "
                         f"folder, or pass --overwrite to replace it")
    if not (out / "truth.json").is_file():
        raise UsageError(f"{out} holds files that are not a synthetic set (no truth.json); --overwrite only replaces "
                         f"a folder an earlier `lfgraph synth` wrote")
    foreign = sorted(c.name for c in out.iterdir() if not (c.name in SYNTH_FILES or (c.is_dir() and c.name.isdigit())))
    if foreign:
        raise UsageError(f"{out} holds files `lfgraph synth` did not write ({', '.join(foreign[:5])}"
                         f"{', ...' if len(foreign) > 5 else ''}); --overwrite would delete them: move them first")
    return True


def cmd_synth_checkerboard(args: argparse.Namespace) -> int:
    """``lfgraph synth checkerboard``: render a named scene's checkerboard captures (optionally another board or frame
    count) with the ground truth into ``args.out``; returns 0."""
    import dataclasses

    import numpy as np

    from lfgraph.datasets.checkerboard import make_checkerboard_truth, write_checkerboard_dataset
    from lfgraph.datasets.rig import make_rig
    from lfgraph.datasets.scenes import get_scene
    from lfgraph.detect.board import BoardSpec

    named = get_scene(args.scene)
    rig = _synth_rig(args, named)
    cfg = named.checkerboard
    changes = {}
    if args.frames is not None:
        changes["frames"] = args.frames
    if args.board is not None or args.square_mm is not None:
        pattern = args.board or f"{cfg.board.cols}x{cfg.board.rows}"
        square_mm = args.square_mm if args.square_mm is not None else cfg.board.square_m * 1000
        changes["board"] = BoardSpec.parse(pattern, square_mm)
    if changes:
        cfg = dataclasses.replace(cfg, **changes)
    rng = np.random.default_rng(args.seed)
    calib = make_rig(rig, rng)
    truth = make_checkerboard_truth(calib, cfg, rng)
    start = time.perf_counter()
    with staged_folder(args.out, replaceable=_prepare_out(args)) as tmp:  # complete, or not there at all
        write_checkerboard_dataset(tmp, calib, truth, cfg, seed=args.seed, layout=args.layout, jobs=args.jobs,
                                   progress=not args.quiet)
    seconds = time.perf_counter() - start
    seen = truth.board_visible
    print(f"wrote {cfg.frames} frames x {calib.num_views} views ({args.layout}) to {args.out} in {seconds:.1f} s")
    print(f"board {cfg.board}; whole board inside a view in {seen.sum()} of {seen.size} view-frames "
          f"(per view min {seen.sum(axis=1).min()}, max {seen.sum(axis=1).max()})")
    print(f"ground truth: {Path(args.out) / 'truth.json'}, corners: {Path(args.out) / 'truth_corners.npz'}")
    return EXIT_OK


def cmd_synth_scene(args: argparse.Namespace) -> int:
    """``lfgraph synth scene``: render textured scene frames of a named scene's rig, optionally shaken first, with the
    ground truth (and the rig before the shake) into ``args.out``; returns 0."""
    import dataclasses

    from lfgraph.apps.synth import knocked_rig, scene_config
    from lfgraph.datasets.scene import write_scene_dataset
    from lfgraph.datasets.scenes import get_scene

    named = get_scene(args.scene)
    named = dataclasses.replace(named, rig=_synth_rig(args, named))
    cfg = scene_config(named, args.keyboard)  # the library's own (lfgraph.apps.synth.scene_capture renders the same)
    frames = args.frames if args.frames is not None else named.frames
    original, truth = knocked_rig(named, args.shake_rot_deg, args.shake_trans_mm, args.shake_axis, args.seed)
    shaken = truth is not original
    start = time.perf_counter()
    with staged_folder(args.out, replaceable=_prepare_out(args)) as tmp:  # complete, or not there at all
        write_scene_dataset(tmp, truth, cfg, frames=frames, seed=args.seed, layout=args.layout, jobs=args.jobs,
                            progress=not args.quiet, original=original if shaken else None)
    seconds = time.perf_counter() - start
    print(f"wrote {frames} frames x {truth.num_views} views ({args.layout}) to {args.out} in {seconds:.1f} s")
    print(f"ground truth: {Path(args.out) / 'truth.json'}"
          + (f"; the rig before the shake: {Path(args.out) / 'original.json'}" if shaken else ""))
    return EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    """``lfgraph demo``: `lfgraph.cli.demo.run_demo` in ``args.out``; returns its exit code."""
    from lfgraph.cli.demo import run_demo

    return run_demo(Path(args.out), jobs=args.jobs, quiet=args.quiet, scene_name=args.scene,
                    with_refinement=not args.no_refine)


def add_parsers(sub: Any) -> None:
    """Add this module's commands to the ``lfgraph`` subparsers."""
    synth = sub.add_parser("synth", help="render synthetic light fields with ground truth")
    synth_sub = synth.add_subparsers(dest="synth_command", required=True)

    def common_synth(p: argparse.ArgumentParser, default_scene: str) -> None:
        p.add_argument("out", type=Path, help="output directory")
        p.add_argument("--scene", default=default_scene, help=f"named scene (default {default_scene})")
        p.add_argument("--grid", type=grid_size, help="ROWSxCOLS, overrides the scene's grid")
        p.add_argument("--image-size", type=image_size, help="WIDTHxHEIGHT per view in pixels")
        p.add_argument("--reference", type=int, help="reference view index (row-major)")
        p.add_argument("--frames", type=positive_int, help="number of frames")
        p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
        p.add_argument("--layout", choices=("folders", "mosaic"), default="folders",
                       help="folders: OUT/<frame>/rRR_cCC.png; mosaic: OUT/<frame>.png with views tiled")
        p.add_argument("--jobs", type=positive_int, default=jobs_default(), help="worker processes")
        p.add_argument("--quiet", action="store_true", help="no progress bar")
        p.add_argument("--overwrite", action="store_true",
                       help="replace OUT when it holds an earlier synthetic set, once the new one is complete "
                            "(refused otherwise)")

    cb = synth_sub.add_parser("checkerboard", help="checkerboard captures rendered as images")
    common_synth(cb, "paper-4x4")
    cb.add_argument("--board", help="inner corners COLSxROWS, OpenCV patternSize (e.g. 11x8)")
    cb.add_argument("--square-mm", type=float, help="square side in millimetres")
    cb.set_defaults(func=cmd_synth_checkerboard)

    sc = synth_sub.add_parser("scene", help="textured scenes (for auto-refinement), optionally after a shake")
    common_synth(sc, "paper-5x5")
    sc.add_argument("--keyboard", action="store_true", help="the hard scene with repetitive texture")
    sc.add_argument("--shake-rot-deg", type=non_negative, default=0.0,
                    help="shake: turn each non-reference view by up to this many degrees")
    sc.add_argument("--shake-trans-mm", type=non_negative, default=0.0,
                    help="shake: move each non-reference view by up to this many millimetres per axis")
    sc.add_argument("--shake-axis", choices=("optical", "any"), default="optical",
                    help="rotation axis of the shake (default: each view's optical axis, as in the paper)")
    sc.set_defaults(func=cmd_synth_scene)


    demo = sub.add_parser("demo", help="the main job on the embedded synthetic default: render, calibrate, "
                                       "evaluate and rectify paper-4x4, then refine a shaken paper-5x5 (~20 s)")
    demo.add_argument("--out", default="out/demo", help="working directory (default out/demo)")
    demo.add_argument("--scene", default="paper-4x4", help="named scene (default paper-4x4; small-2x2 is quick)")
    demo.add_argument("--no-refine", action="store_true", help="skip the refinement part (shaken paper-5x5)")
    demo.add_argument("--jobs", type=positive_int, default=jobs_default(), help="worker processes")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(func=cmd_demo)
