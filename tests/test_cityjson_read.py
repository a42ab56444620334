"""CityJSON reading (1.1, 2.0, sequences), the export command, CityJSON footprints as input."""

import json

import pytest
from click.testing import CliRunner

from conftest import CITYJSON_SCHEMA, shared
from recon3d.cli import cli
from recon3d.io.cityjson import read_cityjson, write_cityjson
from recon3d.quality.meshcheck import check_solid


@pytest.mark.parametrize("name, count, lods, invalid", [
    ("multi_lod.json", 10, {"1.2", "1.3", "2.2"}, 0),
    # CityJSON 1.1, BuildingParts folded into their Building; one solid has a face 1+ cm off its plane (val3dity 203)
    ("DH_01_subs.city.json", 4, {"2"}, 1),     # (read_cityjson(..., parts=True): 9, one per part)
    ("rotterdam_subset.json", 16, {"2"}, 0),      # MultiSurface only: surfaces, no solid to check
])
def test_reads_real_city_models(name, count, lods, invalid):
    city = read_cityjson(shared(f"citymodels/{name}"))
    assert len(city) == count
    assert set().union(*(b.solids for b in city)) == lods
    for b in city:
        assert b.footprint.is_valid and b.footprint.area > 5
        assert b.roof_z > b.ground_z
    solids = [s for b in city for s in b.solids.values() if s.kind == "Solid"]
    assert sum(bool(check_solid(s)) for s in solids) == invalid
    assert len(solids) == (0 if name.startswith("rotterdam") else sum(len(b.solids) for b in city))


def test_round_trip_keeps_geometry(tmp_path):
    city = read_cityjson(shared("citymodels/multi_lod.json"))
    write_cityjson(city, tmp_path / "a.city.json")
    back = read_cityjson(tmp_path / "a.city.json")
    for a, b in zip(city, back, strict=True):
        va = a.solids["2.2"].to_trimesh().volume
        assert b.solids["2.2"].to_trimesh().volume == pytest.approx(va, rel=1e-4)
        assert a.footprint.symmetric_difference(b.footprint).area < 0.01


def test_export_command_all_formats(delft_run, tmp_path):
    import jsonschema
    import trimesh

    out = delft_run.out_dir
    for fmt, name in (("cityjsonseq", "b.city.jsonl"), ("obj", "b.obj"), ("glb", "b.glb"), ("cityjson", "b.city.json")):
        result = CliRunner().invoke(cli, ["export", str(out), "--format", fmt, "-o", str(tmp_path / name)])
        assert result.exit_code == 0, result.output
    seq = (tmp_path / "b.city.jsonl").read_text().splitlines()
    blocks = delft_run.city.blocks()  # a block and its parts share one feature
    assert len(seq) == 1 + len(delft_run.city) - sum(len(p) - 1 for p in blocks.values())
    feature_schema = json.loads(shared("schemas/cityjson-2.0.2/cityjsonfeature.min.schema.json").read_text())
    for line in seq[1:]:
        errors = list(jsonschema.Draft7Validator(feature_schema).iter_errors(json.loads(line)))
        assert not errors, errors[0].message
    doc = json.loads((tmp_path / "b.city.json").read_text())
    # the date of the data (AHN3 LAS header), not of the run, so runs stay byte-identical
    assert doc["metadata"]["referenceDate"] == "2014-03-04"
    assert json.loads(seq[0])["metadata"]["referenceDate"] == "2014-03-04"
    assert not list(jsonschema.Draft7Validator(json.loads(shared(CITYJSON_SCHEMA).read_text())).iter_errors(doc))
    back = read_cityjson(tmp_path / "b.city.jsonl")
    assert len(back) == len(delft_run.city)
    assert sorted((b.id, b.parent or "") for b in back) == sorted((b.id, b.parent or "") for b in delft_run.city)
    total = sum(b.solids["1"].to_trimesh().volume for b in delft_run.city)
    assert sum(b.solids["1"].to_trimesh().volume for b in back) == pytest.approx(total, rel=1e-4)
    glb = trimesh.load(tmp_path / "b.glb")
    assert len(glb.geometry) >= len(delft_run.city)
    again = CliRunner().invoke(cli, ["export", str(out), "--format", "glb", "-o", str(tmp_path / "b.glb")])
    assert again.exit_code == 1 and "--overwrite" in again.output


def test_cityjson_footprints_as_input(delft_run):
    from recon3d.core.geo import parse_crs
    from recon3d.io.vectors import read_footprints

    fps, _ = read_footprints(delft_run.out_dir / "buildings.city.json", crs=parse_crs("EPSG:7415"))
    assert len(fps) == len(delft_run.city)
    for f, b in zip(fps, delft_run.city, strict=True):
        assert f.polygon.symmetric_difference(b.footprint).area < 1e-3 * b.footprint.area  # 2 mm snapping
        assert f.attributes["roof_z"] == pytest.approx(b.roof_z, abs=0.001)


def test_building_parts_folded_or_split():
    """Den Haag: 3 Buildings made of 2-3 BuildingParts each, 1 without parts."""
    path = shared("citymodels/DH_01_subs.city.json")
    doc = json.loads(path.read_text(encoding="utf-8"))
    folded = read_cityjson(path)
    assert all(b.parent is None for b in folded)
    split = read_cityjson(path, parts=True)
    assert len(split) == 9 and sum(b.parent is None for b in split) == 1
    for b in split:
        if b.parent is not None:
            assert doc["CityObjects"][b.id]["type"] == "BuildingPart" and b.id in doc["CityObjects"][b.parent]["children"]
            assert "roofType" in b.attributes


def test_what_is_not_read_is_counted(tmp_path):
    """A MultiSolid building, a CompositeSurface one and a road: the surfaces are read, the
    rest counted by type and reason, and export names them."""
    cube = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    doc = {"type": "CityJSON", "version": "2.0", "transform": {"scale": [0.001] * 3, "translate": [5e5, 5e6, 0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/32631"},
           "CityObjects": {
               "solids": {"type": "Building", "geometry": [{"type": "MultiSolid", "lod": "2", "boundaries": [[cube]]}]},
               "shell": {"type": "Building", "geometry": [{"type": "CompositeSurface", "lod": "2", "boundaries": cube}]},
               "road": {"type": "Road", "geometry": [{"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 2, 3]]]}]},
           },
           "vertices": [[0, 0, 0], [10000, 0, 0], [10000, 10000, 0], [0, 10000, 0],
                        [0, 0, 6000], [10000, 0, 6000], [10000, 10000, 6000], [0, 10000, 6000]]}
    (tmp_path / "buildings.city.json").write_text(json.dumps(doc))
    city = read_cityjson(tmp_path / "buildings.city.json")
    assert [b.id for b in city] == ["solids", "shell"]
    assert not city.buildings[0].solids and city.buildings[1].solids["2"].kind == "MultiSurface"
    assert city.metadata["skipped_geometries"] == {"MultiSolid (not read)": 1, "Road object (not a building)": 1}
    result = CliRunner().invoke(cli, ["export", str(tmp_path), "--format", "obj", "-o", str(tmp_path / "c.obj")])
    assert result.exit_code == 0 and "2 buildings: 1 MultiSurface" in result.output
    assert "skipped: 1 MultiSolid (not read), 1 Road object (not a building)" in result.output
    assert (tmp_path / "c.obj").read_text().count("\nf ") == 12  # the six faces of the shell, as triangles
