"""The bad-input catalogue: each case one line on stderr naming the file and the problem, exit 1,
no traceback and nothing written (the command line in a subprocess, as a user runs it)."""

import json
import subprocess
import sys

import laspy
import numpy as np
import pytest


def _cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "recon3d", "-q", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def _refused(result, *needles):
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("recon3d: error: "), result.stderr
    for n in needles:
        assert n in lines[0], lines[0]


def _las(path, xyz, z_scale=0.01):
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales, header.offsets = [0.01, 0.01, z_scale], xyz.min(axis=0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.write(path)
    return path


def _field(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 100, n), rng.uniform(0, 100, n), rng.uniform(0, 1, n)]) + [5e5, 5e6, 50]


@pytest.mark.parametrize("name, xyz, needles", [
    # 1,000 points at one XYZ: a gradient error deep in the ground filter
    ("same.las", np.tile([[5e5, 5e6, 50.0]], (1000, 1)), ["same.las", "span 0 x 0 metre", "no area"]),
    # 10 random points became one 1,600 m2 building without a word
    ("ten.las", _field(10), ["ten.las", "10 points: too few"]),
    # a whole cloud offset to 1e9 m: float32 rasters collapsed to one value, 0 buildings
    ("high.las", _field(2000) + [0, 0, 1e9], ["high.las", "heights around 1e+09", "vertical offset"]),
])
def test_clouds_that_cannot_be_gridded(tmp_path, name, xyz, needles):
    path = _las(tmp_path / name, xyz)
    result = _cli("run", path, "--crs", "EPSG:32631", "-o", tmp_path / "out", cwd=tmp_path)
    _refused(result, *needles)
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_a_gross_height_error_is_dropped_with_a_warning(tmp_path):
    """One point at Z = 1e9 crashed the LAS writer (OverflowError) after the whole run."""
    xyz = _field(3000)
    xyz[0, 2] = 1e9
    path = _las(tmp_path / "spike.las", xyz, z_scale=1.0)
    result = _cli("run", path, "--crs", "EPSG:32631", "-o", tmp_path / "out", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert any("1 points lie more than" in w for w in run["warnings"])
    assert laspy.read(tmp_path / "out" / "cloud.laz").header.point_count == 2999


@pytest.mark.parametrize("content, needle", [
    ([1, 2], "not CityJSON (the top level is not a JSON object)"),
    ({"type": "CityJSON", "version": "2.0", "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]},
      "CityObjects": {"a": {"type": "Building", "geometry": [{"type": "Solid", "lod": "1",
                                                            "boundaries": [[[[0, 1, 99]]]]}]}},
      "vertices": [[0, 0, 0], [1, 0, 0]]}, "CityObject 'a' has malformed geometry"),
    ("hello", "not valid JSON"),
])
def test_validate_malformed_cityjson(tmp_path, content, needle):
    path = tmp_path / "city.city.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    _refused(_cli("validate", path, cwd=tmp_path), "city.city.json", needle)


def test_footprints_with_an_unclosed_ring(tmp_path):
    cloud = _las(tmp_path / "field.las", _field(3000))
    ring = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [[[5e5, 5e6], [5e5 + 9, 5e6 + 9]]]}}]}
    (tmp_path / "ring.geojson").write_text(json.dumps(ring))
    result = _cli("run", cloud, "--crs", "EPSG:32631", "--footprints", tmp_path / "ring.geojson",
                  "-o", tmp_path / "out", cwd=tmp_path)
    _refused(result, "ring.geojson", "feature 0", "cannot be built")
    assert not (tmp_path / "out").exists()


def test_data_in_the_wrong_crs(tmp_path):
    """Delft's RD coordinates declared as French Lambert 93 were accepted, and landed in the ocean."""
    from conftest import DELFT, shared

    result = _cli("run", shared(DELFT), "--crs", "EPSG:2154", "-o", tmp_path / "out", cwd=tmp_path)
    _refused(result, "delft_ahn3_strip.laz", "EPSG:2154", "outside that CRS's area of use", "is the CRS right?")
    cloud = _las(tmp_path / "field.las", _field(3000))  # UTM 31N coordinates
    tile = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::28992"}},
            "features": [{"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [
                [[5e5, 5e6], [5e5 + 9, 5e6], [5e5 + 9, 5e6 + 9], [5e5, 5e6]]]}}]}
    (tmp_path / "rd.geojson").write_text(json.dumps(tile))
    result = _cli("run", cloud, "--crs", "EPSG:32631", "--footprints", tmp_path / "rd.geojson",
                  "-o", tmp_path / "out", cwd=tmp_path)
    _refused(result, "rd.geojson", "EPSG:28992", "area of use")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.las", "rd.geojson"]


@pytest.mark.parametrize("offset, value, needle", [
    (103, 1, "variable-length records"),  # 16 million VLRs: laspy spent minutes and gigabytes on them
    (250, 0x7F, "the header claims"),  # a point count of billions: the reader allocated 17 GB
])
def test_las_headers_that_claim_too_much(tmp_path, offset, value, needle):
    from recon3d.errors import InputError
    from recon3d.io.las import read_las

    path = _las(tmp_path / "a.las", _field(200))
    data = bytearray(path.read_bytes())
    data[offset] = value
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=needle):  # from the header, before anything is allocated
        read_las(path)


def test_a_las_header_with_a_nan_offset_is_refused(tmp_path):
    """Coordinates are finite when the header's scales and offsets are (the readers check
    the header, not every point); a NaN offset makes every x NaN and is named."""
    from recon3d.core.geo import parse_crs
    from recon3d.errors import InputError
    from recon3d.io.las import read_las

    path = _las(tmp_path / "a.las", _field(200))
    las = laspy.read(path)
    las.header.offsets = np.array([np.nan, las.header.offsets[1], las.header.offsets[2]])
    with np.errstate(invalid="ignore"):  # laspy casts the NaN x back to integers on writing
        las.write(path)
    with pytest.raises(InputError, match="a.las: 200 points have NaN or infinite coordinates"):
        read_las(path, crs=parse_crs("EPSG:32631"))
