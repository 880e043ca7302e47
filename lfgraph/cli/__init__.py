"""The ``lfgraph`` command. Thin: parse, call the library, print a report.

One module per command group (`synth`, `calibrate`, `rectify`, `refine`, `study`, `interop`), each with an
``add_parsers(sub)``; argument types, exit codes and shared flags in `args`. No command module imports another.

Exit codes: 0 success, 1 bad input (the message names the file and what was wrong), 2 usage error, 3 drift found
(``check``), 4 internal error (an optimiser or library failure, never reported as bad input), 130 interrupted.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from lfgraph.cli import calibrate, fleet, interop, rectify, refine, selfcal, study, synth
from lfgraph.cli.args import EXIT_BAD_INPUT, EXIT_DRIFT, EXIT_INTERNAL, EXIT_OK, EXIT_USAGE, UsageError
from lfgraph.core.files import run_outputs

__all__ = ["EXIT_BAD_INPUT", "EXIT_DRIFT", "EXIT_INTERNAL", "EXIT_OK", "EXIT_USAGE", "build_parser", "main"]

LOG_FORMAT = "%(message)s"


def build_parser() -> argparse.ArgumentParser:
    """The ``lfgraph`` argument parser: the global flags (``--version``, ``-v``, ``-q``) and every module's commands."""
    from lfgraph import __version__

    parser = argparse.ArgumentParser(
        prog="lfgraph",
        description="Calibrate, rectify and auto-refine light-field cameras built as camera arrays.",
        epilog="Exit codes: 0 ok, 1 bad input, 2 usage error, 3 drift found (check), 4 internal error, "
               "130 interrupted.")
    parser.add_argument("--version", action="version", version=f"lfgraph {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="more log output (debug level)")
    verbosity.add_argument("-q", "--log-quiet", dest="log_quiet", action="store_true",
                           help="warnings and errors only on the log, no progress bars")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in (synth, calibrate, selfcal, rectify, refine, fleet, study, interop):
        module.add_parsers(sub)
    return parser


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (test harnesses and tqdm swap it)."""

    def __init__(self) -> None:
        super().__init__()

    @property
    def stream(self):  # noqa: ANN201
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:  # noqa: ANN001
        pass


class _Formatter(logging.Formatter):
    """The message alone; a WARNING (or worse) says so (``warning: ...``)."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return f"warning: {text}" if record.levelno >= logging.WARNING and not text.startswith("warning:") else text


def configure_logging(verbose: bool = False, quiet: bool = False) -> None:
    """The library logs through ``logging.getLogger("lfgraph")``; the CLI shows it on standard error."""
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logger = logging.getLogger("lfgraph")
    logger.setLevel(level)
    if not any(getattr(h, "_lfgraph_cli", False) for h in logger.handlers):
        handler = _StderrHandler()
        handler.setFormatter(_Formatter(LOG_FORMAT))
        handler._lfgraph_cli = True  # type: ignore[attr-defined]
        logger.addHandler(handler)
    logger.propagate = False


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfgraph`` command with ``argv`` (default: ``sys.argv[1:]``) and return its exit code.

    A command's own code (0 when it returns None) on success; bad input (ValueError, OSError) prints ``lfgraph: error:
    ...`` and returns 1, an interrupt returns 130, any other exception prints an internal-error note and returns 4. Bad
    arguments and a `UsageError` exit through argparse (SystemExit, code 2). A failed command leaves none of the files
    it created (`run_outputs`).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.log_quiet and hasattr(args, "quiet"):
        args.quiet = True
    configure_logging(args.verbose, args.log_quiet or getattr(args, "quiet", False))
    try:
        with run_outputs():  # a command that fails leaves none of the files it created
            return int(args.func(args) or 0)
    except UsageError as exc:
        parser.error(str(exc))
        return EXIT_USAGE
    except (ValueError, OSError) as exc:
        print(f"lfgraph: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("lfgraph: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001  anything else is lfgraph's (or a library's) failure, not bad input
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        print(f"lfgraph: internal error ({type(exc).__name__}{': ' + first if first else ''}).\n"
              f"  An optimiser that finds its system indeterminate usually means input it cannot use: a board size "
              f"that does not match the images (--board), a view with too few points, an extreme robust threshold. "
              f"If the input is right, please report this with the command line, `lfgraph --version` and the "
              f"output of `-v`.", file=sys.stderr)
        logging.getLogger("lfgraph").debug("internal error", exc_info=True)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
