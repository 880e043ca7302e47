"""`thread_map`: results in the items' order, the first failing item's exception (in order) after all have ended."""

import threading
import time

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
