"""CityJSON, GLB and OBJ exports of a small city model at UTM-sized coordinates."""

from __future__ import annotations

import json
import math
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pyproj
import pytest
import shapely
import trimesh
from shapely.geometry import Polygon, box

from recon3d.core.city import Building, CityModel, Solid
from recon3d.core.geo import LocalFrame
from recon3d.io.cityjson import cityjson_dict, crs_url, quantisation_scale, write_cityjson
from recon3d.io.gltf import GLTF_FROM_LOCAL, write_glb, write_gltf
from recon3d.io.obj import write_obj

SCHEMA = (
    Path(__file__).resolve().parents[1].parent
    / "shared/data/schemas/cityjson-2.0.2/cityjson.min.schema.json"
)
ORIGIN = (594000.0, 5765000.0, 0.0)
NAME = "Café Zürich – 北京"


def prism_solid(polygon: Polygon, z0: float, z1: float) -> Solid:
    """A vertical prism over ``polygon`` (holes allowed) from ``z0`` to ``z1``.

    Ground = reversed rings at z0, roof = rings at z1 (outer counter-clockwise from
    above, holes clockwise), one wall quad per ring edge, all facing outward.
    """
    polygon = shapely.orient_polygons(polygon)
    rings = [np.asarray(polygon.exterior.coords)[:-1, :2]]
    rings += [np.asarray(r.coords)[:-1, :2] for r in polygon.interiors]
    vertices, bottom, top, walls = [], [], [], []
    base = 0
    for xy in rings:
        n = len(xy)
        vertices += [np.column_stack([xy, np.full(n, z0)]), np.column_stack([xy, np.full(n, z1)])]
        b, t = np.arange(base, base + n), np.arange(base + n, base + 2 * n)
        bottom.append(b[::-1])
        top.append(t)
        walls += [[np.array([b[i], b[(i + 1) % n], t[(i + 1) % n], t[i]])] for i in range(n)]
        base += 2 * n
    surfaces = [bottom, top, *walls]
    semantics = ["GroundSurface", "RoofSurface"] + ["WallSurface"] * len(walls)
    return Solid(np.concatenate(vertices), surfaces, semantics)


L_SHAPE = Polygon(
    [(20.0004, 0.0), (32.0, 0.0), (32.0, 4.5), (24.5, 4.5), (24.5, 9.0), (20.0004, 9.0)]
)
COURTYARD = Polygon(
    box(40.0, 0.0, 52.0, 12.0).exterior, [box(44.0, 4.0, 48.0, 8.0).exterior.coords]
)


def make_city(crs: str | None = "EPSG:32631") -> CityModel:
    """Four buildings: a cube, an L-shape (LoD 1 and 2.2), a courtyard block, a failed one."""
    square = box(0, 0, 10, 10)
    cube = Building(
        "cube", square, ground_z=2.0, roof_z=12.0, solids={"1": prism_solid(square, 2.0, 12.0)}
    )
    ell = Building(
        "ell",
        L_SHAPE,
        ground_z=2.5,
        roof_z=8.25,
        solids={"1": prism_solid(L_SHAPE, 2.5, 8.25), "2.2": prism_solid(L_SHAPE, 2.5, 9.1234)},
        attributes={
            "name": NAME,
            "floors": np.int64(3),
            "area": np.float32(2.5),
            "gap": float("nan"),
        },
    )
    yard = Building(
        "yard", COURTYARD, ground_z=1.0, roof_z=7.0, solids={"1": prism_solid(COURTYARD, 1.0, 7.0)}
    )
    failed = Building("failed", box(60, 0, 65, 5), status="failed", reason="no_points")
    frame = LocalFrame(ORIGIN)
    return CityModel([cube, ell, yard, failed], pyproj.CRS(crs) if crs else None, frame)


@pytest.fixture(scope="module")
def validator():
    if not SCHEMA.exists():
        message = f"CityJSON schema not found: {SCHEMA}"
        if os.environ.get("CI") == "true":
            pytest.fail(message)
        pytest.skip(message)
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(SCHEMA.read_text(encoding="utf-8"))
    cls = jsonschema.validators.validator_for(schema)
    assert cls is jsonschema.Draft7Validator  # "$schema": draft-07
    return cls(schema, format_checker=cls.FORMAT_CHECKER)


def assert_valid(validator, doc: dict) -> None:
    errors = sorted(validator.iter_errors(doc), key=lambda e: list(e.absolute_path))
    assert not errors, "\n".join(f"{list(e.absolute_path)}: {e.message[:200]}" for e in errors[:5])


# --------------------------------------------------------------------------- CityJSON


def test_cityjson_validates_against_schema(validator):
    doc = cityjson_dict(make_city())
    assert doc["type"] == "CityJSON" and doc["version"] == "2.0"
    assert_valid(validator, doc)
    assert set(doc["CityObjects"]) == {"cube", "ell", "yard", "failed"}


def test_cityjson_vertices_dequantise_to_world_within_1mm():
    city = make_city()
    doc = cityjson_dict(city)
    t = doc["transform"]
    assert t["translate"] == list(ORIGIN) and t["scale"] == [0.001, 0.001, 0.001]
    vertices = np.asarray(doc["vertices"])
    assert vertices.dtype.kind == "i"
    world = vertices * t["scale"] + t["translate"]
    for b in city.buildings:
        geometry = doc["CityObjects"][b.id]["geometry"]
        for geom, (lod, solid) in zip(geometry, sorted(b.solids.items()), strict=True):
            assert geom["lod"] == lod
            for surface, rings in zip(geom["boundaries"][0], solid.surfaces, strict=True):
                for got, ring in zip(surface, rings, strict=True):
                    expected = city.frame.to_world(solid.vertices[ring])
                    np.testing.assert_allclose(world[got], expected, rtol=0, atol=0.0005 + 1e-9)


def test_cityjson_vertices_are_deduplicated():
    city = make_city()
    city.buildings.append(
        Building("twin", box(10, 0, 20, 10), solids={"1": prism_solid(box(10, 0, 20, 10), 2, 12)})
    )
    doc = cityjson_dict(city)
    vertices = np.asarray(doc["vertices"])
    assert len(np.unique(vertices, axis=0)) == len(vertices)
    n_input = sum(len(s.vertices) for b in city.buildings for s in b.solids.values())
    # the twin shares 4 corners with the cube, ell's LoD 1 and 2.2 their 6 ground corners
    assert len(vertices) == n_input - 4 - 6


def test_cityjson_geometry_lod_strings_and_semantics():
    doc = cityjson_dict(make_city())
    ell = doc["CityObjects"]["ell"]
    assert [g["lod"] for g in ell["geometry"]] == ["1", "2.2"]
    for geom in ell["geometry"]:
        assert geom["type"] == "Solid"
        surfaces, values = geom["semantics"]["surfaces"], geom["semantics"]["values"]
        assert [s["type"] for s in surfaces] == ["GroundSurface", "RoofSurface", "WallSurface"]
        assert len(values) == 1 and len(values[0]) == len(geom["boundaries"][0]) == 8
        assert values[0][:3] == [0, 1, 2]
    yard = doc["CityObjects"]["yard"]["geometry"][0]
    assert len(yard["boundaries"][0][0]) == 2  # ground with its courtyard hole


def test_cityjson_attributes_and_failed_building(validator):
    doc = cityjson_dict(make_city())
    ell = doc["CityObjects"]["ell"]["attributes"]
    assert ell == {
        "name": NAME,
        "floors": 3,
        "area": 2.5,
        "ground_z": 2.5,
        "roof_z": 8.25,
        "height": 5.75,
        "status": "ok",
    }
    assert type(ell["floors"]) is int and type(ell["area"]) is float
    failed = doc["CityObjects"]["failed"]
    assert failed["geometry"] == []
    assert failed["attributes"] == {"status": "failed", "reason": "no_points"}
    failed_only = [make_city().buildings[-1]]
    only_failed = CityModel(failed_only, pyproj.CRS("EPSG:32631"), LocalFrame(ORIGIN))
    doc = cityjson_dict(only_failed)
    assert doc["vertices"] == [] and "geographicalExtent" not in doc["metadata"]
    assert_valid(validator, doc)


def test_cityjson_metadata():
    city = make_city()
    extra = {
        "title": "Test blocks",
        "identifier": "run-42",
        "pointOfContact": {
            "contactName": "recon3d",
            "emailAddress": "nobody@example.org",
            "role": "processor",
        },
        "producer": "recon3d 0.1",  # not a CityJSON 2.0 metadata property: dropped
    }
    meta = cityjson_dict(city, extra)["metadata"]
    assert meta["referenceSystem"] == "https://www.opengis.net/def/crs/EPSG/0/32631"
    assert meta["title"] == "Test blocks" and meta["identifier"] == "run-42"
    assert meta["pointOfContact"]["role"] == "processor"
    assert "producer" not in meta
    assert len(meta["referenceDate"]) == 10
    city.metadata["referenceDate"] = "2014-03-04"  # the data's date, when the pipeline knows it
    assert cityjson_dict(city)["metadata"]["referenceDate"] == "2014-03-04"
    lo = np.array(ORIGIN) + [0.0, 0.0, 1.0]
    hi = np.array(ORIGIN) + [52.0, 12.0, 12.0]
    np.testing.assert_allclose(meta["geographicalExtent"], [*lo, *hi], atol=1e-6)


def test_crs_url_and_scale():
    assert crs_url(pyproj.CRS("EPSG:7415")) == "https://www.opengis.net/def/crs/EPSG/0/7415"
    assert crs_url(None) is None
    assert quantisation_scale(None).tolist() == [0.001] * 3
    feet = quantisation_scale(pyproj.CRS("EPSG:2994"))  # Oregon Lambert, international feet
    assert np.all(feet * 0.3048 <= 0.001) and np.allclose(np.log10(feet), np.round(np.log10(feet)))


def test_write_cityjson_utf8_roundtrip(tmp_path, validator):
    path = tmp_path / "out" / "buildings.city.json"
    write_cityjson(make_city(crs="EPSG:7415"), path, metadata={"title": "Blöcke"})
    raw = path.read_bytes()
    assert NAME.encode("utf-8") in raw  # ensure_ascii=False, UTF-8
    doc = json.loads(raw.decode("utf-8"))
    assert doc["CityObjects"]["ell"]["attributes"]["name"] == NAME
    assert doc["metadata"]["referenceSystem"].endswith("/EPSG/0/7415")
    assert_valid(validator, doc)
    assert [p.name for p in path.parent.iterdir()] == ["buildings.city.json"]  # no temp file left


def test_cityjson_duplicate_ids_rejected():
    city = make_city()
    city.buildings.append(city.buildings[0])
    with pytest.raises(ValueError, match="duplicate"):
        cityjson_dict(city)


# --------------------------------------------------------------------------- glTF


def glb_json(path: Path) -> dict:
    """The JSON chunk of a GLB file."""
    data = path.read_bytes()
    length, kind = struct.unpack("<II", data[12:20])
    assert kind == 0x4E4F534A  # "JSON"
    return json.loads(data[20 : 20 + length])


def test_glb_nodes_extras_and_origin(tmp_path):
    city = make_city(crs="EPSG:7415")
    path = tmp_path / "buildings.glb"
    write_glb(city, path)
    header = glb_json(path)
    nodes = {n["name"]: n for n in header["nodes"]}
    assert set(nodes) == {"cube", "ell", "yard"}  # the failed building has no solid
    assert nodes["ell"]["extras"]["name"] == NAME
    assert nodes["ell"]["extras"]["lod"] == "2.2"
    assert nodes["cube"]["extras"]["height"] == 10.0
    assert all("extras" in m and m["extras"]["id"] == m["name"] for m in header["meshes"])
    extras = header["scenes"][0]["extras"]["recon3d"]
    assert extras["origin"] == list(ORIGIN) and extras["crs"] == "EPSG:7415" and extras["up"] == "Y"
    # one primitive per building: shared vertices, the surface types as triangle ranges
    assert all(len(m["primitives"]) == 1 for m in header["meshes"])
    assert all(set(m["extras"]["surface_types"]) == {"GroundSurface", "WallSurface", "RoofSurface"} for m in header["meshes"])
    assert nodes["ell"]["extras"]["geometry_type"] == "Solid"

    scene = trimesh.load(path)
    assert sorted(scene.graph.nodes_geometry) == ["cube", "ell", "yard"]
    assert scene.metadata["recon3d"]["origin"] == list(ORIGIN)


def test_glb_is_y_up_local_float32(tmp_path):
    city = make_city()
    path = tmp_path / "buildings.glb"
    write_glb(city, path)
    scene = trimesh.load(path)
    for b in city.buildings[:3]:
        lod = max(b.solids, key=float)
        transform, name = scene.graph[b.id]
        np.testing.assert_allclose(transform, np.eye(4))
        mesh = scene.geometry[name]
        extent_y = mesh.bounds[1, 1] - mesh.bounds[0, 1]
        solid = b.solids[lod]
        zmin, zmax = solid.vertices[:, 2].min(), solid.vertices[:, 2].max()
        assert extent_y == pytest.approx(zmax - zmin, abs=1e-5)
        if lod == "1":
            assert extent_y == pytest.approx(b.height, abs=1e-5)
        expected = np.unique(solid.vertices @ GLTF_FROM_LOCAL.T, axis=0)
        got = np.unique(np.asarray(mesh.vertices, dtype=np.float64), axis=0)
        np.testing.assert_allclose(got, expected.astype(np.float32), rtol=0, atol=1e-5)
        # a proper rotation keeps the faces outward: same positive volume
        assert mesh.volume == pytest.approx(solid.to_trimesh().volume, rel=1e-5)
        assert mesh.is_watertight and mesh.is_winding_consistent  # as loaded, nothing merged
        assert len(mesh.vertices) == len(expected)  # one vertex per position
        roof_first, roof_count = mesh.metadata["surface_types"]["RoofSurface"]
        assert (mesh.face_normals[roof_first : roof_first + roof_count, 1] > 0.99).all()  # roofs face +Y


def test_glb_passes_the_gltf_validator_without_any_message(tmp_path):
    path = tmp_path / "buildings.glb"
    write_glb(make_city(crs="EPSG:7415"), path)
    node = shutil.which("node")
    tests = Path(__file__).parent
    if node is None or not (tests.parent / "tools" / "node_modules" / "gltf-validator").exists():
        pytest.skip("node or the gltf-validator package is missing (npm ci --prefix tools)")
    done = subprocess.run([node, str(tests / "gltf_validate.mjs"), str(path)], capture_output=True, text=True,
                          check=True, timeout=300)
    report = json.loads(done.stdout)[0]
    assert report["errors"] == report["warnings"] == report["infos"] == 0 and report["messages"] == [], report


def test_gltf_json_holds_the_glb_scene(tmp_path):
    city = make_city(crs="EPSG:7415")
    write_glb(city, tmp_path / "b.glb")
    write_gltf(city, tmp_path / "b.gltf")
    doc = json.loads((tmp_path / "b.gltf").read_text(encoding="utf-8"))
    assert doc["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")  # nothing beside the file
    binary, text = trimesh.load(tmp_path / "b.glb"), trimesh.load(tmp_path / "b.gltf")
    assert sorted(text.geometry) == sorted(binary.geometry) == ["cube", "ell", "yard"]
    for name, mesh in binary.geometry.items():
        np.testing.assert_array_equal(text.geometry[name].vertices, mesh.vertices)
        np.testing.assert_array_equal(text.geometry[name].faces, mesh.faces)
        assert text.geometry[name].metadata["surface_types"] == mesh.metadata["surface_types"]
    assert text.metadata["recon3d"] == binary.metadata["recon3d"]
    city.buildings = [city.buildings[-1]]  # only the failed building: an empty scene, still a glTF
    write_gltf(city, tmp_path / "empty.gltf")
    assert json.loads((tmp_path / "empty.gltf").read_text(encoding="utf-8"))["scenes"][0]["nodes"] == []


# --------------------------------------------------------------------------- OBJ


def test_obj_volume_bounds_and_materials(tmp_path):
    city = make_city(crs="EPSG:7415")
    path = tmp_path / "buildings.obj"
    write_obj(city, path)
    mtl = path.with_suffix(".mtl").read_text(encoding="utf-8")
    solid = [b.id for b in city.buildings if b.solids]
    assert [line[7:] for line in mtl.splitlines() if line.startswith("newmtl ")] == solid  # one per building
    text = path.read_text(encoding="utf-8")
    assert "# CRS: EPSG:7415" in text and "594000.000000 5765000.000000" in text
    objects = [line for line in text.splitlines() if line.startswith("o ")]
    assert objects == ["o cube", "o ell", "o yard"]

    per_building = trimesh.load(path, process=False)  # trimesh's default groups by material: per building
    assert sorted(per_building.geometry) == ["cube", "ell", "yard"]
    assert all(m.is_watertight and m.is_winding_consistent for m in per_building.geometry.values())
    mesh = trimesh.load(path, force="mesh")
    volumes = [b.solids[max(b.solids, key=float)].to_trimesh().volume for b in city.buildings[:3]]
    expected = 100 * 10 + L_SHAPE.area * (9.1234 - 2.5) + COURTYARD.area * 6
    assert sum(volumes) == pytest.approx(expected, rel=1e-9)
    assert mesh.volume == pytest.approx(expected, rel=1e-6)
    np.testing.assert_allclose(mesh.bounds, [[0, 0, 1], [52, 12, 12]], atol=1e-6)
    assert math.isclose(mesh.bounds[0, 0], 0.0, abs_tol=1e-9)


def test_cityjson_ring_cleaned_when_quantisation_merges_vertices():
    solid = prism_solid(box(0, 0, 1, 1), 0.0, 1.0)
    ground = solid.surfaces[0][0]  # (k,) ring; add a point 0.2 mm after its last vertex
    vertices = np.vstack([solid.vertices, solid.vertices[ground[-1]] + [0.0002, 0.0, 0.0]])
    surfaces = [[np.r_[ground, len(vertices) - 1]], *solid.surfaces[1:]]
    merged = Solid(vertices, surfaces, solid.semantics)
    building = Building("q", box(0, 0, 1, 1), solids={"1": merged})
    doc = cityjson_dict(CityModel([building], None, LocalFrame(ORIGIN)))
    assert len(doc["vertices"]) == 8
    assert len(doc["CityObjects"]["q"]["geometry"][0]["boundaries"][0][0][0]) == 4


def test_glb_and_obj_without_any_solid(tmp_path):
    city = make_city()
    city.buildings = [city.buildings[-1]]  # only the failed building
    write_glb(city, tmp_path / "empty.glb")
    extras = glb_json(tmp_path / "empty.glb")["scenes"][0]["extras"]
    assert extras["recon3d"]["origin"] == list(ORIGIN)
    assert len(trimesh.load(tmp_path / "empty.glb").geometry) == 0
    write_obj(city, tmp_path / "empty.obj")
    assert "o " not in (tmp_path / "empty.obj").read_text(encoding="utf-8")
    assert (tmp_path / "empty.mtl").exists()


def test_cityjson_vertex_deduplication_matches_numpys_row_unique():
    from recon3d.io.cityjson import _unique_rows

    rng = np.random.default_rng(3)
    q = rng.integers(-50, 50, (5000, 3))  # many repeats
    huge = q * np.int64(2**40)  # a span no single int64 key holds: the row-wise path
    for rows in (q, huge):
        got, want = _unique_rows(rows), np.unique(rows, axis=0, return_index=True, return_inverse=True)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a.reshape(-1), b.reshape(-1))
