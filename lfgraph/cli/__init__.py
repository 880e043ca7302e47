"""The ``lfgraph`` command. Thin: parse, call the library, print a report.

One module per command group (`synth`, `calibrate`, `rectify`, `refine`, `study`, `interop`), each with an
``add_parsers(sub)``, imported when the parser is built (so that the program reaches `main`, and its Ctrl-C
handling, within milliseconds of its start); argument types, exit codes and shared flags in `args`. No command
module imports another.

Exit codes: 0 success, 1 bad input (the message names the file and what was wrong), 2 usage error, 3 drift found
(``check``), 4 internal error (an optimiser or library failure, never reported as bad input), 130 interrupted, 141
the reader of standard output or error went away (``| head``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
from collections.abc import Sequence
from contextlib import AbstractContextManager, nullcontext, redirect_stdout

from lfgraph.cli.args import EXIT_BAD_INPUT, EXIT_DRIFT, EXIT_INTERNAL, EXIT_OK, EXIT_USAGE, UsageError
from lfgraph.core.files import run_outputs

__all__ = ["EXIT_BAD_INPUT", "EXIT_DRIFT", "EXIT_INTERNAL", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_READER_GONE",
           "EXIT_USAGE", "build_parser", "main"]

EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_READER_GONE = 141  # 128 + SIGPIPE: what a shell reports for a program that a closed pipe ended
COMMAND_MODULES = ("synth", "calibrate", "selfcal", "rectify", "refine", "fleet", "study", "interop")
LOG_FORMAT = "%(message)s"


def build_parser() -> argparse.ArgumentParser:
    """The ``lfgraph`` argument parser: the global flags (``--version``, ``-v``, ``-q``) and every module's commands."""
    from lfgraph import __version__

    parser = argparse.ArgumentParser(
        prog="lfgraph",
        description="Calibrate, rectify and auto-refine light-field cameras built as camera arrays.",
        epilog="Exit codes: 0 ok, 1 bad input, 2 usage error, 3 drift found (check), 4 internal error, "
               "130 interrupted, 141 the reader of the output went away.")
    parser.add_argument("--version", action="version", version=f"lfgraph {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="more log output (debug level)")
    verbosity.add_argument("-q", "--log-quiet", dest="log_quiet", action="store_true",
                           help="quiet: nothing on standard output (but --json's document), warnings and errors only "
                                "on standard error, no progress bars; the exit code says how it went")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"lfgraph.cli.{name}").add_parsers(sub)
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


class ReaderGone(BaseException):  # noqa: N818  (like KeyboardInterrupt: an event, not an error)
    """The reader of standard output or error went away (``lfgraph ... | head``): the run ends (exit 141) as a closed
    pipe ends a program, and no more is written. A BaseException, like KeyboardInterrupt, so that handlers of ordinary
    errors (logging's, an ERROR row's) do not swallow it; a failed run's outputs are removed as for any failure."""


class _Guarded:
    """A standard text stream of the program: a write that finds the pipe closed raises `ReaderGone` once; from then
    on the file descriptor is /dev/null (later writes, the interpreter's last flush and C libraries' writes go
    nowhere)."""

    def __init__(self, stream, fd: int) -> None:  # noqa: ANN001
        self._stream, self._fd, self._gone = stream, fd, False

    def write(self, text: str) -> int:
        if not self._gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._reader_gone()
        return len(text)

    def flush(self) -> None:
        if not self._gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._reader_gone()

    def _reader_gone(self) -> None:
        self._gone = True
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, self._fd)
        os.close(null)
        raise ReaderGone

    def __getattr__(self, name: str):  # noqa: ANN204  everything else is the stream's
        return getattr(self._stream, name)


def _open_std_streams() -> None:
    """Standard streams that are closed (``2>&-``, ``>&-``, as under some service managers) become /dev/null, at the
    file-descriptor level too: what is written to them is dropped, and the next file opened cannot become fd 1 or 2
    (where anything written to the closed stream would land in it)."""
    for fd, name, mode in ((0, "stdin", "r"), (1, "stdout", "w"), (2, "stderr", "w")):
        reopened = False
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_RDWR)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
            reopened = True
        if getattr(sys, name) is None:  # Python found the stream closed at its start
            setattr(sys, name, open(fd if reopened else os.devnull, mode, closefd=not reopened))  # noqa: SIM115


_interrupted: list[bool] = []  # the program's Ctrl-C came (`_interrupt_once`)


def _interrupt_once(_signum: int, _frame: object) -> None:
    """SIGINT handler of the program: the first Ctrl-C stops the run; later ones are ignored, so that the clean-up it
    starts (removing partial outputs, stopping workers) is not cut short. It is remembered: whatever exception the
    interrupt turns into on its way out (a C extension interrupted while it loads raises ImportError) ends the run
    as interrupted."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _interrupted.append(True)
    raise KeyboardInterrupt


def _program_streams_and_signals() -> None:
    signal.signal(signal.SIGINT, _interrupt_once)
    _open_std_streams()
    for name, fd in (("stdout", 1), ("stderr", 2)):
        stream = getattr(sys, name)
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(line_buffering=True)  # a reader gone is seen at the next line, not at the exit
        setattr(sys, name, _Guarded(stream, fd))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``lfgraph`` command with ``argv`` and return its exit code.

    Without ``argv`` this is the program (``sys.argv[1:]``; the console script and ``python -m lfgraph``): Ctrl-C at
    any instant ends it with 130 and no traceback (`_interrupt_once`; SIGINT is ignored once `main` returns, so the
    interpreter's exit is not cut short either), closed standard streams are /dev/null (`_open_std_streams`), and a
    reader of the output that goes away ends the run with 141 (`ReaderGone`). With ``argv`` (a caller in Python),
    signals and streams are the caller's. See `run_command` for the rest.
    """
    if argv is not None:
        return run_command(argv)
    try:
        _program_streams_and_signals()
        return run_command(sys.argv[1:])
    except KeyboardInterrupt:  # one that came outside `run_command`'s own handler
        try:
            print("lfgraph: interrupted", file=sys.stderr)
        except ReaderGone:
            pass
        return EXIT_INTERRUPTED
    except ReaderGone:
        return EXIT_READER_GONE
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_command(argv: Sequence[str]) -> int:
    """Run the ``lfgraph`` command with ``argv`` and return its exit code.

    A command's own code (0 when it returns None) on success; bad input (ValueError, OSError) prints ``lfgraph: error:
    ...`` and returns 1, an interrupt returns 130, a reader gone from the output (`ReaderGone`) 141 with no message,
    any other exception prints an internal-error note and returns 4. Bad arguments and a `UsageError` exit through
    argparse (SystemExit, code 2). A failed command leaves none of the files it created (`run_outputs`).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.log_quiet and hasattr(args, "quiet"):
        args.quiet = True
    configure_logging(args.verbose, args.log_quiet or getattr(args, "quiet", False))
    try:
        with run_outputs(), _quiet_stdout(args):  # a command that fails leaves none of the files it created
            code = int(args.func(args) or 0)
            for stream in (sys.stdout, sys.stderr):  # a reader gone before the last line is a failure, said here
                stream.flush()
            return code
    except ReaderGone:
        return EXIT_READER_GONE
    except Exception as exc:  # noqa: BLE001  sorted by `_failure`
        return _failure(exc, parser)
    except KeyboardInterrupt:
        print("lfgraph: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


class _Dropped:
    """A text stream that drops what is written to it (the standard output of a ``-q`` run)."""

    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass


def _quiet_stdout(args: argparse.Namespace) -> AbstractContextManager:
    """Under ``-q`` a command prints nothing on standard output: its report, tables, notes and "wrote ..." lines are
    dropped, so success is the exit code alone (errors and warnings reach standard error as always). What was asked
    for on standard output is kept: ``--json``'s document, and ``--stdout``'s rerun recording (written to the file
    descriptor, not through `sys.stdout`)."""
    if args.log_quiet and not getattr(args, "json", False):
        return redirect_stdout(_Dropped())
    return nullcontext()


def _failure(exc: Exception, parser: argparse.ArgumentParser) -> int:
    """The exit code and message of a command that raised ``exc``."""
    if _interrupted:  # what a Ctrl-C turned into on its way out
        print("lfgraph: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if isinstance(exc, UsageError):
        parser.error(str(exc))
        return EXIT_USAGE
    if isinstance(exc, ValueError | OSError):
        print(f"lfgraph: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    # anything else is lfgraph's (or a library's) failure, not bad input
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
