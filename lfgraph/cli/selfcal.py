"""``lfgraph calibrate-scene``: calibrate an array without a target, from design values and scene frames."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lfgraph.cli.args import (
    EXIT_OK,
    LAYOUT_CHOICES,
    UsageError,
    check_output_file,
    grid_size,
    positive_float,
    positive_int,
)


def _focal_px(args: argparse.Namespace, image_width_px: int) -> float:
    from lfgraph.selfcal import focal_from_lens

    if args.focal_px is not None:
        if args.focal_mm is not None or args.sensor_width_mm is not None:
            raise UsageError("give either --focal-px or --focal-mm with --sensor-width-mm, not both")
        return args.focal_px
    if args.focal_mm is None or args.sensor_width_mm is None:
        raise UsageError("the nominal focal length is needed: --focal-px F, or --focal-mm F --sensor-width-mm W")
    return focal_from_lens(args.focal_mm, args.sensor_width_mm, image_width_px)


def _pins(args: argparse.Namespace, grid, inputs: list) -> tuple:
    """The pins the flags ask for (`lfgraph.selfcal.pins`), every file read and checked before the work starts.

    Raises:
        UsageError: a pin's flags that do not go together; PinError / CaptureError: a pin's file (named)."""
    from lfgraph.selfcal import BoardPin, DistancePin, ViewPin

    pins = []
    board_flags = [f for f, v in (("--board", args.board), ("--square-mm", args.square_mm)) if v is not None]
    if args.pin_board is None and (board_flags or args.marker_mm is not None):
        raise UsageError(f"{', '.join(board_flags or ['--marker-mm'])} describe(s) the board of --pin-board DIR")
    if args.pin_board is not None:
        from lfgraph.detect.board import BoardSpec
        from lfgraph.detect.detections import detect_capture
        from lfgraph.io.capture import open_capture

        if args.board is None or args.square_mm is None:
            raise UsageError("--pin-board needs the board: --board COLSxROWS --square-mm S (and --marker-mm for a "
                             "ChArUco board)")
        try:
            board = BoardSpec.parse(args.board, args.square_mm, args.marker_mm)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        capture = open_capture(args.pin_board, grid, args.layout)
        inputs += [p for f in range(len(capture)) for p in capture.paths(f)]
        obs, _ = detect_capture(capture, board, progress=not args.quiet, cache=False)  # writes nothing
        pins.append(BoardPin.from_observations(obs, args.pin_corner_sigma_px, name=f"board {args.pin_board}"))
    if args.pin_distance is not None:
        inputs.append(args.pin_distance)
        pins.append(DistancePin.load(args.pin_distance, grid))
    for spec in args.pin_view or ():
        view, sep, path = spec.partition("=")
        if not sep or not view or not path:
            raise UsageError(f"--pin-view takes VIEW=calibration.json (e.g. r00_c00=calib.json), got {spec!r}")
        inputs.append(Path(path))
        pins.append(ViewPin.from_file(view, Path(path), grid))
    return tuple(pins)


def cmd_calibrate_scene(args: argparse.Namespace) -> int:
    """``lfgraph calibrate-scene``: calibrate from design values and textured scene frames (no target), rectify unless
    ``--no-rectify``, save, and print the report (``--report-json``: also as JSON); returns 0."""
    import dataclasses
    import json

    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    from lfgraph.core.files import write_text_atomic
    from lfgraph.core.grid import ViewGrid
    from lfgraph.io.capture import open_capture
    from lfgraph.rectification.rectify import rectify
    from lfgraph.refinement.trackers import DEFAULT_TRACKER, tracker_by_name
    from lfgraph.selfcal import Design, SelfCalConfig, calibrate_scene

    rows, cols = args.grid
    reference = args.reference or 0
    if not 0 <= reference < rows * cols:
        raise UsageError(f"--reference {reference} is not a view of the {rows}x{cols} grid")
    try:
        config = SelfCalConfig(tracks_per_frame=args.tracks_per_frame, max_frames=args.max_frames,
                               focal_tolerance=args.focal_tolerance_pct / 100.0,
                               principal_tolerance_px=args.principal_tolerance_px,
                               rotation_tolerance_deg=args.rotation_tolerance_deg,
                               position_tolerance_mm=args.position_tolerance_mm,
                               tracker=None if args.tracker == DEFAULT_TRACKER else tracker_by_name(args.tracker))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if (args.lens == "unified") != (args.xi is not None):
        raise UsageError("--xi goes with --lens unified, and --lens unified needs --xi (its lens's xi: the maker's "
                         "value, or `lfgraph calibrate --lens unified` on a board)")
    capture = open_capture(args.input, ViewGrid(rows, cols, reference), args.layout)
    capture.require_one_size("calibrate-scene")
    inputs = [p for f in range(len(capture)) for p in capture.paths(f)]
    pins = _pins(args, capture.grid, inputs)
    if pins:
        config = dataclasses.replace(config, pins=pins)
    check_output_file(args.output, inputs=inputs)
    if args.report_json is not None:
        check_output_file(args.report_json, inputs=[*inputs, args.output])
    try:
        design = Design(rows, cols, args.pitch_mm, _focal_px(args, capture.image_size_px[0]), capture.image_size_px,
                        reference, lens=args.lens, xi=args.xi or 0.0)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    n = len(capture) if args.max_frames is None else min(len(capture), args.max_frames)
    print(f"{args.input}: {capture.layout} layout, {len(capture)} frames of {rows}x{cols} views "
          f"{design.image_size_px[0]}x{design.image_size_px[1]} px; design: pitch {design.pitch_mm:g} mm, focal "
          f"{design.focal_px:.1f} px, {design.lens} lenses{f' (xi {design.xi:g})' if design.xi else ''}")
    bar = tqdm(capture.frames(limit=n), total=n, desc="tracking", unit="frame", disable=args.quiet)
    with logging_redirect_tqdm():
        calib, report = calibrate_scene(bar, design, config)
    if not args.no_rectify:
        from lfgraph.cli.tables import rectification_text
        from lfgraph.rectification.rectify import stored_rectification

        calib = rectify(calib, args.crop)
        print(rectification_text(calib, stored_rectification(calib)))
    calib.save(args.output)
    print(report.text())
    print("scale comes from the design pitch (scene frames carry none)")
    if args.report_json is not None:
        write_text_atomic(args.report_json, json.dumps(report.as_dict(), indent=1) + "\n")
        print(f"wrote {args.report_json}")
    print(f"wrote {args.output}" + ("" if args.no_rectify else " (with its rectification; `lfgraph rectify` uses it)"))
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    """Add this module's commands to the ``lfgraph`` subparsers."""
    from lfgraph.selfcal.defaults import (
        FOCAL_TOLERANCE,
        POSITION_TOLERANCE_MM,
        PRINCIPAL_TOLERANCE_PX,
        ROTATION_TOLERANCE_DEG,
        TRACKS_PER_FRAME,
    )

    p = sub.add_parser("calibrate-scene", help="calibrate without a target: from design values and ordinary "
                                               "textured scene frames")
    p.add_argument("input", type=Path, help="capture folder of textured scenes (many frames, varied depths)")
    p.add_argument("--grid", type=grid_size, required=True, help="views as ROWSxCOLS, e.g. 5x5")
    p.add_argument("--pitch-mm", type=positive_float, required=True, help="nominal distance between adjacent views")
    p.add_argument("--focal-px", type=positive_float, help="nominal focal length in pixels")
    p.add_argument("--focal-mm", type=positive_float, help="nominal lens focal length (with --sensor-width-mm)")
    p.add_argument("--sensor-width-mm", type=positive_float, help="sensor width (with --focal-mm)")
    p.add_argument("--lens", choices=("radtan", "fisheye", "unified"), default="radtan",
                   help="every view's lens model (default radtan; fisheye: Kannala-Brandt, its k1, k2 fitted from 0; "
                        "unified: Mei's, its k1, k2 fitted from 0 at the --xi given)")
    p.add_argument("--xi", type=float, default=None,
                   help="a unified lens's xi (required with --lens unified: the maker's value or a board "
                        "calibration's; scene frames barely tell it from the focal length, so it is held)")
    p.add_argument("-o", "--output", type=Path, required=True, help="calibration.json to write")
    p.add_argument("--reference", type=int, help="reference view (row-major index; default 0)")
    p.add_argument("--layout", choices=LAYOUT_CHOICES, default="auto", help="input layout (default: detect)")
    p.add_argument("--max-frames", type=positive_int, help="use at most this many frames")
    p.add_argument("--tracker", default="chain", metavar="NAME",
                   help="what tracks features: chain (default: KLT along the grid) or sift (SIFT between grid "
                        "neighbours, for steps too wide for KLT)")
    p.add_argument("--tracks-per-frame", type=positive_int, default=TRACKS_PER_FRAME,
                   help=f"tracks kept per frame, spread over the image (default {TRACKS_PER_FRAME})")
    p.add_argument("--focal-tolerance-pct", type=positive_float, default=100 * FOCAL_TOLERANCE,
                   help=f"1-sigma spread of the focal lengths about the design, %% (default {100 * FOCAL_TOLERANCE:g})")
    p.add_argument("--principal-tolerance-px", type=positive_float, default=PRINCIPAL_TOLERANCE_PX,
                   help=f"1-sigma spread of the principal points (default {PRINCIPAL_TOLERANCE_PX:g} px)")
    p.add_argument("--rotation-tolerance-deg", type=positive_float, default=ROTATION_TOLERANCE_DEG,
                   help=f"1-sigma spread of the view rotations (default {ROTATION_TOLERANCE_DEG:g} deg)")
    p.add_argument("--position-tolerance-mm", type=positive_float, default=POSITION_TOLERANCE_MM,
                   help=f"1-sigma spread of the view positions (default {POSITION_TOLERANCE_MM:g} mm)")
    pin = p.add_argument_group("pins: what fixes the common zoom (absolute focal length)")
    pin.add_argument("--pin-board", type=Path, metavar="DIR",
                     help="a capture folder of a few frames of a known board (even one, seen by one view or more; "
                          "held tilted; better two, tilted about perpendicular axes), with --board and --square-mm")
    pin.add_argument("--board", help="the pin board: checkerboard inner corners COLSxROWS (e.g. 11x8) or "
                                     "charuco:SQUARESXxSQUARESY:DICT_NAME (with --marker-mm)")
    pin.add_argument("--square-mm", type=positive_float, help="the pin board's square side in millimetres")
    pin.add_argument("--marker-mm", type=positive_float, help="the pin board's ChArUco marker side in millimetres")
    pin.add_argument("--pin-corner-sigma-px", type=positive_float,
                     help="the pin board's corner noise (default: measured from its corners)")
    pin.add_argument("--pin-distance", type=Path, metavar="FILE",
                     help='a known distance between two points marked in one view of one frame: JSON {"view": '
                          '"r00_c00", "frame": 0, "points_px": [[u, v], [u, v]], "distance_m": 1.0, "sigma_m": '
                          '0.001} (points at different depths)')
    pin.add_argument("--pin-view", action="append", metavar="VIEW=FILE",
                     help="one view's intrinsics from a factory or earlier calibration.json, with its stored sigmas, "
                          "e.g. r00_c00=calib.json")
    p.add_argument("--no-rectify", action="store_true", help="do not compute and store the rectification")
    p.add_argument("--crop", choices=("valid", "full"), default="valid", help="rectification crop (default valid)")
    p.add_argument("--report-json", type=Path, help="also write the report (coverage, sigmas, modes, verdict)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_calibrate_scene)
