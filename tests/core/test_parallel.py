"""`thread_map`: results in the items' order, the first failing item's exception (in order) after all have ended, BLAS
on one thread for its calls; `one_blas_thread` restored whichever thread leaves it last."""

import threading
import time

import cv2  # noqa: F401  (its OpenBLAS is one of the libraries the guard limits)
import numpy as np  # noqa: F401  (and numpy's)
import pytest

from lfgraph.core.parallel import thread_map

SLOW_S = 0.05  # the first item sleeps this long, so later items end first on a second thread


def test_thread_map_keeps_the_order_and_raises_the_first_failure_in_order():
    ended = []

    def work(i):
        if i == 0:
            time.sleep(SLOW_S)
        ended.append(i)
        if i in (1, 3):
            raise ValueError(f"item {i}")
        return i * i, threading.get_ident()

    assert [r[0] for r in thread_map(work, [0, 2, 4], workers=2)] == [0, 4, 16]
    ended.clear()
    with pytest.raises(ValueError, match="item 1"):
        thread_map(work, [0, 1, 2, 3], workers=2)
    assert sorted(ended) == [0, 1, 2, 3]  # every call ended before the exception went on


def test_thread_map_on_one_worker_runs_in_this_thread():
    here = threading.get_ident()
    assert thread_map(lambda i: threading.get_ident(), [1, 2], workers=1) == [here, here]


def _blas_threads() -> list[int]:
    """The BLAS libraries' thread limits, read without a new threadpoolctl controller (making one resets which
    thread may change the limits, and would hide the failure the guard's test looks for)."""
    from lfgraph.core.parallel import _blas_controller

    return [lib.num_threads for lib in _blas_controller().lib_controllers]


def test_one_blas_thread_is_restored_by_whichever_thread_leaves_last():
    """Two threads inside the guard at once, the first to enter leaving first and staying alive: the last to leave
    restores the limit (threadpoolctl ignores a limit change from any thread but the one that set the last one; the
    limit stayed at one thread for the rest of the process)."""
    from lfgraph.core.parallel import one_blas_thread

    before = _blas_threads()
    if max(before, default=1) < 2:
        pytest.skip("BLAS runs on one thread here: nothing to limit")
    a_in, a_out, b_in, a_may_end = (threading.Event() for _ in range(4))
    seen = {}

    def first():
        with one_blas_thread():
            a_in.set()
            b_in.wait()
        a_out.set()
        a_may_end.wait()  # alive while the other leaves

    def second():
        a_in.wait()
        with one_blas_thread():
            b_in.set()
            a_out.wait()
            seen["inside"] = _blas_threads()

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for t in threads:
        t.start()
    threads[1].join()
    seen["after"] = _blas_threads()
    a_may_end.set()
    threads[0].join()
    assert set(seen["inside"]) == {1}
    assert seen["after"] == before


def test_thread_map_calls_run_blas_on_one_thread_and_the_limit_comes_back():
    before = _blas_threads()
    inside = thread_map(lambda i: _blas_threads(), range(4), workers=2)
    assert all(set(s) <= {1} for s in inside)
    assert _blas_threads() == before
