"""Atomic file output: nothing half-written ever appears under the final name."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


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
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``, on error removed.

    The temporary file keeps ``path``'s suffix so writers that choose the format by extension (``cv2.imwrite``)
    still work. Only a regular file (or nothing) is ever replaced (`check_replaceable`, before and after the work).
    """
    final = Path(path)
    check_replaceable(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".tmp{final.suffix}", dir=final.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        check_replaceable(final)
        # mkstemp creates 0600; give the file the mode a plain open() would (or keep the replaced file's)
        os.chmod(tmp_path, final.stat().st_mode & 0o777 if final.exists() else default_mode(0o666))
        os.replace(tmp_path, final)
    finally:
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
