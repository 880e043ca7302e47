"""Argument types, exit codes and shared flags of the ``lfgraph`` command (no command imports another)."""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Iterable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext, redirect_stdout
from pathlib import Path

from lfgraph.core.files import OutputError, check_replaceable

EXIT_OK, EXIT_BAD_INPUT, EXIT_USAGE, EXIT_DRIFT, EXIT_INTERNAL = 0, 1, 2, 3, 4


class UsageError(ValueError):
    """A command-line value that makes no sense; exit code 2."""


MAX_IMAGE_SIDE_PX = 16384  # larger "images" are typing mistakes (and would exhaust memory before any message)


def image_size(text: str) -> tuple[int, int]:
    """argparse type: ``WIDTHxHEIGHT`` (e.g. ``960x960``) as (width, height) px, each side positive and at most
    `MAX_IMAGE_SIDE_PX`; argparse's type error otherwise."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"image size must be WIDTHxHEIGHT such as 960x960, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"image size must be positive, got {text!r}")
    if max(w, h) > MAX_IMAGE_SIDE_PX:
        raise argparse.ArgumentTypeError(f"image size {w}x{h} is larger than any camera's; each side must be at most "
                                         f"{MAX_IMAGE_SIDE_PX} px")
    return w, h


def image_sizes(text: str) -> tuple[tuple[int, int], dict[str, tuple[int, int]]]:
    """``1920x1080,r00_c02=1280x720``: a default size, then per-view ones (views by name)."""
    default, per_view = None, {}
    for token in (t.strip() for t in text.split(",") if t.strip()):
        if "=" in token:
            name, _, size = token.partition("=")
            per_view[name.strip()] = image_size(size.strip())
        elif default is None:
            default = image_size(token)
        else:
            raise argparse.ArgumentTypeError(f"image size: one default WIDTHxHEIGHT, then VIEW=WIDTHxHEIGHT, got "
                                             f"{text!r}")
    if default is None:
        raise argparse.ArgumentTypeError(f"image size needs a default WIDTHxHEIGHT first, got {text!r}")
    return default, per_view


def grid_size(text: str) -> tuple[int, int]:
    """argparse type: ``ROWSxCOLS`` as (rows, cols) (`lfgraph.core.grid.parse_grid`; its ValueError becomes a type
    error)."""
    from lfgraph.core.grid import parse_grid

    try:
        return parse_grid(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _bounded(text: str, kind: type, minimum: float, inclusive: bool, what: str) -> int | float:
    """``text`` as a finite ``kind`` >= (or >) ``minimum``; argparse's type error naming ``what`` otherwise."""
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(value) or value < minimum or (not inclusive and value == minimum):
        raise argparse.ArgumentTypeError(f"expected {what} {'>=' if inclusive else '>'} {minimum:g}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1."""
    return _bounded(text, int, 1, True, "a whole number")


def view_index(text: str) -> int:
    """argparse type: a view index, a whole number >= 0 (not checked against a grid here)."""
    return _bounded(text, int, 0, True, "a view index (a whole number)")


def non_negative(text: str) -> float:
    """argparse type: a finite number >= 0."""
    return _bounded(text, float, 0.0, True, "a number")


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    return _bounded(text, float, 0.0, False, "a number")


LAYOUT_CHOICES = ("auto", "folders", "mosaic", "hci", "pairs", "middlebury", "views", "video")


RERUN_SINK_FLAGS = ("save", "connect", "serve", "stdout", "url")


def check_rerun(args: argparse.Namespace) -> bool:
    """Validate the rerun flags before any work; True when logging was asked for (rerun is imported only then)."""
    if not any(getattr(args, name, None) for name in RERUN_SINK_FLAGS):
        return False
    if getattr(args, "connect", None) or getattr(args, "url", None):
        check_viewer_listens(getattr(args, "url", None))
    if getattr(args, "save", None):
        from lfgraph.viz.rerun_log import check_save_path

        try:
            check_save_path(args.save)
        except ValueError as exc:
            raise UsageError(f"--save {exc}") from None
    return True


DEFAULT_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"  # rerun's own default for connect_grpc
VIEWER_PROBE_S = 2.0  # a viewer that does not accept a connection within this is not there


def check_viewer_listens(url: str | None) -> None:
    """Refuse ``--connect`` before any work when nothing listens at the viewer's address (rerun would otherwise
    retry for about a minute after the work, then fail).

    Raises:
        UsageError: a URL without host and port, or no viewer there (exit code 2).
    """
    import socket
    from urllib.parse import urlparse

    parsed = urlparse((url or DEFAULT_VIEWER_URL).replace("rerun+", "", 1))
    if not parsed.hostname or not parsed.port:
        raise UsageError(f"--url {url}: expected rerun+http://HOST:PORT/proxy")
    try:
        with socket.create_connection((parsed.hostname, parsed.port), timeout=VIEWER_PROBE_S):
            pass
    except OSError:
        raise UsageError(f"--connect: no rerun viewer listens at {parsed.hostname}:{parsed.port}; start one first "
                         f"(`.venv/bin/rerun`), or record to a file with --save run.rrd") from None


def check_side_outputs(args: argparse.Namespace, inputs: Iterable[Path] = (), outputs: Iterable[Path] = ()) -> None:
    """``--save`` (a rerun recording) and ``--plots`` (a figures folder) follow ``-o``'s rule, before any work: never
    one of the command's inputs (a calibration, an image), never another of its outputs, and ``--plots`` never a
    folder inside the input capture (figures there would make it an ambiguous capture).

    Raises:
        ValueError: the path is an input or lies inside the input folder (exit code 1).
        UsageError: the path is another output of the command, or its folder is missing (exit code 2).
    """
    inputs = [Path(p) for p in inputs]
    outputs = [Path(p) for p in outputs if p is not None]
    save = getattr(args, "save", None)
    if save:
        check_output_file(Path(save), inputs=inputs, flag="--save")
        for out in outputs:
            if _same_file(Path(save), out):
                raise UsageError(f"--save {save}: is also the command's output {out}; give the recording its own path")
    plots = getattr(args, "plots", None)
    if plots is not None:
        plots = Path(plots)
        if plots.exists() and not plots.is_dir():
            raise UsageError(f"--plots {plots} is a file; give a folder for the report figures")
        root = getattr(args, "input", None)
        if root is not None and Path(root).is_dir() and _inside(plots, Path(root)):
            raise ValueError(f"--plots {plots}: lies inside the input {root}; figures there would become part of "
                             f"the capture. Give a folder outside it")
        for p in (*inputs, *outputs, *([Path(save)] if save else [])):
            if _same_file(plots, p):
                raise ValueError(f"--plots {plots}: is {p}, which this command reads or writes")


def _inside(path: Path, root: Path) -> bool:
    """Whether ``path`` is ``root`` or lies below it (resolved)."""
    path, root = path.resolve(), root.resolve()
    return path == root or root in path.parents


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file (resolved, or hard links)."""
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist: they cannot be one file
        return False


def check_output_file(output: Path, inputs: Iterable[Path] = (), overwritable: Iterable[Path] = (),
                      overwrite: bool = False, is_folder: bool = False, flag: str = "-o") -> None:
    """Refuse, before any work, an output that would destroy an input or cannot be written.

    Args:
        output: the output path.
        inputs: every path the command reads (images of the capture, the file being imported, ...).
        overwritable: inputs that may be replaced in place with ``overwrite`` (a calibration refined in place).
        overwrite: the user's explicit ``--overwrite``.
        is_folder: the output is a folder (a COLMAP model), not a file.

    Raises:
        ValueError: the output is one of the inputs, or its folder is not writable (exit code 1).
        UsageError: its folder is missing or not a folder; a file output that is an existing folder, or a folder
            output that is an existing file (exit code 2).
    """
    output = Path(output)
    for source in overwritable:
        if _same_file(output, Path(source)) and not overwrite:
            raise ValueError(f"{flag} {output}: is the input calibration; refusing to overwrite it (pass --overwrite "
                             f"to replace it in place)")
    for source in inputs:
        if _same_file(output, Path(source)):
            raise ValueError(f"{flag} {output}: is the input {source}; refusing to overwrite it, write elsewhere")
    if output.is_symlink() or (output.exists() and not output.is_dir() and not output.is_file()):
        try:
            check_replaceable(output)
        except OutputError as exc:
            raise ValueError(f"{flag} {exc}") from None
    folder = output.parent
    if not folder.exists():
        raise UsageError(f"{flag} {output}: folder {folder} does not exist")
    if not folder.is_dir():
        raise UsageError(f"{flag} {output}: {folder} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK) or (output.is_file() and not os.access(output, os.W_OK)):
        raise ValueError(f"{flag} {output}: not writable")
    if is_folder and output.exists() and not output.is_dir():
        raise UsageError(f"{flag} {output} is a file; this format writes a model folder")
    if not is_folder and output.is_dir():
        raise UsageError(f"{flag} {output} is a folder; give the output file's path")


def check_output_folder(path: Path, input_root: Path | None = None, flag: str = "-o") -> None:
    """Refuse, before any work, an output folder that exists and is not empty, lies inside the input capture, or
    whose parent cannot be written."""
    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise UsageError(f"{flag} {path} exists and is not an empty folder; choose a new output folder")
    if input_root is not None:
        if _inside(path, Path(input_root)):
            raise UsageError(f"{flag} {path} is inside the input {input_root}; choose a folder outside it")
    parent = path.parent if str(path.parent) else Path(".")
    existing = parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise UsageError(f"{flag} {path}: {existing} is not a writable folder")


def _finite(obj: object) -> object:
    """``obj`` with every non-finite float (and numpy scalar) turned into None, containers recursed."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, str | bytes):  # numpy arrays and scalars
        return _finite(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def json_text(obj: object, indent: int | None = 1) -> str:
    """What ``--json`` prints: strict JSON (no NaN or Infinity; such numbers become null)."""
    import json

    return json.dumps(_finite(obj), indent=indent, allow_nan=False)


def jobs_default() -> int:
    """Default ``--jobs``: the number of CPUs (`os.cpu_count`), at least 1."""
    return max(1, os.cpu_count() or 1)


def number_list(text: str, kind: type, minimum: float, what: str) -> list:
    """Comma-separated ``kind`` values (empty items skipped), each finite and >= ``minimum``; argparse's type error
    naming ``what`` otherwise, and when there is none."""
    try:
        values = [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text!r}") from None
    if not values or any(not math.isfinite(v) or v < minimum for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated {what} >= {minimum:g}, got {text!r}")
    return values


def floats(text: str) -> list[float]:
    """argparse type: comma-separated numbers >= 0 (`number_list`)."""
    return number_list(text, float, 0.0, "numbers")


def ints(text: str) -> list[int]:
    """argparse type: comma-separated whole numbers >= 1 (`number_list`)."""
    return number_list(text, int, 1, "whole numbers")


@contextmanager
def rerun_session(args: argparse.Namespace, grid, logging: bool, kind: str = "calibrate") -> Iterator:
    """A `lfgraph.viz.RerunLogger` for a ``with`` block when ``logging``, else None (no recording is created);
    closed at the end, a failure discards a ``--save`` file. ``kind`` (the command) picks the default blueprint."""
    if not logging:
        yield None
        return
    from lfgraph.viz.rerun_log import RerunLogger

    if args.stdout:
        logger = RerunLogger.stdout(grid, kind)
    elif args.serve:
        logger = RerunLogger.serve(grid, kind)
    elif args.connect or args.url:
        logger = RerunLogger.connect(args.url, grid, kind)
    else:
        logger = RerunLogger.to_file(args.save, grid, kind)
    from lfgraph.viz.rerun_log import StdoutClosed

    try:
        with logger:
            yield logger
    except StdoutClosed as exc:  # | head: the recording was cut, the command's own outputs were written
        err = OSError(f"--stdout: {exc}; every other output of the command was written")
        err.keep_outputs = True  # type: ignore[attr-defined]  (`lfgraph.core.files.run_outputs` keeps them)
        raise err from None
    if logger.path is not None:
        print(f"rerun recording: {logger.path} (open it with: rerun {logger.path})")


def note(args: argparse.Namespace, text: str) -> None:
    """A ``note: ...`` line for the user: on standard output, or on standard error when ``--json`` makes standard
    output the JSON document (which then parses as it is)."""
    print(f"note: {text}", file=sys.stderr if getattr(args, "json", False) else sys.stdout)


def reports_to_stderr(args: argparse.Namespace) -> AbstractContextManager:
    """With ``--stdout`` standard output carries the binary recording: print the human-readable report to stderr
    (rerun writes to the file descriptor, not through `sys.stdout`)."""
    return redirect_stdout(sys.stderr) if getattr(args, "stdout", False) else nullcontext()


def cli_observer(logger):
    """What the commands pass as ``observer=``: None (log lines go to `logging`, which the CLI shows on stderr), or
    the open rerun recording, which logs them there too."""
    return logger


def add_rerun_args(p: argparse.ArgumentParser) -> None:
    """rerun's sink flags (the same names as rerun's ``script_add_args``), without importing rerun."""
    group = p.add_argument_group("rerun visual debugging (nothing is logged without --save/--connect/--serve/--stdout)")
    group.add_argument("--save", metavar="FILE.rrd", help="write a rerun recording to this file (atomically)")
    group.add_argument("--connect", action="store_true", help="stream to a running rerun viewer")
    group.add_argument("--url", help="the viewer's gRPC URL for --connect")
    group.add_argument("--serve", action="store_true", help="host a gRPC server and web viewer")
    group.add_argument("--stdout", action="store_true", help="write the recording to standard output (| rerun -)")
