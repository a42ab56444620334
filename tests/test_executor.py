"""Local worker processes (recon3d.pipeline.executor)."""

import math

from recon3d.pipeline.executor import default_workers, map_ordered


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
    assert [c for c in calls if c[0].startswith("lod ")] == [(f"lod {k}/4 buildings", lod_index, len(STAGES)) for k in range(1, 5)]
