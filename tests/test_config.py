import pytest

from recon3d.config import PipelineConfig
from recon3d.errors import InputError


def test_overrides_parse_toml_values():
    cfg = PipelineConfig().with_overrides(["dsm.resolution=0.5", "buildings.min_area=30", "ground.method=provider"])
    assert cfg.dsm.resolution == 0.5
    assert cfg.buildings.min_area == 30.0 and isinstance(cfg.buildings.min_area, float)
    assert cfg.ground.method == "provider"
    assert PipelineConfig().dsm.resolution is None  # frozen defaults untouched


def test_toml_file(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[dsm]\nresolution = 1\n[buildings]\nmin_height = 3.0\n")
    cfg = PipelineConfig.from_toml(f)
    assert cfg.dsm.resolution == 1.0 and cfg.buildings.min_height == 3.0


@pytest.mark.parametrize(
    "override, message",
    [
        ("dsm.foo=1", "unknown setting 'dsm.foo'"),
        ("nope.x=1", "unknown stage 'nope'"),
        ("dsm.resolution=abc", "is not a valid"),
        ("ground.method='csf'", "ground.method must be"),
        ("dsm.resolution", "expected stage.key=value"),
        ("stereo.tile_size=10", "at least 128 px"),
    ],
)
def test_bad_overrides_name_the_problem(override, message):
    with pytest.raises(InputError, match=message):
        PipelineConfig().with_overrides([override])


def test_bad_toml(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[dsm\nresolution = 1")
    with pytest.raises(InputError, match="not valid TOML"):
        PipelineConfig.from_toml(f)
    with pytest.raises(InputError, match="not found"):
        PipelineConfig.from_toml(tmp_path / "missing.toml")
