"""Atomic file output: nothing half-written ever appears under the final name, and a command that fails leaves
none of the files it created (`run_outputs`, `staged_folder`)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any


def default_mode(requested: int = 0o666) -> int:
    """``requested`` less the process umask: the mode ``open()`` (0o666) or ``mkdir`` (0o777) would give."""
    mask = os.umask(0)
    os.umask(mask)
    return requested & ~mask


class OutputError(ValueError):
    """An output path that must not be replaced (a device, FIFO, socket, folder or symbolic link)."""


def check_replaceable(path: Path) -> None:
    """Refuse to replace anything but a regular file (or nothing): renaming over ``/dev/null``, a FIFO or a link
    would destroy it (run as root, ``-o /dev/null`` turned the device into a file).

    Raises:
        OutputError: naming the path and what it is.
    """
    if path.is_symlink():
        raise OutputError(f"{path}: is a symbolic link (to {os.readlink(path)}); writing would replace the link, not "
                          f"its target: give the target's own path or a new file")
    if path.exists() and not path.is_file():
        kind = "a folder" if path.is_dir() else "not a regular file (a device, FIFO or socket)"
        raise OutputError(f"{path}: is {kind}; refusing to replace it")


def input_problem(path: Path) -> str | None:
    """What keeps ``path`` from being read as an input file, or None: missing, a folder, or not a regular file (a
    FIFO would block the reader forever, a device would be read without end)."""
    if not path.exists():
        return "does not exist"
    if path.is_dir():
        return "is a folder, expected a file"
    if not path.is_file():
        return "is not a regular file (a FIFO, device or socket); give a file"
    return None


@contextlib.contextmanager
def deferred_interrupt() -> Iterator[None]:
    """Hold a Ctrl-C back until the block ends, then let the SIGINT handler that was in place act on it (in the main
    thread, when Python handles SIGINT; elsewhere a no-op). Around the few steps that create a file and take charge
    of it (an interrupt between ``mkstemp`` and the ``try`` that removes the file on failure left it behind), and
    around the start of a pool's workers (`lfgraph.core.parallel`)."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous in (None, signal.SIG_IGN):
        yield
        return
    caught: list[tuple[int, Any]] = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append((signum, frame)))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and callable(previous):
            previous(*caught[0])
        elif caught:  # the default action: die by the signal
            signal.raise_signal(signal.SIGINT)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``, on error removed.

    The temporary file keeps ``path``'s suffix so writers that choose the format by extension (``cv2.imwrite``)
    still work. Only a regular file (or nothing) is ever replaced (`check_replaceable`, before and after the work).
    """
    final = Path(path)
    check_replaceable(final)
    with deferred_interrupt():  # created and in the charge of the ``try`` below, or not created
        new_folders = _missing_folders(final.parent)
        final.parent.mkdir(parents=True, exist_ok=True)
        _record(*new_folders)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".tmp{final.suffix}", dir=final.parent)
        os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        check_replaceable(final)
        # mkstemp creates 0600; give the file the mode a plain open() would (or keep the replaced file's)
        existed = final.exists()
        os.chmod(tmp_path, final.stat().st_mode & 0o777 if existed else default_mode(0o666))
        with deferred_interrupt():  # a new file in place is recorded (a failure later removes it)
            os.replace(tmp_path, final)
            if not existed:
                _record(final)
    finally:
        with deferred_interrupt():
            if tmp_path.exists():
                tmp_path.unlink()


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 text to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write bytes to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


# ------------------------------------------------------------------ outputs of a run that fails are removed
_ledger: list[Path] | None = None  # paths a command created (files, then folders), while `run_outputs` is active


def _missing_folders(path: Path) -> list[Path]:
    """``path`` and its ancestors that do not exist yet, outermost first."""
    out = []
    for p in (path, *path.parents):
        if p.exists():
            break
        out.append(p)
    return out[::-1]


def _record(*paths: Path) -> None:
    if _ledger is not None:
        _ledger.extend(paths)


def record_created(path: str | os.PathLike) -> None:
    """Tell `run_outputs` that the running command created ``path`` (a file renamed into place by a writer other
    than `atomic_path`, e.g. a rerun recording): a failure later removes it too."""
    _record(Path(path))


@contextlib.contextmanager
def run_outputs() -> Iterator[list[Path]]:
    """Within it, every file `atomic_path` creates (it did not exist before) and every folder it makes for one are
    recorded; if the block fails (any exception, Ctrl-C), they are removed again — newest first, folders only when
    empty — so a failed command leaves none of its outputs (``lfgraph calibrate -o … --save … --plots …`` stopped
    after writing the calibration used to leave it, the recording and half the figures). Files written by other
    processes are not seen: commands that write a folder of them use `staged_folder`."""
    global _ledger
    outer, _ledger = _ledger, []
    try:
        yield _ledger
    except BaseException as exc:
        if getattr(exc, "keep_outputs", False):  # the command's own outputs are complete (a cut --stdout stream)
            raise
        for p in reversed(_ledger):
            with contextlib.suppress(OSError):
                p.rmdir() if p.is_dir() and not p.is_symlink() else p.unlink()
        raise
    finally:
        _ledger = outer


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one owned by another user counts as alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_partials(final: Path) -> None:
    """Remove ``.NAME.PID.*.tmp`` folders that a killed earlier run (its process is gone) left beside ``final``."""
    if not final.parent.is_dir():
        return
    for stale in final.parent.glob(f".{final.name}.*.tmp"):
        pid = stale.name[len(final.name) + 2:].split(".")[0]
        if stale.is_dir() and pid.isdigit() and not process_alive(int(pid)):
            shutil.rmtree(stale, ignore_errors=True)


@contextlib.contextmanager
def staged_folder(final: str | os.PathLike, replaceable: bool = False) -> Iterator[Path]:
    """Yield a temporary folder beside ``final`` (``.NAME.PID.XXXX.tmp``, the user's umask); when the block succeeds
    it takes ``final``'s place, when it fails (any exception, Ctrl-C) it is removed, so ``final`` is either what it
    was or complete (a kill -9 leaves only the hidden temporary, removed by the next run).

    ``final`` must be absent or an empty folder, or — with ``replaceable`` (the caller checked it holds only what
    it may replace) — a folder that is replaced whole on success.
    """
    final = Path(final)
    if final.is_symlink() or (final.exists() and not final.is_dir()):
        raise OutputError(f"{final}: is not a folder; refusing to replace it")
    if final.is_dir() and any(final.iterdir()) and not replaceable:
        raise OutputError(f"{final}: is not empty; give a new or empty folder")
    new_folders = _missing_folders(final.parent)
    final.parent.mkdir(parents=True, exist_ok=True)
    _record(*new_folders)
    remove_stale_partials(final)
    with deferred_interrupt():  # created and in the charge of the ``try`` below, or not created
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.{os.getpid()}.", suffix=".tmp", dir=final.parent))
        tmp.chmod(default_mode(0o777))  # mkdtemp makes it 0700
    try:
        yield tmp
    except BaseException:
        with deferred_interrupt():
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    with deferred_interrupt():  # the swap is not cut halfway
        _replace_folder(tmp, final)


def _replace_folder(tmp: Path, final: Path) -> None:
    """Put the folder ``tmp`` in the place of ``final`` (absent or a folder, removed once the new one is there)."""
    old = None
    if final.is_dir():  # an earlier set the caller may replace: set aside until the new one is in place
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.{os.getpid()}.", suffix=".tmp", dir=final.parent))
        os.rmdir(old)
        final.rename(old)
    try:
        tmp.rename(final)
    except BaseException:
        if old is not None:
            old.rename(final)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
