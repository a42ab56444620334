"""Local worker processes (recon3d.pipeline.executor)."""

import math
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from recon3d.pipeline.executor import Executor, _signals_held, default_workers, map_ordered


def test_map_ordered_keeps_the_order_of_the_jobs():
    jobs = [9.0, 1.0, 16.0, 4.0, 25.0]
    assert map_ordered(math.sqrt, jobs, workers=1) == [3.0, 1.0, 4.0, 2.0, 5.0]
    assert map_ordered(math.sqrt, jobs, workers=2) == [3.0, 1.0, 4.0, 2.0, 5.0]
    assert map_ordered(math.sqrt, [], workers=4) == []


def test_default_workers_is_at_least_one():
    assert default_workers() >= 1


def test_done_counts_the_results_as_they_come():
    seen = []
    map_ordered(math.sqrt, [1.0, 4.0, 9.0], workers=2, done=seen.append)
    assert seen == [1, 2, 3]


def test_a_failed_job_stops_the_queue_at_once_and_no_thread_fails(monkeypatch):
    """The pending jobs are dropped, not run; on Python 3.11 the pool's manager thread
    failed with InvalidStateError when a future was cancelled while it broke the pool."""
    failures = []
    monkeypatch.setattr(threading, "excepthook", failures.append)
    start = time.perf_counter()
    with pytest.raises(ValueError, match="non-negative"):
        map_ordered(time.sleep, [-1.0, 60.0, 60.0, 60.0], workers=2)  # time.sleep(-1) raises
    assert time.perf_counter() - start < 30.0  # 180 s if the queue were drained
    assert failures == []


def test_signals_held_while_workers_start_take_effect_after():
    """Ctrl-C while a pool starts its workers left one half started (a traceback from it)."""
    reached = False
    # Python's own Ctrl-C handler, also when the suite runs as a background job (which ignores Ctrl-C)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with _signals_held():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)  # a handler runs between bytecodes: it would have run by now
                reached = True
    finally:
        signal.signal(signal.SIGINT, before)
    assert reached


def test_run_reports_its_stages_and_the_buildings(tmp_path):
    """``progress`` hears of every stage in order, and of each building the lod stage
    finishes (the CLI's progress bar shows "lod 3/4 buildings")."""
    from conftest import IGN, shared
    from recon3d.pipeline.run import STAGES, run

    calls = []
    run(shared(IGN), tmp_path / "out", progress=lambda name, i, n: calls.append((name, i, n)))
    stages = [c for c in calls if " " not in c[0]]
    assert stages == [(name, i, len(STAGES)) for i, (name, _) in enumerate(STAGES)]
    lod_index = [name for name, _ in STAGES].index("lod")
    built = [c for c in calls if c[0].startswith("lod ") and c[0].endswith(" buildings")]
    assert built == [(f"lod {k}/4 buildings", lod_index, len(STAGES)) for k in range(1, 5)]


def test_cgroup_quota_caps_the_workers(tmp_path):
    """A container limited to 1.5 CPUs (cgroup v2 "150000 100000") gets 2 workers at
    most, one without a quota ("max") as many as its affinity allows; v1 files too."""
    from recon3d.pipeline.executor import cgroup_cpus

    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert cgroup_cpus(tmp_path) == 1.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpus(tmp_path) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert cgroup_cpus(v1) is None
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("400000\n")
    assert cgroup_cpus(v1) == 4.0
    assert cgroup_cpus(tmp_path / "missing") is None


def test_cli_with_worker_processes(tmp_path):
    """``python -m recon3d run --workers 2`` in its own process, the way users call it:
    the forkserver workers start, build the solids and the run records them."""
    import json
    import subprocess
    import sys

    from conftest import IGN, shared

    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "recon3d", "-q", "run", str(shared(IGN)), "-o", str(out), "--workers", "2"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads((out / "run.json").read_text())["chosen"]["workers"]["value"] == 2


_ORDER: list[str] = []


def _note_tile(spec, tile, value):
    _ORDER.append(tile.name)
    return {"value": value}


def test_tile_passes_hand_out_the_largest_tiles_first(tmp_path):
    """Longest processing time first; the results still come back in the tiles' order."""
    from types import SimpleNamespace

    import numpy as np

    from recon3d.pipeline.tiling import Tile

    tiles = [Tile((0, k), slice(0, 8), slice(8 * k, 8 * k + 8)) for k in range(4)]
    spec = SimpleNamespace(folder=tmp_path, summary=SimpleNamespace(count=100))
    _ORDER.clear()
    paths = Executor(1).tiles("t", _note_tile, spec, tiles, [(k,) for k in range(4)], sizes=[5, 40, 1, 40])
    assert _ORDER == ["0_1", "0_3", "0_0", "0_2"]
    assert [int(np.load(p)["value"]) for p in paths] == [0, 1, 2, 3]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_memory_freed_goes_back_to_the_system():
    # 128 MB of heap blocks, freed under a block still in use at the top of the heap:
    # free() alone leaves them resident, release_memory() returns them
    script = """
import os
from recon3d.pipeline.executor import release_memory
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
blocks = [bytearray(64 * 1024) for _ in range(2000)]
top = blocks[-1]
del blocks
before = rss()
release_memory()
print(before - rss())
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert float(done.stdout) > 64  # MB given back
