"""The ``export`` and ``import`` subcommands: calibrations to and from other tools' formats (see lfgraph.interop).

    lfgraph export CALIB.json --to opencv-yaml|kalibr|colmap|json -o PATH
    lfgraph import PATH --from opencv-yaml|kalibr|colmap|json|middlebury|hci [--grid RxC [--reference N]] \
        -o CALIB.json

Each command's ``func(args)`` returns 0 and raises ValueError or OSError on bad input; the main CLI turns those
into exit code 1 and a message. The output is checked before the input is read: an output that is (or, for a scene
or model folder, is a file of) the input is refused with exit code 1, as is an output folder that cannot be written;
a missing output folder, or an output that is a folder where a file is written (a file where ``colmap`` writes a
folder), is a usage error (exit code 2), as for ``calibrate`` and ``refine``. No folder is created.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lfgraph.cli.args import EXIT_OK, UsageError, check_output_file, grid_size, view_index

# the built-in formats as lfgraph.interop registers them (tests/interop/test_interop.py checks they agree), for the
# help text without importing the format modules (OpenCV, GTSAM) to build the parser; a name is checked against the
# registry when the command runs (`lfgraph.interop.register_format` adds one)
EXPORT_FORMATS = ("opencv-yaml", "kalibr", "colmap", "json", "ros", "mrcal")
IMPORT_FORMATS = ("opencv-yaml", "kalibr", "colmap", "json", "middlebury", "hci")


def cmd_export(args: argparse.Namespace) -> int:
    """Read ``args.calibration`` (calibration.json) and write it as ``args.fmt`` to ``args.output``."""
    from lfgraph.core.calibration import Calibration
    from lfgraph.interop import export_calibration, export_formats, file_format

    if args.fmt not in export_formats():
        raise UsageError(f"--to: unknown export format {args.fmt!r}; valid formats: {', '.join(export_formats())}")
    check_output_file(args.output, (args.calibration,), is_folder=not file_format(args.fmt).one_file)
    calib = Calibration.load(args.calibration)
    out = export_calibration(calib, args.fmt, args.output)
    print(f"wrote {out} ({args.fmt}: {calib.num_views} views, {calib.grid} grid, reference view "
          f"{calib.grid.reference})")
    return EXIT_OK


def cmd_import(args: argparse.Namespace) -> int:
    """Read ``args.source`` as ``args.fmt`` and save it as calibration.json at ``args.output``.

    Raises:
        ValueError: ``--reference`` without ``--grid``, a reference outside the grid, an output that is the input
            or cannot be written (`check_output`), or a bad input file (the message names the file and the key).
    """
    from lfgraph.core.grid import ViewGrid
    from lfgraph.interop import import_calibration, import_formats, input_paths

    if args.fmt not in import_formats():
        raise UsageError(f"--from: unknown import format {args.fmt!r}; valid formats: {', '.join(import_formats())}")
    check_output_file(args.output, input_paths(args.source, args.fmt), is_folder=False)
    grid: Any = args.grid
    if args.reference is not None:
        if grid is None:
            raise ValueError("--reference needs --grid RxC")
        grid = ViewGrid(grid[0], grid[1], args.reference)
    calib = import_calibration(args.source, args.fmt, grid)
    calib.save(args.output)
    print(f"wrote {args.output} from {args.source} ({args.fmt}: {calib.num_views} views, {calib.grid} grid, "
          f"reference view {calib.grid.reference}" + (", with its rectification" if calib.rectification else "") + ")")
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    """Add the ``export`` and ``import`` subcommands to ``sub = parser.add_subparsers(...)``."""
    ex = sub.add_parser("export", help="write a calibration in another tool's format",
                        description="Write calibration.json as OpenCV FileStorage YAML (with the stereo names M1 D1 "
                                    "M2 D2 R T R1 R2 P1 P2 Q for a pair), a Kalibr camchain.yaml, a COLMAP text "
                                    "model folder (cameras.txt + rigs.txt + rig_config.json), lfgraph JSON, a folder "
                                    "of ROS camera_info YAML files or a folder of mrcal .cameramodel files (one per "
                                    "view).")
    ex.add_argument("calibration", type=Path, metavar="CALIB.json", help="lfgraph calibration.json")
    ex.add_argument("--to", dest="fmt", required=True, metavar="FORMAT",
                    help=f"output format: {', '.join(EXPORT_FORMATS)} (or one registered from Python)")
    ex.add_argument("-o", "--output", type=Path, required=True, metavar="PATH",
                    help="output file (a folder for colmap, ros and mrcal)")
    ex.set_defaults(func=cmd_export)

    im = sub.add_parser("import", help="read a calibration from another tool's format",
                        description="Read OpenCV FileStorage YAML, a Kalibr camchain.yaml, a COLMAP text model "
                                    "folder, lfgraph JSON, a Middlebury 2014 calib.txt or an HCI 4D light-field "
                                    "parameters.cfg and save it as calibration.json.")
    im.add_argument("source", type=Path, metavar="PATH",
                    help="input file (colmap: the model folder; middlebury, hci: the file or its scene folder)")
    im.add_argument("--from", dest="fmt", required=True, metavar="FORMAT",
                    help=f"input format: {', '.join(IMPORT_FORMATS)} (or one registered from Python)")
    im.add_argument("--grid", type=grid_size, metavar="RxC",
                    help="view grid ROWSxCOLS, views row-major; required for kalibr (and colmap models not written "
                         "by lfgraph), otherwise checked against the file")
    im.add_argument("--reference", type=view_index, metavar="N",
                    help="reference view (row-major index; needs --grid): poses are re-expressed relative to it. "
                         "Default: the file's reference (view 0 for kalibr, middlebury and hci)")
    im.add_argument("-o", "--output", type=Path, required=True, metavar="CALIB.json", help="calibration.json to write")
    im.set_defaults(func=cmd_import)
