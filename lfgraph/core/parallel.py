"""Run independent tasks on a local process pool with a progress bar."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from tqdm import tqdm

from lfgraph.core.files import process_alive

PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_POLL_S = 1.0  # the portable fallback checks for an orphaned worker this often


def _libc_prctl():
    """libc's ``prctl``, looked up here in the parent: a forked worker must not call ``dlopen``/``dlsym``, whose loader
    lock another thread of the parent may have held at the fork (the worker would wait for it forever)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _libc_prctl()


# Workers start from a fork server, never by forking this process: a fork copies the locks other threads hold at
# that moment (OpenCV's thread pool, measured: a detection worker waited forever on an OpenCV mutex in
# findChessboardCorners after the test process had run OpenCV in parallel), and the server has no such threads. It
# imports the heavy modules once, so a worker starts in milliseconds.
FORKSERVER_PRELOAD = ["numpy", "cv2", "gtsam", "lfgraph.detect.detections", "lfgraph.datasets.checkerboard"]


def _watch_parent(parent_pid: int) -> None:
    while True:
        time.sleep(PARENT_POLL_S)
        if not process_alive(parent_pid):
            os._exit(1)


def die_with_parent(parent_pid: int) -> None:
    """Pool initializer: end this worker when the process that started it dies, even by ``kill -9`` (which runs no
    clean-up in the parent). Linux: the kernel sends SIGKILL when the fork server that started it ends, which it does
    when this process ends (``prctl(PR_SET_PDEATHSIG)``); a daemon thread also watches the process itself."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)
    if not process_alive(parent_pid):  # the parent died before the signal was armed
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()


def process_pool(max_workers: int) -> ProcessPoolExecutor:
    """A process pool whose workers never outlive this process."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(FORKSERVER_PRELOAD)
    return ProcessPoolExecutor(max_workers=max_workers, mp_context=ctx, initializer=die_with_parent,
                               initargs=(os.getpid(),))


def run_tasks(fn: Callable[[Any], Any], tasks: Sequence[Any], jobs: int | None, desc: str, unit: str,
              progress: bool = True) -> list[Any]:
    """``[fn(t) for t in tasks]`` in order, on ``jobs`` processes (default: all cores; 1 = in this process)."""
    jobs = max(1, jobs or os.cpu_count() or 1)
    results = []
    with tqdm(total=len(tasks), desc=desc, unit=unit, disable=not progress) as bar:
        if jobs == 1:
            for t in tasks:
                results.append(fn(t))
                bar.update()
        else:
            with process_pool(min(jobs, len(tasks) or 1)) as pool:
                for r in pool.map(fn, tasks):
                    results.append(r)
                    bar.update()
    return results
