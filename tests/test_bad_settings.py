"""Settings outside their valid range, and grids too large for memory: one clear error, nothing written."""

import pytest
from conftest import AUTZEN, IGN, shared

from recon3d.config import PipelineConfig
from recon3d.errors import InputError, MemoryLimitError


@pytest.mark.parametrize("setting, needle", [
    ("dsm.resolution=0", "between 0.01 and 1000"),  # was silently replaced by the automatic value
    ("dsm.resolution=-1", "between 0.01 and 1000"),  # crashed in the report after the whole run
    ("dsm.resolution=nan", "between 0.01 and 1000"),
    ("dsm.resolution=1e6", "between 0.01 and 1000"),
    ("dsm.resolution=1e-6", "between 0.01 and 1000"),  # asked for a 44 PiB grid
    ("dsm.max_hole_area=-5", "dsm.max_hole_area"),
    ('lod.lods=["3"]', "choose among 1, 1.3, 2.2"),  # was accepted and built LoD1
    ("lod.lods=[]", "choose among"),
    ("lod.plane_distance=0", "lod.plane_distance"),
])
def test_setting_out_of_range(setting, needle):
    with pytest.raises(InputError, match=needle.replace(".", r"\.").replace("[", r"\[")):
        PipelineConfig().with_overrides([setting])


def test_grid_too_large_for_memory(tmp_path, monkeypatch):
    """dsm.resolution=0.005 on a 100 x 62 m tile grew to 4.3 GB before failing: now refused up front."""
    import recon3d.pipeline.run as pipeline
    from recon3d.core.memory import LIMIT_VARIABLE, available_memory

    assert available_memory() > 2.0**30  # the real figure: MemAvailable or the cgroup's limit
    monkeypatch.setenv(LIMIT_VARIABLE, str(2**30))  # --max-memory 1G, whatever the machine has
    with pytest.raises(MemoryLimitError, match=r"needs about .* GiB, more than the 1.0 GiB available "
                                               r"\(the --max-memory cap\).*dsm.resolution"):
        pipeline.run(shared(AUTZEN), tmp_path / "out", config=PipelineConfig().with_overrides(["dsm.resolution=0.05"]))
    assert list(tmp_path.iterdir()) == []


def test_max_memory_stops_a_run_before_it_reads(tmp_path):
    """``--max-memory`` caps every guard: a cap below the smallest work tile stops the run
    before any tile is worked, one line, nothing written."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "-m", "recon3d", "-q", "run", shared(IGN), "-o", tmp_path / "out",
                             "--max-memory", "10M"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert result.returncode == 1
    line, = result.stderr.strip().splitlines()
    assert "ign_village" in line and "more than the 10 MiB available (the --max-memory cap)" in line
    assert list(tmp_path.iterdir()) == []
    bad = subprocess.run([sys.executable, "-m", "recon3d", "run", shared(IGN), "-o", tmp_path / "out",
                          "--max-memory", "lots"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert bad.returncode == 2 and "not a memory size" in bad.stderr


def test_matching_and_roof_grids_check_memory_first(monkeypatch):
    """The census cost volume of a strip and a roof's label grid are refused, not allocated, past the cap."""
    import numpy as np
    import shapely

    from recon3d.buildings import roofgrid
    from recon3d.core.memory import LIMIT_VARIABLE
    from recon3d.stereo.match import MatchParams, match

    rng = np.random.default_rng(0)
    left = rng.uniform(0, 255, (64, 96)).astype(np.float32)
    monkeypatch.setenv(LIMIT_VARIABLE, str(100_000))
    with pytest.raises(MemoryLimitError, match=r"matching 96 x 64 px over \d+ disparities .* KiB available \(the --max-memory cap\)"):
        match(left, np.roll(left, -4, axis=1), MatchParams(min_disparity=0, max_disparity=32))
    square = shapely.box(0, 0, 200, 200)
    points = np.column_stack([rng.uniform(0, 200, (500, 2)), np.full(500, 10.0)])
    with pytest.raises(roofgrid.LodFailure, match="roof grid of .* needs") as failure:
        roofgrid.label_grid(square, points, np.zeros(500, np.int64), 0.25, 1.0)
    assert failure.value.reason == "too_large"
