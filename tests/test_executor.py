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
