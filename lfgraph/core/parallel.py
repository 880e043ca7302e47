"""Run independent tasks on a local process pool with a progress bar, or on this process's threads (`thread_map`);
numpy's and OpenCV's BLAS on one thread (`one_blas_thread`).

The pool's processes never outlive this one and never see Ctrl-C:

- Workers start from multiprocessing's fork server (see `FORKSERVER_PRELOAD`). The server is started with SIGINT
  blocked and, on Linux, armed to be killed by the kernel when this process dies (``prctl(PR_SET_PDEATHSIG)``, set in
  the server itself while it loads its modules); every worker is armed the same way against the server. So a
  ``kill -9`` of this process takes the server and the workers with it at once, even while this process is an
  unreaped zombie (the caller of a killed run, e.g. ``Popen.communicate`` after ``kill()``, waits for the end of the
  run's pipes, which the workers hold). Watching the parent with ``os.kill(pid, 0)`` does not see that death: the
  signal reaches a zombie.
- Workers ignore SIGINT from birth (the server ignores it before it forks them): a Ctrl-C reaches the whole process
  group, and a worker interrupted halfway through unpickling its task printed a traceback. This process stops them:
  on any exception inside `process_pool` (Ctrl-C, a failed task, a reader gone from a pipe) the tasks not started
  are cancelled and the workers are killed and waited for, so nothing they write can appear after the caller's
  clean-up, and none is left.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import multiprocessing.forkserver
import os
import queue
import select
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from contextlib import contextmanager
from functools import lru_cache
from typing import Any

import threadpoolctl

from lfgraph.core.files import deferred_interrupt, process_alive

PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_POLL_S = 1.0  # the fallback watcher checks for an orphaned worker this often
WORKER_STOP_S = 10.0  # a killed worker is waited for this long at most (it takes milliseconds)


def _libc_prctl():
    """libc's ``prctl``, looked up at import: a forked worker must not call ``dlopen``/``dlsym``, whose loader lock
    another thread may have held at the fork (the worker would wait for it forever)."""
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
# imports the heavy modules once, so a worker starts in milliseconds. This module comes first: importing it in the
# server arms the server (`_arm_fork_server`) before the long imports.
FORKSERVER_PRELOAD = ["lfgraph.core.parallel", "numpy", "cv2", "gtsam", "lfgraph.detect.detections",
                      "lfgraph.datasets.checkerboard"]


def _fork_server_alive_fd() -> int | None:
    """When this module is being imported by multiprocessing's fork server (loading its preload modules): the read
    end of the server's "alive" pipe, whose only writer is the parent until the server forks a worker; else None."""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_code.co_name == "main" and frame.f_globals.get("__name__") == "multiprocessing.forkserver":
            return frame.f_locals.get("alive_r")
        frame = frame.f_back
    return None


def _arm_fork_server(alive_r: int) -> None:
    """In the fork server, before it forks any worker: ignore SIGINT (the server records the handler it finds and
    gives it to every worker it forks; the parent started the server with SIGINT blocked, so a Ctrl-C that came
    meanwhile is pending, and ignoring it discards it), and die with the parent. A parent that died before the
    signal was armed has closed the alive pipe (it never writes to it): then the server ends at once, instead of
    after loading the other modules (a second, during which it held the caller's pipes)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)
    if select.select([alive_r], [], [], 0)[0]:
        os._exit(0)


if (_alive_r := _fork_server_alive_fd()) is not None:
    _arm_fork_server(_alive_r)


def _exited(pid: int) -> bool:
    """Whether process ``pid`` has ended — a zombie (dead, not yet reaped by its parent) counts as ended, unlike with
    ``os.kill(pid, 0)``."""
    if not os.path.exists("/proc/self/stat"):  # no procfs: the portable check
        return not process_alive(pid)
    try:
        with open(f"/proc/{pid}/stat") as fh:
            state = fh.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return True
    return state in ("Z", "X")


def _watch_parent(parent_pid: int) -> None:
    while True:
        time.sleep(PARENT_POLL_S)
        if _exited(parent_pid):
            os._exit(1)


def die_with_parent(server_pid: int, parent_pid: int) -> None:
    """Pool initializer: end this worker when the process that made the pool dies, even by ``kill -9`` (which runs no
    clean-up there). Linux: the kernel kills the worker when the fork server that forked it ends
    (``prctl(PR_SET_PDEATHSIG)``), checked right after arming against the server's pid (a server that ended
    before cannot signal); the server itself ends with the parent (`_arm_fork_server`). A daemon thread also watches
    the parent (a fork server lfgraph did not start is not armed)."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)
        if os.getppid() != server_pid:
            os._exit(1)
    if _exited(parent_pid):
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()


# ------------------------------------------------------------------------------ starting the fork server
_keeper: queue.SimpleQueue | None = None
_keeper_lock = threading.Lock()


def _start_fork_server() -> int:
    """Start the fork server if it is not running (SIGINT blocked meanwhile, as multiprocessing's resource tracker is
    started: the server and the tracker inherit the blocked mask and ignore SIGINT before they unblock it); its pid."""
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()  # first: starting it unblocks SIGINT in the calling thread
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    return multiprocessing.forkserver._forkserver._forkserver_pid


def _keep(requests: queue.SimpleQueue) -> None:
    while True:
        done, box = requests.get()
        try:
            box.append(_start_fork_server())
        except BaseException as exc:  # noqa: BLE001  handed to the thread that asked
            box.append(exc)
        done.set()


def fork_server_pid() -> int:
    """The running fork server's pid, starting it when needed from a daemon thread that lives as long as this process:
    the kernel's parent-death signal fires when the *thread* that started a process ends, and a pool made in a
    short-lived thread must not lose its server when that thread ends."""
    global _keeper
    with _keeper_lock:
        if _keeper is None:
            _keeper = queue.SimpleQueue()
            threading.Thread(target=_keep, args=(_keeper,), name="lfgraph-fork-server", daemon=True).start()
        done, box = threading.Event(), []
        _keeper.put((done, box))
        done.wait()
    if isinstance(box[0], BaseException):
        raise box[0]
    return box[0]


# ------------------------------------------------------------------------------ the pool
def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Cancel the tasks not started and kill the workers (they ignore Ctrl-C; their work is lost with the run),
    waiting until they are gone."""
    workers = list((getattr(pool, "_processes", None) or {}).values())  # Python < 3.14 has no public handle
    pool.shutdown(wait=False, cancel_futures=True)
    for w in workers:
        try:
            w.kill()
        except (OSError, ValueError):  # already gone, or closed
            pass
    for w in workers:
        try:
            w.join(WORKER_STOP_S)
        except (OSError, ValueError, AssertionError):
            pass
    pool.shutdown(wait=True)


@contextmanager
def process_pool(max_workers: int) -> Iterator[ProcessPoolExecutor]:
    """A process pool whose workers never outlive this process, for a ``with`` block: on success it is shut down
    (pending tasks finish), on any exception its workers are killed (`_stop_workers`) before the exception goes on."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(FORKSERVER_PRELOAD)
    server = fork_server_pid()
    pool = ProcessPoolExecutor(max_workers=max_workers, mp_context=ctx, initializer=die_with_parent,
                               initargs=(server, os.getpid()))
    try:
        yield pool
    except BaseException:
        _stop_workers(pool)
        raise
    pool.shutdown(wait=True)


def run_tasks(fn: Callable[[Any], Any], tasks: Sequence[Any], jobs: int | None, desc: str, unit: str,
              progress: bool = True) -> list[Any]:
    """``[fn(t) for t in tasks]`` in order, on ``jobs`` processes (default: all cores; 1 = in this process)."""
    from tqdm import tqdm

    jobs = max(1, jobs or os.cpu_count() or 1)
    results = []
    with tqdm(total=len(tasks), desc=desc, unit=unit, disable=not progress) as bar:
        if jobs == 1:
            for t in tasks:
                results.append(fn(t))
                bar.update()
        else:
            with process_pool(min(jobs, len(tasks) or 1)) as pool:
                with deferred_interrupt():
                    results_in_order = pool.map(fn, tasks)
                for r in results_in_order:
                    results.append(r)
                    bar.update()
    return results


# ------------------------------------------------------------------------------ BLAS threads
_BLAS_LOCK = threading.Lock()
_blas_users = 0
_blas_limit = None


@lru_cache(maxsize=1)
def _blas_controller() -> threadpoolctl.ThreadpoolController:
    """threadpoolctl's view of the BLAS libraries loaded in this process (numpy's and OpenCV's OpenBLAS; scanned
    once)."""
    return threadpoolctl.ThreadpoolController()


def _free_blas_control() -> None:
    """Let the calling thread change the limit: threadpoolctl (3.8) lets one thread at a time size a process-wide
    OpenBLAS pool (the first to set a limit, until it clears itself or ends) and silently ignores the others. A limit
    set by one thread and restored by another (the last of several users to finish) was left in place: measured,
    BLAS stayed on one thread for the rest of the process once two threads had used this guard at once. Called
    under the lock, before and after each change (no thread keeps control between changes)."""
    clear = getattr(getattr(threadpoolctl, "OpenBLASController", None), "clear_controlling_thread", None)
    if clear is not None:
        clear(force=True)


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """numpy's and OpenCV's BLAS on one thread (threadpoolctl): the reduced systems of the engine are small (C <= a
    few hundred), and on a shared machine their threads mostly spin (measured: a 286-landmark solve took 87 ms of
    CPU with 2 threads, 3.5 ms with one). The limit is process-wide: counted across threads, set by the first user to
    start and restored by the last to finish, whichever threads they are; BLAS calls of other threads in the meantime
    run on one thread (`thread_map` holds it for its calls, so none of them sees it change)."""
    global _blas_users, _blas_limit
    with _BLAS_LOCK:
        if _blas_users == 0:
            _free_blas_control()
            _blas_limit = _blas_controller().limit(limits=1, user_api="blas")
            _free_blas_control()
        _blas_users += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _blas_users -= 1
            if _blas_users == 0 and _blas_limit is not None:
                _free_blas_control()
                _blas_limit.restore_original_limits()
                _free_blas_control()
                _blas_limit = None


def thread_map(fn: Callable[[Any], Any], items: Sequence[Any], workers: int | None = None) -> list[Any]:
    """``[fn(i) for i in items]`` in order, on up to ``workers`` threads of this process (default: the cores it may
    run on): for calls that release the GIL (OpenCV's, numpy's on large arrays). The first item's exception, in
    order, is raised, after every call has ended.

    BLAS runs on one thread throughout (`one_blas_thread`, entered before the first call and left after the last,
    on one worker too): the calls already share the cores, and OpenBLAS's results differ in the last bits between
    one thread and two (OpenCV's fisheye fit of hetero1's 2048x2048 view, measured), so a limit changed by one call
    (an engine solve) while another is inside BLAS made that call's result depend on timing."""
    workers = min(len(items), workers or len(os.sched_getaffinity(0)))
    with one_blas_thread():
        if workers <= 1:
            return [fn(i) for i in items]
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="lfgraph") as pool:
            futures = [pool.submit(fn, i) for i in items]
        return [f.result() for f in futures]
