"""One executor abstraction for independent trials: a local process pool by default, a Dask cluster on request.

``--executor`` values: ``local`` (default; ``--jobs N`` processes, 1 = in this process), ``dask-local`` (starts a
`distributed.LocalCluster` with ``jobs`` single-threaded workers), ``dask://HOST:PORT`` (an existing scheduler).
Dask is an optional extra (``pip install lfgraph[dask]``). Trials must be seeded by their own parameters so that
results do not depend on the executor or on the order in which trials finish.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import as_completed
from contextlib import contextmanager
from typing import Any

from lfgraph.core.parallel import deferred_interrupt, process_pool

EXECUTORS = ("local", "dask-local", "dask://HOST:PORT")


class Executor:
    """Runs ``fn(task)`` for every task and yields ``(task, result)`` as each finishes."""

    def __init__(self, kind: str, jobs: int, pool: Any = None, client: Any = None) -> None:
        self.kind, self.jobs, self._pool, self._client = kind, jobs, pool, client

    def run(self, fn: Callable[[Any], Any], tasks: Iterable[Any]) -> Iterator[tuple[Any, Any]]:
        """Run ``fn(task)`` for every task and yield ``(task, result)`` as each finishes.

        In completion order on a process pool or a Dask cluster, in task order in this process (one job). A task's
        exception is raised when its result is reached.
        """
        tasks = list(tasks)
        if self._client is not None:
            from distributed import as_completed as dask_completed

            futures = {self._client.submit(fn, t, pure=False): t for t in tasks}
            for fut in dask_completed(futures):
                yield futures[fut], fut.result()
        elif self._pool is not None:
            with deferred_interrupt():  # submitting starts the workers: not to be cut short halfway
                futures = {self._pool.submit(fn, t): t for t in tasks}
            for fut in as_completed(futures):
                yield futures[fut], fut.result()
        else:
            for t in tasks:
                yield t, fn(t)


def parse_executor(spec: str) -> str:
    """Validate an ``--executor`` value; raises ValueError naming the valid forms."""
    if spec in ("local", "dask-local") or (spec.startswith("dask://") and ":" in spec[len("dask://"):]):
        return spec
    raise ValueError(f"unknown executor {spec!r}; use one of {', '.join(EXECUTORS)}")


@contextmanager
def open_executor(spec: str = "local", jobs: int | None = None) -> Iterator[Executor]:
    """The executor for ``spec`` (see the module docstring); shuts it down on exit.

    Raises:
        ValueError: unknown spec, or Dask requested but not installed.
    """
    spec = parse_executor(spec)
    jobs = max(1, jobs or os.cpu_count() or 1)
    if spec == "local":
        if jobs == 1:
            yield Executor("local", 1)
            return
        with process_pool(jobs) as pool:
            yield Executor("local", jobs, pool=pool)
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ValueError("the Dask executor needs the optional extra: pip install 'lfgraph[dask]'") from None
    if spec == "dask-local":
        with LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
                Client(cluster) as client:
            yield Executor("dask-local", jobs, client=client)
        return
    address = "tcp://" + spec[len("dask://"):]
    with Client(address, timeout="30s") as client:
        yield Executor(spec, jobs, client=client)
