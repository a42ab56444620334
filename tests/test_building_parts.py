"""Blocks split at height jumps: one CityJSON Building with BuildingPart children."""

from __future__ import annotations

import json

import numpy as np
import pyproj
import pytest
import shapely
import trimesh
from affine import Affine

from conftest import CITYJSON_SCHEMA, shared
from recon3d.buildings import blocks, detect, lod
from recon3d.config import BuildingsConfig
from recon3d.core.city import Building, CityModel
from recon3d.core.geo import LocalFrame, Units
from recon3d.core.raster import Raster
from recon3d.io.cityjson import cityjson_dict, read_cityjson, write_cityjson, write_cityjsonseq

UNITS = Units()
CFG = BuildingsConfig()
FEATURE_SCHEMA = "schemas/cityjson-2.0.2/cityjsonfeature.min.schema.json"


def _validator(name: str):
    import jsonschema

    return jsonschema.Draft7Validator(json.loads(shared(name).read_text(encoding="utf-8")))


def assert_valid(validator, doc: dict) -> None:
    errors = sorted(validator.iter_errors(doc), key=lambda e: list(e.absolute_path))
    assert not errors, "\n".join(f"{list(e.absolute_path)}: {e.message[:200]}" for e in errors[:5])


def detected_city() -> CityModel:
    """Detection on a synthetic nDSM: a block of two touching roofs 6 m and 12 m high
    (split at the jump), a stand-alone house, and two houses of one height 2 m apart.
    """
    data = np.zeros((80, 100), np.float32)
    data[10:40, 10:30] = 6.0
    data[10:40, 30:50] = 12.0
    data[55:70, 10:30] = 8.0  # stand-alone
    data[55:75, 50:65] = 9.0  # two houses, a 2 m gap between them
    data[55:75, 69:84] = 9.0
    ndsm = Raster(data, Affine(0.5, 0.0, 85000.0, 0.0, -0.5, 447000.0 + 80 * 0.5))
    veg = np.zeros(data.shape, bool)
    polygons = detect.detect_buildings(ndsm, veg, CFG, UNITS)
    labels = detect.label_footprints(polygons, ndsm)
    frame = LocalFrame.around((85000.0, 447000.0, 0.0))
    buildings = []
    for i, poly in enumerate(polygons):
        roof = float(np.median(data[labels == i + 1]))
        solids = {"1": lod.lod1_solid(poly, 0.0, roof, frame), "2.2": lod.lod1_solid(poly, 0.0, roof + 0.5, frame)}
        buildings.append(Building(f"b{i + 1:04d}", poly, 0.0, roof, solids, attributes={"source": "detected", "cells": i}))
    n = blocks.assign_blocks(buildings, labels, detect.building_mask(ndsm, veg, CFG, UNITS), min_shared=CFG.min_edge)
    assert n == 1
    return CityModel(buildings, pyproj.CRS("EPSG:7415"), frame)


def _block(city: CityModel) -> tuple[str, list[Building]]:
    ((bid, parts),) = city.blocks().items()
    return bid, parts


def test_detected_block_gets_a_parent():
    city = detected_city()
    assert len(city) == 5
    bid, parts = _block(city)
    assert bid == "block0001"
    assert sorted(b.roof_z for b in parts) == [6.0, 12.0]
    assert parts[0].footprint.touches(parts[1].footprint)
    alone = [b for b in city if b.parent is None]
    assert sorted(b.roof_z for b in alone) == [8.0, 9.0, 9.0]  # the 2 m gap separates two blocks


def test_assign_blocks_skips_used_ids_and_resets():
    city = detected_city()
    parts = _block(city)[1]
    parts[0].id = "block0001"  # an id a block would get
    labels = detect.label_footprints([b.footprint for b in city], _grid())
    blocks.assign_blocks(city.buildings, labels, labels > 0, min_shared=CFG.min_edge)
    assert set(city.blocks()) == {"block0002"}
    blocks.assign_blocks(city.buildings, labels, np.zeros(labels.shape, bool), min_shared=CFG.min_edge)
    assert city.blocks() == {}  # no raised region: nothing is a block


def _grid() -> Raster:
    return Raster(np.zeros((80, 100), np.float32), Affine(0.5, 0.0, 85000.0, 0.0, -0.5, 447000.0 + 80 * 0.5))


def test_split_block_written_as_building_and_parts():
    city = detected_city()
    doc = cityjson_dict(city)
    assert_valid(_validator(CITYJSON_SCHEMA), doc)
    objs = doc["CityObjects"]
    bid, parts = _block(city)
    ids = [p.id for p in parts]
    block = objs[bid]
    assert block["type"] == "Building" and block["children"] == ids and block["geometry"] == []
    a = block["attributes"]
    assert a["parts"] == 2 and a["status"] == "ok" and a["source"] == "detected"
    assert a["ground_z"] == 0.0 and a["roof_z"] == 12.0 and a["height"] == 12.0
    assert a["area"] == pytest.approx(sum(p.footprint.area for p in parts), abs=1e-3)
    assert "cells" not in a  # the parts disagree
    for p in parts:
        o = objs[p.id]
        assert o["type"] == "BuildingPart" and o["parents"] == [bid]
        assert [g["lod"] for g in o["geometry"]] == ["1", "2.2"]
        assert o["attributes"]["roof_z"] == p.roof_z and o["attributes"]["cells"] == p.attributes["cells"]
    singles = [o for o in objs.values() if o["type"] == "Building" and "children" not in o]
    assert len(singles) == 3 and all("parents" not in o and len(o["geometry"]) == 2 for o in singles)
    # the block comes just before its first part; the other objects keep the model's order
    order = list(objs)
    assert order.index(bid) == order.index(ids[0]) - 1
    assert [o for o in order if o != bid] == [b.id for b in city]


def test_split_block_round_trip(tmp_path):
    city = detected_city()
    write_cityjson(city, tmp_path / "a.city.json")
    back = read_cityjson(tmp_path / "a.city.json")
    assert [b.id for b in back] == [b.id for b in city]
    assert [b.parent for b in back] == [b.parent for b in city]
    for a, b in zip(city, back, strict=True):
        assert b.roof_z == pytest.approx(a.roof_z, abs=1e-3) and b.attributes["cells"] == a.attributes["cells"]
        assert set(b.solids) == {"1", "2.2"}
        assert b.solids["1"].to_trimesh().volume == pytest.approx(a.solids["1"].to_trimesh().volume, rel=1e-4)
        assert a.footprint.symmetric_difference(b.footprint).area < 0.01
        assert "parts" not in b.attributes  # block-wide attributes stay on the block
    # written again: the same document
    write_cityjson(back, tmp_path / "b.city.json")
    da, db = (json.loads((tmp_path / n).read_text()) for n in ("a.city.json", "b.city.json"))
    assert list(da["CityObjects"]) == list(db["CityObjects"])
    assert da["CityObjects"]["block0001"] == db["CityObjects"]["block0001"]
    # parts=False folds a block into one Building as for other files (first part's solid per LoD)
    merged = read_cityjson(tmp_path / "a.city.json", parts=False)
    assert len(merged) == 4 and "block0001" in [b.id for b in merged]
    assert all(b.parent is None for b in merged)


def test_split_block_cityjsonseq(tmp_path):
    city = detected_city()
    write_cityjsonseq(city, tmp_path / "a.city.jsonl")
    lines = [json.loads(line) for line in (tmp_path / "a.city.jsonl").read_text().splitlines()]
    assert len(lines) == 1 + 4  # header, the block with its two parts, three houses
    validator = _validator(FEATURE_SCHEMA)
    bid, parts = _block(city)
    for feature in lines[1:]:
        assert_valid(validator, feature)
        top = feature["CityObjects"][feature["id"]]
        assert "parents" not in top
        n = len(feature["vertices"])
        for obj in feature["CityObjects"].values():
            for g in obj["geometry"]:
                flat = np.asarray([i for s in g["boundaries"][0] for r in s for i in r])
                assert flat.min() >= 0 and flat.max() < n
    (block,) = [f for f in lines[1:] if f["id"] == bid]
    assert list(block["CityObjects"]) == [bid, *(p.id for p in parts)]
    back = read_cityjson(tmp_path / "a.city.jsonl")
    assert sorted((b.id, b.parent) for b in back) == sorted((b.id, b.parent) for b in city)
    total = sum(b.solids["2.2"].to_trimesh().volume for b in city)
    assert sum(b.solids["2.2"].to_trimesh().volume for b in back) == pytest.approx(total, rel=1e-4)


def test_failed_part_and_block_id_clash():
    city = detected_city()
    bid, parts = _block(city)
    parts[1].solids.clear()
    parts[1].status, parts[1].reason = "failed", "no_points"
    doc = cityjson_dict(city)
    assert_valid(_validator(CITYJSON_SCHEMA), doc)
    assert doc["CityObjects"][parts[1].id]["geometry"] == []
    assert doc["CityObjects"][bid]["attributes"]["status"] == "partial"
    city.buildings[-1].id = bid
    with pytest.raises(ValueError, match="duplicate"):
        cityjson_dict(city)


def test_glb_and_obj_name_parts_by_their_ids(tmp_path):
    from recon3d.io.gltf import write_glb
    from recon3d.io.obj import write_obj

    city = detected_city()
    write_glb(city, tmp_path / "a.glb")
    scene = trimesh.load(tmp_path / "a.glb")
    assert set(scene.graph.nodes_geometry) == {b.id for b in city}
    for b in city:
        extras = scene.geometry[b.id].metadata
        assert extras.get("parent") == b.parent, extras
    write_obj(city, tmp_path / "a.obj")
    names = [line[2:] for line in (tmp_path / "a.obj").read_text().splitlines() if line.startswith("o ")]
    assert names == [b.id for b in city]


def test_delft_split_blocks(delft_run):
    """The Delft strip: a block of roofs split at a height jump becomes Building + BuildingParts."""
    city = delft_run.city
    blocks = city.blocks()
    # measured: 10 buildings, one block (a 7 m and a 17 m roof, 3.4 m of shared wall)
    assert len(blocks) >= 1 and all(len(parts) >= 2 for parts in blocks.values())
    doc = json.loads((delft_run.out_dir / "buildings.city.json").read_text(encoding="utf-8"))
    assert_valid(_validator(CITYJSON_SCHEMA), doc)
    objs = doc["CityObjects"]
    part_ids = [oid for oid, o in objs.items() if o["type"] == "BuildingPart"]
    assert len(part_ids) == sum(len(p) for p in blocks.values())
    assert delft_run.report["buildings"]["blocks"] == len(blocks)
    assert "blocks of BuildingParts" in (delft_run.out_dir / "report.html").read_text(encoding="utf-8")
    for oid in part_ids:
        (parent,) = objs[oid]["parents"]
        assert objs[parent]["type"] == "Building" and oid in objs[parent]["children"]
        assert objs[oid]["geometry"]  # parts carry the solids
    for bid, parts in blocks.items():
        assert objs[bid]["children"] == [p.id for p in parts] and objs[bid]["geometry"] == []
        footprints = shapely.union_all([p.footprint.buffer(0.01) for p in parts])
        assert footprints.geom_type == "Polygon"  # the parts touch: one block outline
    tops = [oid for oid, o in objs.items() if o["type"] == "Building" and "children" not in o]
    assert len(tops) + len(part_ids) == len(city)
