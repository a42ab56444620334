"""Running a run's independent jobs: on local worker processes or a Dask cluster.

Tiles (one pass at a time) and buildings are independent jobs. Results come back in
the order of the jobs and each job's result depends only on the job (Open3D's RANSAC
is seeded per call and held to one thread), so the output is the same for any number
of workers and on any executor. A tile pass keeps each tile's result in the run's work
folder, so a resumed run (``--resume``) does only the tiles that were not finished; a
tile that fails is tried once more, and a run with tiles that failed twice stops with
their list.

The module also tells how many CPUs this process may use (affinity and container
quota); its memory is :mod:`recon3d.core.memory`'s.

Workers are started with the "forkserver" method: forking the pipeline's own process,
which may hold OpenMP or TBB thread pools, can deadlock a child. Tile passes hand out
the largest tiles first.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from recon3d.errors import InputError, Recon3dError

log = logging.getLogger(__name__)

__all__ = ["Executor", "TileFailure", "cgroup_cpus", "connect", "default_workers", "map_ordered"]


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
    pool = _pool(workers)
    try:
        results = _on_pool(pool, func, jobs, done)
    finally:
        pool.shutdown()
    return results


def _pool(workers: int) -> ProcessPoolExecutor:
    method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
    return ProcessPoolExecutor(workers, mp_context=mp.get_context(method))


def _on_pool(pool: ProcessPoolExecutor, func, jobs: list, done) -> list:
    try:
        with _signals_held():  # a worker interrupted while it starts prints a traceback
            futures = [pool.submit(func, job) for job in jobs]
        return _collect((f.result() for f in futures), done)
    except BaseException:  # Ctrl-C, SIGTERM, an error: stop now, not after every queued job
        _stop(pool)
        raise


def _stop(pool: ProcessPoolExecutor) -> None:
    """Terminate the workers and wait (briefly) until the pool has failed every pending job.

    No future is cancelled here: the pool's manager thread marks every pending one
    failed once it sees its workers gone, and on Python 3.11 it fails with
    ``InvalidStateError`` on a future cancelled meanwhile. Waiting for that thread also
    keeps it from running on into the interpreter's exit.
    """
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False)
    for process in processes:
        process.terminate()
    manager = getattr(pool, "_executor_manager_thread", None)
    if manager is not None:
        manager.join(timeout=_STOP_TIMEOUT)


#: Seconds the pool's manager thread gets to fail the pending jobs after an interrupt.
_STOP_TIMEOUT = 10.0


@contextlib.contextmanager
def _signals_held():
    """Ctrl-C and SIGTERM received inside the block take effect as it ends (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    kinds = (signal.SIGINT, signal.SIGTERM)
    before = {k: signal.signal(k, lambda signum, frame: held.append(signum)) for k in kinds}
    try:
        yield
    finally:
        for k, handler in before.items():
            signal.signal(k, handler)
        for signum in held[:1]:
            signal.raise_signal(signum)


def _collect(results: Iterable[Any], done: Callable[[int], None] | None) -> list[Any]:
    out = []
    for result in results:
        out.append(result)
        if done is not None:
            done(len(out))
    return out


def release_memory() -> None:
    """Give the memory freed since the last call back to the system (glibc's ``malloc_trim``).

    A large array freed in the middle of the heap stays in this process's resident
    memory until something reuses it: a worker that has finished a tile would go on
    holding its peak while the next pass, or the main process, needs the memory. A few
    milliseconds per call; nothing where the C library is not glibc.
    """
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _libc():
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc if hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_LIBC = _libc() if os.name == "posix" else None


class TileFailure(Recon3dError):
    """Tiles failed twice; nothing is published."""


def connect(scheduler: str) -> Any:
    """A Dask distributed client: ``"local"`` starts a LocalCluster of this machine's
    CPUs, anything else is a scheduler address (``tcp://host:8786``).

    Raises
    ------
    InputError
        Dask is not installed, or the scheduler does not answer within 10 s.
    """
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise InputError("--scheduler/--dask needs Dask: pip install 'dask[distributed]'") from None
    if scheduler == "local":
        cluster = LocalCluster(n_workers=default_workers(), threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR)
        return Client(cluster)
    try:
        return Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise InputError(f"--scheduler {scheduler}: no Dask scheduler answers there ({exc})") from None


class Executor:
    """Where a run's jobs go: this process, local worker processes, or a Dask cluster.

    Parameters
    ----------
    workers : int
        Local processes for tile passes and buildings (1: this process).
    client : distributed.Client, optional
        Run tile passes and buildings on this Dask cluster instead.
    """

    def __init__(self, workers: int = 1, client: Any = None) -> None:
        self.workers = max(1, int(workers))
        self.client = client
        self._pool: ProcessPoolExecutor | None = None

    def map(self, func: Callable[[Any], Any], jobs: list, *, done: Callable[[int], None] | None = None,
            local: bool = False, workers: int | None = None) -> list:
        """``[func(job) for job in jobs]`` on the executor (in this process when ``local``);
        ``workers`` caps the local processes used for these jobs."""
        workers = min(self.workers if workers is None else workers, len(jobs))
        if local or not jobs or (self.client is None and workers <= 1):
            return map_ordered(func, jobs, 1, done=done)
        if self.client is not None:
            futures = self.client.map(func, jobs, pure=False)
            out = []
            for k, future in enumerate(futures, 1):
                out.append(future.result())
                if done:
                    done(k)
            return out
        if self._pool is None:  # one pool for the run: its processes start (and import) once
            self._pool = _pool(self.workers)
        try:
            return _on_pool(self._pool, func, jobs, done)
        except BaseException:
            self._pool = None
            raise

    def close(self) -> None:
        """Stop the worker processes (the Dask client is the caller's)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def tiles(self, name: str, func: Callable, spec: Any, tiles: list, args: list[tuple], *,
              progress: Callable[[str], None] | None = None, local: bool = False,
              sizes: list[int] | None = None) -> list[Path]:
        """Run pass ``name`` (``func(spec, tile, *args)``) over every tile not done yet.

        With ``sizes`` (a work measure per tile, such as its points) the largest tiles
        are handed out first, so that no worker is left with a large one at the end
        (longest processing time first); the results do not depend on the order.

        ``progress`` hears, after each tile, "<name> tile k/n, <rate> M points/s, ETA <s> s"
        (the points counted as the survey's share of the tiles done).

        Returns
        -------
        list of Path
            Each tile's saved result (``<tile folder>/<name>.npz``), in the order of ``tiles``.

        Raises
        ------
        TileFailure
            Tiles that failed twice, each with its reason.
        """
        paths = [spec.folder / t.name / f"{name}.npz" for t in tiles]
        todo = [i for i, p in enumerate(paths) if not p.exists()]
        if sizes is not None:
            todo.sort(key=lambda i: -sizes[i])
        jobs = [(func, name, spec, tiles[i], args[i]) for i in todo]
        start, total = time.perf_counter(), len(jobs)
        points = spec.summary.count * total / max(len(tiles), 1)

        def report(k: int) -> None:
            if progress:
                elapsed = max(time.perf_counter() - start, 1e-9)
                eta = (total - k) * elapsed / k
                progress(f"{name} tile {k}/{total}, {points * k / total / elapsed / 1e6:.2f} M points/s, ETA {eta:.0f} s")

        results = self.map(_tile_job, jobs, done=report, local=local)
        failed = [(tiles[i], r) for i, r in zip(todo, results, strict=True) if isinstance(r, str)]
        if failed:
            listing = "; ".join(f"tile {t.name} (cells {t.rows.start}-{t.rows.stop}, {t.cols.start}-{t.cols.stop}): {why}"
                                for t, why in failed[:10])
            raise TileFailure(f"{len(failed)} of {len(tiles)} tiles failed twice in the {name} pass: {listing}")
        return paths


#: Times a tile is tried before the run stops with its reason.
TILE_TRIES = 2


def _tile_job(job: tuple) -> Path | str:
    """One tile of one pass, its result saved beside the tile's others; the reason
    (a string) when it failed :data:`TILE_TRIES` times."""
    func, name, spec, tile, args = job
    path = spec.folder / tile.name / f"{name}.npz"
    reason = ""
    for attempt in range(TILE_TRIES):
        try:
            result = func(spec, tile, *args)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{name}.{os.getpid()}.npz")
            np.savez(tmp, **result)
            os.replace(tmp, path)
            del result
            release_memory()
            return path
        except (MemoryError, OSError, ValueError, RuntimeError, IndexError, KeyError) as exc:
            reason = f"{type(exc).__name__}: {exc}"
            log.warning("tile %s, pass %s, attempt %d failed: %s", tile.name, name, attempt + 1, reason)
    return reason
