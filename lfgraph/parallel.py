"""Run independent tasks on a local process pool with a progress bar."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from tqdm import tqdm


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
            with ProcessPoolExecutor(max_workers=min(jobs, len(tasks) or 1)) as pool:
                for r in pool.map(fn, tasks):
                    results.append(r)
                    bar.update()
    return results
