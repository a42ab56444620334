"""Shared fixtures: paths to the real data in ../shared/data and cached pipeline runs."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

# Runs compared byte for byte may straddle midnight; an input without a date takes the
# day of the run (test_io tests that rule), so the suite fixes the day.
os.environ["SOURCE_DATE_EPOCH"] = "1767225600"  # 2026-01-01

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

DELFT = "lidar/delft_ahn3_strip.laz"
IGN = "lidar/ign_village_2154.laz"
AUTZEN = "lidar/autzen_trim.laz"
BDUNI = "footprints/ign_village_2154/bduni_buildings.shp"
CITYJSON_SCHEMA = "schemas/cityjson-2.0.2/cityjson.min.schema.json"


def shared(relative: str) -> Path:
    """Path of a file in ../shared/data; fails in CI, skips elsewhere, when it is missing."""
    path = SHARED_DATA / relative
    if not path.exists():
        message = f"shared test data missing: {path}"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    return path


def chromium() -> str:
    """Path of Debian's chromium for the browser tests; fails in CI, skips elsewhere, when
    it (or the playwright package driving it) is missing."""
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        path = None
    if path is None:
        message = "chromium or playwright missing: apt-get install chromium; pip install -e '.[dev]'"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    return path


def copy_scene(scene: Path, tmp_path: Path) -> Path:
    """A copy of a scene folder to spoil, in ``tmp_path / "scene"``."""
    dst = tmp_path / "scene"
    shutil.copytree(scene, dst)
    return dst


def run_fails(args: list, tmp_path: Path, *needles: str) -> None:
    """``recon3d run ARGS -o tmp_path/out`` exits 1 naming every needle, and writes nothing."""
    from click.testing import CliRunner

    from recon3d.cli import cli

    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["-q", "run", *map(str, args), "-o", str(out)])
    assert result.exit_code == 1, result.output
    for n in needles:
        assert n in result.output, result.output
    assert not out.exists()
    assert not list(tmp_path.glob(".out.partial-*"))


@pytest.fixture(scope="session")
def delft_run(tmp_path_factory):
    """The Delft AHN3 strip through `recon3d run` with its CRS given (it has none)."""
    from recon3d.core.geo import parse_crs
    from recon3d.pipeline.run import run

    out = tmp_path_factory.mktemp("delft") / "out"
    return run(shared(DELFT), out, crs=parse_crs("EPSG:7415"))


@pytest.fixture(scope="session")
def ign_footprints_run(tmp_path_factory):
    """The IGN village with its BD Uni footprints."""
    from recon3d.pipeline.run import run

    out = tmp_path_factory.mktemp("ign_fp") / "out"
    return run(shared(IGN), out, footprints=shared(BDUNI))


@pytest.fixture(scope="session")
def ign_run(tmp_path_factory):
    """The IGN village, buildings detected from the nDSM."""
    from recon3d.pipeline.run import run

    out = tmp_path_factory.mktemp("ign") / "out"
    return run(shared(IGN), out)


@pytest.fixture(scope="session")
def autzen_run(tmp_path_factory):
    """Autzen: a CRS in US feet, classes 1 and 2 only."""
    from recon3d.pipeline.run import run

    out = tmp_path_factory.mktemp("autzen") / "out"
    return run(shared(AUTZEN), out)
