"""`recon3d run` end to end on the real LiDAR files, measured against the providers' data."""

import json

import laspy
import numpy as np
import pytest
import rasterio
from conftest import CITYJSON_SCHEMA, shared

CONTRACT = [
    "run.json",
    "cloud.laz",
    "dsm.tif",
    "dtm.tif",
    "ndsm.tif",
    "model_dsm.tif",
    "buildings.city.json",
    "buildings.obj",
    "buildings.glb",
    "buildings_3dtiles/tileset.json",
    "footprints.geojson",
    "footprints.gpkg",
    "report.json",
]


def _table(state, product, reference):
    return next(t for t in state.report["accuracy"] if t["product"] == product and t["reference"].startswith(reference))


def _validate_cityjson(path):
    import jsonschema

    schema = json.loads(shared(CITYJSON_SCHEMA).read_text())
    doc = json.loads(path.read_text(encoding="utf-8"))
    errors = list(jsonschema.Draft7Validator(schema).iter_errors(doc))
    assert not errors, errors[0].message
    return doc


def test_delft_writes_the_whole_contract(delft_run):
    out = delft_run.out_dir
    for name in CONTRACT:
        assert (out / name).is_file(), name
    assert not list(out.parent.glob(".out.partial-*"))
    for name in ("dsm", "dtm", "ndsm", "model_dsm"):
        with rasterio.open(out / f"{name}.tif") as src:
            assert src.crs.to_epsg() == 7415
            assert src.dtypes[0] == "float32" and np.isnan(src.nodata)
            assert src.transform == delft_run.dsm.transform
    assert laspy.read(out / "cloud.laz").header.parse_crs().to_epsg() == 7415
    run = json.loads((out / "run.json").read_text())
    assert run["chosen"]["dsm.resolution"]["value"] == 0.5
    assert "spacing" in run["chosen"]["dsm.resolution"]["reason"]
    assert set(run["timings_s"]) >= {"read", "dsm", "ground", "dtm", "buildings", "lod", "write"}


def test_delft_terrain_against_provider(delft_run):
    dtm = _table(delft_run, "DTM", "provider ground points")
    assert dtm["n"] == 87130
    assert dtm["rms"] <= 0.10 and abs(dtm["mean"]) <= 0.05 and dtm["within_1m"] >= 99.9
    ground = delft_run.report["ground_filter"]
    assert ground["total_percent"] <= 1.0 and ground["kappa"] >= 0.97


def test_delft_buildings_and_solids(delft_run):
    cover = delft_run.report["buildings_vs_provider"]
    assert cover["completeness_percent"] >= 75.0 and cover["correctness_percent"] >= 95.0
    city = delft_run.city
    assert len(city) >= 3
    from recon3d.quality.meshcheck import check_solid

    for b in city:
        mesh = b.solids["1"].to_trimesh()
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
        assert mesh.volume == pytest.approx(b.footprint.area * b.height, rel=1e-3)
        assert all(not check_solid(solid) for solid in b.solids.values())  # every LoD valid
        assert b.status == "ok" or b.reason  # a fallback always says why
    classes = laspy.read(delft_run.out_dir / "cloud.laz").classification
    assert set(np.unique(classes)) <= {1, 2, 5, 6}
    assert np.mean(classes == 5) > 0.05  # the trees of the strip are vegetation


def test_delft_cityjson_is_valid_and_georeferenced(delft_run):
    doc = _validate_cityjson(delft_run.out_dir / "buildings.city.json")
    assert doc["version"] == "2.0"
    assert doc["metadata"]["referenceSystem"].endswith("/EPSG/0/7415")
    scale, translate = np.array(doc["transform"]["scale"]), np.array(doc["transform"]["translate"])
    world = np.array(doc["vertices"]) * scale + translate
    lo, hi = delft_run.cloud.bounds
    assert (world[:, :2] >= lo[:2] - 1).all() and (world[:, :2] <= hi[:2] + 1).all()
    for obj in doc["CityObjects"].values():
        if "children" in obj:  # a block split at height jumps: its BuildingParts carry the solids
            assert obj["geometry"] == [] and all(c in doc["CityObjects"] for c in obj["children"])
            continue
        lods = [g["lod"] for g in obj["geometry"]]
        assert all(g["type"] == "Solid" for g in obj["geometry"])
        assert "1" in lods and set(lods) <= {"1", "1.3", "2.2"}  # LoD1 always, LoD2.2 or its fallback
    assert sum("2.2" in [g["lod"] for g in o["geometry"]] for o in doc["CityObjects"].values()) >= 5


def test_ign_with_footprints(ign_footprints_run):
    s = ign_footprints_run
    assert len(s.city) == 40
    # the BD Uni layer covers more than the LiDAR tile: 6 footprints lie on it
    assert sum(bool(b.solids) for b in s.city) == 6
    assert sum(b.reason == "outside_data" for b in s.city) == 34
    # every footprint is written, with the reason when it got no solid
    fc = json.loads((s.out_dir / "footprints.geojson").read_text())
    assert len(fc["features"]) == 40
    for f in fc["features"]:
        p = f["properties"]
        assert p["status"] == "ok" or p["reason"]
    dtm = _table(s, "DTM", "provider ground points")
    assert dtm["rms"] <= 0.10
    # 71 % measured: BD Uni misses part of the tile's buildings and is offset from the LiDAR
    assert s.report["buildings_vs_provider"]["completeness_percent"] >= 65.0
    _validate_cityjson(s.out_dir / "buildings.city.json")


def test_ign_detected_buildings(ign_run):
    cover = ign_run.report["buildings_vs_provider"]
    # correctness is not asserted here: this IGN tile leaves many roof points in class 1
    assert cover["completeness_percent"] >= 85.0
    assert len(ign_run.city) == 4
    assert ign_run.report["ground_filter"]["total_percent"] <= 0.5


def test_autzen_in_feet(autzen_run):
    s = autzen_run
    assert s.units.name in ("foot", "US survey foot")
    with rasterio.open(s.out_dir / "dsm.tif") as src:
        assert src.res == (5.0, 5.0)  # 5 ft: about 2 x the 0.66 m point spacing
        assert "foot" in src.crs.to_wkt().lower()
    dtm = _table(s, "DTM", "provider ground points")
    assert dtm["rms"] <= 0.15  # metres, although the data are in feet
    run = json.loads((s.out_dir / "run.json").read_text())
    assert run["inputs"]["units"]["metres_per_unit"] == pytest.approx(0.3048, rel=1e-5)


def test_checkpoints_report(tmp_path, delft_run):
    """Check points taken from the provider's ground and roof points give tables per product."""
    from recon3d.core.geo import parse_crs
    from recon3d.pipeline.run import run

    cloud = delft_run.cloud
    c = delft_run.reference_classes
    rng = np.random.default_rng(0)
    ground = cloud.xyz[rng.choice(np.flatnonzero(c == 2), 50, replace=False)]
    roof = cloud.xyz[rng.choice(np.flatnonzero(c == 6), 50, replace=False)]
    csv = tmp_path / "cp.csv"
    rows = ["x,y,z,id,kind"] + [f"{p[0]},{p[1]},{p[2]},g{i},ground" for i, p in enumerate(ground)]
    rows += [f"{p[0]},{p[1]},{p[2]},r{i},roof" for i, p in enumerate(roof)]
    csv.write_text("\n".join(rows) + "\n")
    s = run(shared("lidar/delft_ahn3_strip.laz"), tmp_path / "out", crs=parse_crs("EPSG:7415"), checkpoints=csv)
    assert _table(s, "DTM", "check points (ground)")["rms"] <= 0.15
    assert _table(s, "DTM", "check points (ground)")["within_1m"] == 100.0
    # the DSM keeps the highest point of a cell: above ground points under trees, close on roofs
    assert _table(s, "DSM", "check points (ground)")["n"] == 50
    roof = _table(s, "DSM", "check points (roof)")
    assert roof["n"] == 50 and roof["nmad"] <= 0.3
    report = json.loads((s.out_dir / "report.json").read_text())
    assert any(t["reference"] == "check points (roof)" and t["product"] == "model DSM" for t in report["accuracy"])


def test_same_input_same_bytes(ign_run, tmp_path):
    """Products are byte-identical run to run and whatever the number of processes
    building the solids (run.json and report.html hold timings)."""
    from recon3d.pipeline.run import run

    again = run(shared("lidar/ign_village_2154.laz"), tmp_path / "again", workers=3)
    assert again.auto["workers"]["value"] == 3
    for name in CONTRACT:
        if name not in ("run.json",):
            a, b = (ign_run.out_dir / name).read_bytes(), (again.out_dir / name).read_bytes()
            assert a == b, name
