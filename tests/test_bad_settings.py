"""Settings outside their valid range, and grids too large for memory: one clear error, nothing written."""

import pytest
from conftest import AUTZEN, shared

from recon3d.config import PipelineConfig
from recon3d.errors import InputError


@pytest.mark.parametrize("setting, needle", [
    ("dsm.resolution=0", "between 0.01 and 1000"),  # was silently replaced by the automatic value
    ("dsm.resolution=-1", "between 0.01 and 1000"),  # crashed in the report after the whole run
    ("dsm.resolution=nan", "between 0.01 and 1000"),
    ("dsm.resolution=1e6", "between 0.01 and 1000"),
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

    assert pipeline.available_memory() > 2.0**30  # the real figure: MemAvailable or the cgroup's limit
    monkeypatch.setattr(pipeline, "available_memory", lambda: 2.0**30)  # 1 GiB, whatever the machine has
    with pytest.raises(InputError, match=r"needs about .* GiB, more than the 1.0 GiB available.*dsm.resolution"):
        pipeline.run(shared(AUTZEN), tmp_path / "out", config=PipelineConfig().with_overrides(["dsm.resolution=0.05"]))
    assert list(tmp_path.iterdir()) == []
