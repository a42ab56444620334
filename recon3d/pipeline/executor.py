"""Per-building work on local worker processes.

Buildings are independent once the terrain and the footprints are known, so their
solids can be built in parallel. Results come back in the order of the jobs and each
job's result depends only on the job (Open3D's RANSAC is seeded per call and held to
one thread), so the output is the same for any number of workers.

The module also tells how many CPUs this process may use (affinity and container
quota); its memory is :mod:`recon3d.core.memory`'s.

Workers are started with the "forkserver" method: forking the pipeline's own process,
which may hold OpenMP or TBB thread pools, can deadlock a child.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

__all__ = ["cgroup_cpus", "default_workers", "map_ordered"]


def default_workers() -> int:
    """The CPUs this process may use: its affinity mask, capped by a container's CPU
    quota (cgroup v2 ``cpu.max`` or v1 ``cpu.cfs_quota_us``), not the machine's count."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    quota = cgroup_cpus()
    return max(1, min(cpus, math.ceil(quota)) if quota else cpus)


def cgroup_cpus(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """The CPU quota of this process's cgroup in CPUs, None when there is none."""
    try:
        v2 = root / "cpu.max"
        if v2.exists():
            quota, period = v2.read_text().split()[:2]
            return None if quota == "max" else int(quota) / int(period)
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return quota / period if quota > 0 and period > 0 else None
    except (OSError, ValueError):
        return None


def map_ordered(
    func: Callable[[Any], Any], jobs: Iterable[Any], workers: int, *, done: Callable[[int], None] | None = None
) -> list[Any]:
    """``[func(job) for job in jobs]``, on ``workers`` processes when more than one.

    Parameters
    ----------
    func : callable
        A module-level function (it is pickled by name).
    jobs : iterable
        Picklable arguments, one per call.
    workers : int
        Processes to use; 1 runs everything in this process.
    done : callable, optional
        Called with the number of results collected so far, after each one.

    Returns
    -------
    list
        The results in the order of ``jobs``.
    """
    jobs = list(jobs)
    workers = min(int(workers), len(jobs))
    if workers <= 1:
        results = (func(job) for job in jobs)
        return _collect(results, done)
    method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(workers, mp_context=mp.get_context(method))
    try:
        results = _collect(pool.map(func, jobs, chunksize=1), done)
    except BaseException:  # Ctrl-C, SIGTERM, an error: stop now, not after every queued job
        processes = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        raise
    pool.shutdown()
    return results


def _collect(results: Iterable[Any], done: Callable[[int], None] | None) -> list[Any]:
    out = []
    for result in results:
        out.append(result)
        if done is not None:
            done(len(out))
    return out
