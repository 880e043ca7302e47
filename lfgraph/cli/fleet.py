"""``lfgraph fleet``: check, and refine on drift, every recording of a manifest."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from lfgraph.cli.args import EXIT_OK, UsageError, check_output_file, jobs_default, positive_int


def cmd_fleet(args: argparse.Namespace) -> int:
    """``lfgraph fleet``: check (and on drift refine) every camera of a manifest, write the rows to ``--output`` and
    print the verdict counts and the first errors; returns 0 (a bad ``--executor`` is a `UsageError`)."""
    from lfgraph.apps.fleet import VERDICTS, run_fleet, summarise
    from lfgraph.cli.tables import format_table
    from lfgraph.core.executor import parse_executor

    try:
        parse_executor(args.executor)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    check_output_file(args.output, inputs=[args.manifest])
    rows = run_fleet(args.manifest, args.output, args.executor, args.jobs, progress=not args.quiet)
    counts = summarise(rows)
    print(format_table(["verdict", "cameras"], [[v, counts.get(v, 0)] for v in VERDICTS]))
    errors = [r for r in rows if r["verdict"] == "ERROR"]
    for r in errors[:10]:  # a camera's error: on standard error, which -q keeps
        print(f"ERROR {r['camera']}: {r['error']}", file=sys.stderr)
    print(f"wrote {args.output} ({len(rows)} cameras)")
    return EXIT_OK


def add_parsers(sub: Any) -> None:
    """Add ``fleet`` to the ``lfgraph`` subparsers."""
    fl = sub.add_parser("fleet", help="check (and on drift refine) many recordings listed in a manifest CSV",
                        description="For each row of MANIFEST.csv (columns camera, calibration, capture; paths "
                                    "relative to the manifest; optional layout, max_frames, max_px, tolerance_px): "
                                    "the drift check, "
                                    "and on drift the refinement, written next to the input as NAME.vN.json. One "
                                    "result row per camera with its verdict (OK, DRIFTED, UNCERTAIN, ERROR); a "
                                    "re-run skips cameras already in the results.")
    fl.add_argument("manifest", type=Path, help="manifest CSV")
    fl.add_argument("-o", "--output", type=Path, required=True, help="results CSV (created or resumed)")
    fl.add_argument("--executor", default="local",
                    help="local (process pool, default), dask-local (a LocalCluster) or dask://HOST:PORT")
    fl.add_argument("--jobs", type=positive_int, default=jobs_default(), help="processes / Dask workers")
    fl.add_argument("--quiet", action="store_true", help="no progress bar")
    fl.set_defaults(func=cmd_fleet)
