"""The command line: bad input gives one line naming the file, exit 1, and no output."""

import numpy as np
import pyproj
import pytest
import shapely
from click.testing import CliRunner
from conftest import BDUNI, DELFT, IGN, shared

from recon3d.cli import cli


def _run(args):
    return CliRunner().invoke(cli, ["-q", "run", *map(str, args)])


def _assert_clean_failure(result, out, *needles):
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("recon3d: error:"), result.output
    for n in needles:
        assert n in lines[0]
    assert "Traceback" not in result.output
    assert not out.exists() or not any(out.iterdir())
    assert not list(out.parent.glob(f".{out.name}.partial-*"))


def test_help_lists_options():
    result = CliRunner().invoke(cli, ["run", "--help"])
    assert result.exit_code == 0
    for option in ("--crs", "--footprints", "--checkpoints", "--overwrite", "--set", "--config"):
        assert option in result.output


def test_missing_file(tmp_path):
    out = tmp_path / "out"
    _assert_clean_failure(_run([tmp_path / "nope.laz", "-o", out]), out, "nope.laz", "not found")


def test_corrupt_laz(tmp_path):
    bad = tmp_path / "broken.laz"
    data = shared(IGN).read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    _assert_clean_failure(_run([bad, "-o", out]), out, "broken.laz", "cannot read")


def test_empty_cloud(tmp_path):
    import laspy

    las = laspy.read(shared(IGN))
    las.points = las.points[:0]
    empty = tmp_path / "empty.laz"
    las.write(empty)
    out = tmp_path / "out"
    _assert_clean_failure(_run([empty, "-o", out]), out, "empty.laz", "empty")


def test_no_crs_and_unknown_epsg(tmp_path):
    out = tmp_path / "out"
    _assert_clean_failure(_run([shared(DELFT), "-o", out]), out, "delft_ahn3_strip.laz", "--crs")
    _assert_clean_failure(_run([shared(DELFT), "-o", out, "--crs", "EPSG:999999"]), out, "EPSG:999999")


def test_footprints_that_miss_the_data(tmp_path):
    from recon3d.io.vectors import write_features

    far = tmp_path / "far.geojson"
    write_features(far, [shapely.box(650000, 6860000, 650010, 6860010)], [{"id": "x"}], pyproj.CRS.from_epsg(2154))  # Paris
    out = tmp_path / "out"
    _assert_clean_failure(_run([shared(IGN), "-o", out, "--footprints", far]), out, "far.geojson", "overlaps")


def test_footprints_without_crs(tmp_path):
    import pyogrio

    box = shapely.box(870210, 6617090, 870230, 6617110)
    shp = tmp_path / "nocrs.shp"  # a shapefile without .prj
    pyogrio.raw.write(shp, np.array([shapely.to_wkb(box)], dtype=object), [], fields=[], geometry_type="Polygon", crs=None, driver="ESRI Shapefile")
    out = tmp_path / "out"
    _assert_clean_failure(_run([shared(IGN), "-o", out, "--footprints", shp]), out, "nocrs.shp", "no CRS")
    # GeoJSON without a crs member is WGS84 by definition: projected numbers in it are caught
    gj = tmp_path / "projected.geojson"
    gj.write_text('{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, "geometry": '
                  + shapely.to_geojson(box) + "}]}")
    _assert_clean_failure(_run([shared(IGN), "-o", out, "--footprints", gj]), out, "projected.geojson", "longitude/latitude")


def test_footprints_in_another_crs_are_reprojected(tmp_path):
    from recon3d.core.geo import parse_crs
    from recon3d.io.vectors import read_footprints, write_features

    fps, _ = read_footprints(shared(BDUNI), crs=parse_crs("EPSG:2154"))
    t = pyproj.Transformer.from_crs(2154, 4326, always_xy=True)
    geoms = [shapely.transform(f.polygon, lambda xy: np.column_stack(t.transform(xy[:, 0], xy[:, 1]))) for f in fps]
    wgs = tmp_path / "bduni_wgs84.geojson"
    write_features(wgs, geoms, [{"id": f.id} for f in fps], pyproj.CRS.from_epsg(4326))
    out = tmp_path / "out"
    result = _run([shared(IGN), "-o", out, "--footprints", wgs])
    assert result.exit_code == 0, result.output
    import json

    fc = json.loads((out / "footprints.geojson").read_text())
    assert len(fc["features"]) == 40
    assert fc["bbox"][0] > 800000  # Lambert-93 metres, not degrees


def test_existing_output_needs_overwrite(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    keep = out / "mine.txt"
    keep.write_text("user data")
    result = _run([shared(IGN), "-o", out])
    assert result.exit_code == 1 and "--overwrite" in result.output
    assert keep.read_text() == "user data"
    result = _run([shared(IGN), "-o", out, "--overwrite", "--set", "dsm.resolution=1.0"])
    assert result.exit_code == 0, result.output
    assert not keep.exists() and (out / "dsm.tif").exists()
    import rasterio

    with rasterio.open(out / "dsm.tif") as src:
        assert src.res == (1.0, 1.0)


def test_bad_setting(tmp_path):
    out = tmp_path / "out"
    _assert_clean_failure(_run([shared(IGN), "-o", out, "--set", "dsm.resolutoin=1"]), out, "dsm.resolutoin")


def test_evaluate_buildings_command(ign_run, tmp_path):
    import json

    from conftest import BDUNI

    result = CliRunner().invoke(
        cli, ["evaluate", "buildings", str(ign_run.out_dir), "--reference", str(shared(BDUNI)), "--json", str(tmp_path / "b.json")]
    )
    assert result.exit_code == 0, result.output
    numbers = json.loads((tmp_path / "b.json").read_text())
    assert numbers["n_reference"] == 6  # the BD Uni footprints inside the LiDAR tile
    assert numbers["area_completeness"] >= 95.0 and numbers["object_completeness"] == 100.0


def test_validate_command(delft_run):
    ok = CliRunner().invoke(cli, ["validate", str(delft_run.out_dir / "buildings.city.json")])
    assert ok.exit_code == 0 and "solids valid" in ok.output
    n = sum(len(b.solids) for b in delft_run.city)
    assert f"{n} of {n} solids valid" in ok.output
    # the Den Haag sample has one face 1+ cm off its plane: found, exit 1
    bad = CliRunner().invoke(cli, ["validate", str(shared("citymodels/DH_01_subs.city.json"))])
    assert bad.exit_code == 1 and "203 NON_PLANAR_POLYGON_DISTANCE_PLANE" in bad.output
    # every solid of every object: its 9 BuildingPart solids, not the 4 one per Building gave
    assert "8 of 9 solids valid in 9 city objects" in bad.output and "(BuildingPart)" in bad.output
    # MultiSurface buildings have no solid: counted, not passed as "0 of 0 solids valid", exit 1
    surfaces = CliRunner().invoke(cli, ["validate", str(shared("citymodels/rotterdam_subset.json"))])
    assert surfaces.exit_code == 1 and "16 MultiSurface geometries" in surfaces.output
    lods = CliRunner().invoke(cli, ["validate", str(shared("citymodels/multi_lod.json"))])
    assert lods.exit_code == 0 and "30 of 30 solids valid" in lods.output


def test_change_detection_outputs(tmp_path):
    """`run --old-buildings` and `recon3d change` write the change products, all readable."""
    import json

    import jsonschema
    from conftest import BDUNI, CITYJSON_SCHEMA

    out = tmp_path / "out"
    result = _run([shared(IGN), "-o", out, "--old-buildings", shared(BDUNI)])
    assert result.exit_code == 0, result.output
    changes = json.loads((out / "changes.geojson").read_text())
    classes = [f["properties"]["class"] for f in changes["features"]]
    assert classes.count("not_observed") == 34  # BD Uni footprints off the LiDAR tile: no data, not demolished
    assert "demolished" not in classes
    doc = json.loads((out / "buildings_updated.city.json").read_text())
    assert not list(jsonschema.Draft7Validator(json.loads(shared(CITYJSON_SCHEMA).read_text())).iter_errors(doc))
    assert "Changes against the older building database" in (out / "report.html").read_text()
    _assert_help_lists(out)  # changes.geojson, changes.tif, buildings_updated.city.json too
    again = CliRunner().invoke(cli, ["change", str(out), "--old-buildings", str(shared(BDUNI))])
    assert again.exit_code == 1 and "--overwrite" in again.output
    again = CliRunner().invoke(cli, ["change", str(out), "--old-buildings", str(shared(BDUNI)), "--overwrite"])
    assert again.exit_code == 0 and "not_observed 34" in again.output


def test_export_keeps_every_solid_or_says_why(tmp_path):
    """Den Haag's 9 BuildingPart solids became 4; Rotterdam's MultiSurface buildings were written empty."""
    import json
    import shutil

    import jsonschema
    from conftest import CITYJSON_SCHEMA

    for name in ("DH_01_subs.city.json", "rotterdam_subset.json"):
        folder = tmp_path / name.split(".")[0]
        folder.mkdir()
        shutil.copy(shared(f"citymodels/{name}"), folder / "buildings.city.json")
    dh = CliRunner().invoke(cli, ["export", str(tmp_path / "DH_01_subs"), "--format", "cityjson",
                                  "-o", str(tmp_path / "dh.city.json")])
    assert dh.exit_code == 0 and "9 solids" in dh.output
    check = CliRunner().invoke(cli, ["validate", str(tmp_path / "dh.city.json")])
    assert "of 9 solids valid" in check.output
    # MultiSurface buildings are exported as surfaces: every surface with an area, in every format
    source = json.loads(shared("citymodels/rotterdam_subset.json").read_text())
    vertices = np.asarray(source["vertices"]) * source["transform"]["scale"]
    rings = [vertices[surface[0]] for obj in source["CityObjects"].values() for g in obj["geometry"]
             for surface in g["boundaries"]]
    with_area = sum(len(np.unique(r, axis=0)) >= 3 for r in rings)  # 12 of the 248 collapse to a line or a point
    for fmt, name in (("cityjson", "r.city.json"), ("obj", "r.obj"), ("glb", "r.glb")):
        result = CliRunner().invoke(cli, ["export", str(tmp_path / "rotterdam_subset"), "--format", fmt,
                                          "-o", str(tmp_path / name)])
        assert result.exit_code == 0 and "16 buildings: 16 MultiSurface" in result.output, result.output
    doc = json.loads((tmp_path / "r.city.json").read_text())
    assert not list(jsonschema.Draft7Validator(json.loads(shared(CITYJSON_SCHEMA).read_text())).iter_errors(doc))
    geoms = [g for obj in doc["CityObjects"].values() for g in obj["geometry"]]
    assert len(geoms) == 16 and {g["type"] for g in geoms} == {"MultiSurface"}
    assert sum(len(g["boundaries"]) for g in geoms) == with_area
    assert (tmp_path / "r.obj").read_text().count("\nf ") >= with_area
    check = CliRunner().invoke(cli, ["validate", str(tmp_path / "r.city.json")])
    assert check.exit_code == 1 and "16 MultiSurface geometries" in check.output  # surfaces, never passed as solids


# -- issue 21 item 6: verbosity after the subcommand, evaluate, export, run --help ------------


@pytest.fixture
def restore_logging():
    """Leave the recon3d logger as the test found it (the CLI replaces its handler and level)."""
    import logging

    logger = logging.getLogger("recon3d")
    saved = logger.level, list(logger.handlers)
    yield logger
    logger.setLevel(saved[0])
    logger.handlers[:] = saved[1]


def test_verbosity_after_the_subcommand(restore_logging, tmp_path):
    import logging

    city = str(shared("citymodels/multi_lod.json"))
    for args, level in ((["validate", city, "-v"], logging.INFO), (["validate", city, "-vv"], logging.DEBUG),
                        (["-v", "validate", city, "-v"], logging.DEBUG), (["validate", city, "-q"], logging.ERROR),
                        (["-v", "validate", city, "-q"], logging.WARNING)):
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 0, (args, result.output)
        assert restore_logging.level == level, args
    out = tmp_path / "out"
    for flag in ("-v", "-q", "--verbose", "--quiet"):  # run takes them after its arguments too
        result = CliRunner().invoke(cli, ["run", str(tmp_path / "nope.laz"), "-o", str(out), flag])
        _assert_clean_failure(result, out, "nope.laz", "not found")
    assert "-v, --verbose" in CliRunner().invoke(cli, ["evaluate", "ground", "--help"]).output


def _shifted_las(source, target, dx: float):
    """A copy of a LAS/LAZ file moved ``dx`` CRS units east."""
    import laspy

    las = laspy.read(source)
    las.header.offsets = las.header.offsets + [dx, 0, 0]
    las.x = las.x + dx
    las.write(target)
    return target


def _refused_overlap(args, json_path):
    result = CliRunner().invoke(cli, [*map(str, args), "--json", str(json_path)])
    assert result.exit_code == 1, result.output
    line = result.output.strip()
    assert line.startswith("recon3d: error:") and "does not overlap" in line and "\n" not in line, result.output
    assert not json_path.exists()


def test_evaluate_refuses_a_reference_elsewhere(ign_run, tmp_path):
    """A reference 10 km away (or in another CRS) printed zeros and exited 0."""
    import shapely.affinity
    from affine import Affine

    from recon3d.core.geo import parse_crs
    from recon3d.core.raster import Raster
    from recon3d.io.geotiff import read_raster, write_raster
    from recon3d.io.vectors import read_footprints, write_features

    out = ign_run.out_dir
    far_las = _shifted_las(shared(IGN), tmp_path / "far.laz", 10000.0)
    _refused_overlap(["evaluate", "ground", out / "cloud.laz", "--reference", far_las], tmp_path / "g.json")
    _refused_overlap(["evaluate", "buildings", out, "--reference", far_las], tmp_path / "b.json")
    crs = parse_crs("EPSG:2154")
    fps, _ = read_footprints(shared(BDUNI), crs=crs)
    far = tmp_path / "far.geojson"
    write_features(far, [shapely.affinity.translate(f.polygon, 10000.0) for f in fps], [{"id": f.id} for f in fps], crs)
    _refused_overlap(["evaluate", "buildings", out, "--reference", far], tmp_path / "b.json")
    dtm = read_raster(out / "dtm.tif")  # the right reference, a DTM somewhere else
    far_dtm = tmp_path / "far_dtm.tif"
    write_raster(Raster(dtm.data, Affine.translation(10000.0, 0.0) @ dtm.transform, dtm.crs), far_dtm)
    _refused_overlap(["evaluate", "ground", out / "cloud.laz", "--reference", shared(IGN), "--dtm", far_dtm],
                     tmp_path / "g.json")


def test_evaluate_ground_table_is_aligned(ign_run):
    result = CliRunner().invoke(cli, ["evaluate", "ground", str(ign_run.out_dir / "cloud.laz"),
                                      "--reference", str(shared(IGN))])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    header, rows = lines[1], lines[2:]
    assert header.split()[:3] == ["product", "reference", "n"], header  # was "productreference"
    assert rows and all(len(r) == len(header) for r in rows), result.output  # right-aligned columns end together
    for r in rows:
        assert r[header.index("reference"):].startswith(("DTM from provider", "provider ground")), r
        assert r[: header.index("reference")].strip() == "DTM"


def test_export_gltf_writes_json(ign_run, tmp_path):
    import json

    import trimesh

    out = ign_run.out_dir
    for fmt, name in (("gltf", "b.gltf"), ("glb", "b.glb")):
        result = CliRunner().invoke(cli, ["export", str(out), "--format", fmt, "-o", str(tmp_path / name)])
        assert result.exit_code == 0, result.output
    assert (tmp_path / "b.glb").read_bytes()[:4] == b"glTF"
    doc = json.loads((tmp_path / "b.gltf").read_text(encoding="utf-8"))  # JSON, not GLB bytes
    assert doc["asset"]["version"] == "2.0"
    assert all(b["uri"].startswith("data:") for b in doc["buffers"])  # one file: no .bin beside it
    assert sorted(n["name"] for n in doc["nodes"]) == sorted(b.id for b in ign_run.city if b.solids)
    assert doc["scenes"][0]["extras"]["recon3d"]["crs"] == "EPSG:2154"
    as_json, as_glb = trimesh.load(tmp_path / "b.gltf"), trimesh.load(tmp_path / "b.glb")
    assert sorted(as_json.geometry) == sorted(as_glb.geometry)
    for key, mesh in as_json.geometry.items():
        assert np.array_equal(mesh.vertices, as_glb.geometry[key].vertices)
        assert np.array_equal(mesh.faces, as_glb.geometry[key].faces)
    # a name the format contradicts is refused, nothing written
    for fmt, name in (("gltf", "c.glb"), ("glb", "c.gltf")):
        result = CliRunner().invoke(cli, ["export", str(out), "--format", fmt, "-o", str(tmp_path / name)])
        assert result.exit_code == 1 and "--format" in result.output and not (tmp_path / name).exists()


def test_export_gltf_reads_in_pygltflib(ign_run, tmp_path):
    pygltflib = pytest.importorskip("pygltflib")
    result = CliRunner().invoke(cli, ["export", str(ign_run.out_dir), "--format", "gltf", "-o", str(tmp_path / "b.gltf")])
    assert result.exit_code == 0, result.output
    gltf = pygltflib.GLTF2().load(str(tmp_path / "b.gltf"))
    assert len(gltf.nodes) == sum(1 for b in ign_run.city if b.solids)
    assert gltf.binary_blob() is None or gltf.buffers[0].uri.startswith("data:")


def test_export_default_is_a_new_file(ign_run, tmp_path):
    """Without -o, 4 of the 5 formats named the run's own file and answered "exists"."""
    import hashlib
    import shutil

    out = tmp_path / "out"
    shutil.copytree(ign_run.out_dir, out)
    digest = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in out.iterdir() if p.is_file()}
    for fmt, name in (("cityjson", "buildings.city.json"), ("cityjsonseq", "buildings.city.jsonl"),
                      ("obj", "buildings.obj"), ("gltf", "buildings.gltf"), ("glb", "buildings.glb"), ("3dtiles", "buildings_3dtiles")):
        result = CliRunner().invoke(cli, ["export", str(out), "--format", fmt])
        assert result.exit_code == 0, (fmt, result.output)
        assert (out / "export" / name).exists() and str(out / "export" / name) in result.output
        again = CliRunner().invoke(cli, ["export", str(out), "--format", fmt])
        assert again.exit_code == 1 and "--overwrite" in again.output
    assert (out / "export" / "buildings.mtl").is_file()
    assert {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in out.iterdir() if p.is_file()} == digest


def _assert_help_lists(folder):
    """Every file a run wrote in ``folder`` is named in ``recon3d run --help``."""
    text = CliRunner().invoke(cli, ["run", "--help"]).output
    missing = [p.name for p in sorted(folder.iterdir()) if p.name not in text]
    assert not missing, f"run --help does not name {missing}"


def test_run_help_lists_every_output(ign_run):
    assert (ign_run.out_dir / "report.html").is_file()
    _assert_help_lists(ign_run.out_dir)
