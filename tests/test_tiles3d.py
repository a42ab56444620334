"""3D Tiles 1.1 export: a tileset that streams, placed on the globe, buildings as features.

Checked on a synthetic city of 400 buildings (quadtree, bounded tiles, metadata),
on the Delft and IGN runs (the product of ``recon3d run``, and the same buildings cut
into several tiles), by the Khronos glTF Validator (npm, installed in tools/) and
by the rules of :mod:`tiles3d_checks`.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pyproj
import pytest
import trimesh
from click.testing import CliRunner
from conftest import SHARED_DATA
from shapely.geometry import box
from test_io_exports import NAME, make_city, prism_solid
from tiles3d_checks import (
    Y_UP_TO_Z_UP,
    accessor,
    check_features,
    check_tileset,
    content_vertices,
    feature_table,
    tiles,
)

from recon3d.core.city import Building, CityModel
from recon3d.core.geo import LocalFrame, crs_units
from recon3d.io.obj import highest_lod
from recon3d.io.tiles3d import write_3dtiles

TESTS = Path(__file__).resolve().parent
OFFICIAL_SCHEMA = SHARED_DATA / "schemas" / "3d-tiles-1.1"


def grid_city(side: int = 20, spacing: float = 40.0) -> CityModel:
    """``side`` x ``side`` box buildings ``spacing`` m apart in UTM 31N, heights 5-24 m."""
    buildings = []
    for k in range(side * side):
        x, y = (k % side) * spacing, (k // side) * spacing
        foot = box(x, y, x + 12.0, y + 9.0)
        top = 5.0 + k % 20
        buildings.append(Building(f"g{k}", foot, ground_z=3.0, roof_z=3.0 + top,
                                  solids={"1": prism_solid(foot, 3.0, 3.0 + top)},
                                  attributes={"flat": k % 2 == 0, "floors": k % 7 or None}))
    return CityModel(buildings, pyproj.CRS("EPSG:32631"), LocalFrame((500000.0, 5700000.0, 0.0)))


def world_vertices(city: CityModel) -> dict[str, np.ndarray]:
    """(n, 3) world coordinates of each building's highest-LoD solid, by id."""
    out = {}
    for b in city.buildings:
        lod = highest_lod(b)
        if lod is not None:
            out[b.id] = city.frame.to_world(b.solids[lod].vertices)
    return out


def ecef_to_crs(ecef: np.ndarray, crs: pyproj.CRS) -> np.ndarray:
    """(n, 3) EPSG:4978 points back in ``crs`` (heights in its units), by pyproj."""
    lon, lat, h = pyproj.Transformer.from_crs(4978, 4979, always_xy=True).transform(*ecef.T)
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    x, y = pyproj.Transformer.from_crs(4326, horizontal, always_xy=True).transform(lon, lat)
    return np.column_stack([x, y, np.asarray(h) / crs_units(crs).vertical])


def tileset_vertices(checked: dict) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The root transform and, by building id, the (n, 3) EPSG:4978 corners of its triangles."""
    transform = np.asarray(checked["tileset"]["root"]["transform"]).reshape(4, 4).T
    out = {}
    for gltf, binary in checked["contents"].values():
        local = content_vertices(gltf, binary)
        ecef = local @ transform[:3, :3].T + transform[:3, 3]
        feature = check_features(gltf, binary)
        for k, row in enumerate(feature_table(gltf, binary)):
            out[row["id"]] = ecef[feature == k]
    return transform, out


def check_placement(folder: Path, city: CityModel, tol: float = 0.01) -> dict:
    """The tileset centre at the buildings' centre (< 1 m) and every corner where the
    building is in the CRS (< ``tol``), through pyproj both ways."""
    checked = check_tileset(folder)
    transform, by_id = tileset_vertices(checked)
    world = world_vertices(city)
    assert set(by_id) == set(world)
    everything = np.concatenate(list(world.values()))
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    centre = ecef_to_crs(transform[:3, 3][None], city.crs)[0]
    units = crs_units(city.crs)
    assert np.hypot(*(centre[:2] - 0.5 * (lo[:2] + hi[:2]))) * units.horizontal < 1.0
    assert abs(centre[2] - lo[2]) * units.vertical < 1.0
    for bid, ecef in by_id.items():
        back = ecef_to_crs(ecef, city.crs)
        d = np.min(np.linalg.norm(back[:, None, :] - world[bid][None], axis=2), axis=1)
        assert d.max() * units.horizontal < tol, bid  # every corner is a vertex of the solid
    return checked


def validate_with_gltf_validator(paths: list[Path]) -> list[dict]:
    """Reports of the Khronos glTF Validator (npm gltf-validator in tools/) on GLB files."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the glTF Validator cannot run")
    if not (TESTS.parent / "tools" / "node_modules" / "gltf-validator").is_dir():
        pytest.fail("the glTF Validator is not installed: run `npm ci --prefix tools` (README, Install)")
    done = subprocess.run([node, str(TESTS / "gltf_validate.mjs"), *map(str, paths)],
                          capture_output=True, text=True, check=True, timeout=300)
    reports = json.loads(done.stdout)
    for r in reports:
        unsupported = {m["message"].rsplit("'", 2)[1] for m in r["messages"] if m["code"] == "UNSUPPORTED_EXTENSION"}
        assert unsupported <= {"EXT_mesh_features", "EXT_structural_metadata"}, r
        assert r["errors"] == 0 and r["warnings"] == 0, r
    return reports


def check_contents(folder: Path) -> dict:
    """Every content passes the glTF Validator and loads in trimesh; the checked tileset."""
    checked = check_tileset(folder)
    uris = sorted(checked["contents"])
    validate_with_gltf_validator([folder / u for u in uris])
    for uri in uris:
        scene = trimesh.load(folder / uri, force="scene")
        (mesh,) = scene.geometry.values()
        gltf, _ = checked["contents"][uri]
        assert len(mesh.vertices) == gltf["accessors"][0]["count"]
    return checked


# --------------------------------------------------------------------------- synthetic


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    city = grid_city()
    folder = tmp_path_factory.mktemp("grid") / "buildings_3dtiles"
    write_3dtiles(city, folder, max_buildings=25)
    return city, folder


def test_3dtiles_quadtree_bounds_the_buildings_per_tile(grid):
    city, folder = grid
    checked = check_contents(folder)
    counts = {uri: gltf["extensions"]["EXT_structural_metadata"]["propertyTables"][0]["count"]
              for uri, (gltf, _) in checked["contents"].items()}
    assert len(counts) >= 16 and max(counts.values()) <= 25
    assert sum(counts.values()) == len(city)
    root = checked["tileset"]["root"]
    assert "content" not in root and root["refine"] == "ADD"
    leaves = [t for t, _ in tiles(root) if "content" in t]
    assert all(t["geometricError"] == 0 and "children" not in t for t in leaves)
    inner = [t for t, _ in tiles(root) if "children" in t]
    tallest, lowest = np.linalg.norm([12.0, 9.0, 24.0]), np.linalg.norm([12.0, 9.0, 5.0])  # building boxes
    assert root["geometricError"] == pytest.approx(tallest, rel=1e-3)  # metres on the ground: UTM's scale
    assert all(lowest < t["geometricError"] <= root["geometricError"] for t in inner)
    assert checked["tileset"]["geometricError"] > root["geometricError"]


def test_3dtiles_placed_on_the_globe(grid):
    city, folder = grid
    check_placement(folder, city)
    extras = json.loads((folder / "tileset.json").read_text())["extras"]["recon3d"]
    lon, lat = pyproj.Transformer.from_crs(32631, 4326, always_xy=True).transform(500000.0 + 386.0, 5700000.0 + 384.5)  # extent 772 x 769 m
    assert extras["centre"]["lon"] == pytest.approx(lon, abs=1e-8) and extras["centre"]["lat"] == pytest.approx(lat, abs=1e-8)
    assert extras["crs"] == "EPSG:32631" and "ellipsoidal" in extras["heights"]


def test_3dtiles_features_carry_the_building_attributes(grid):
    city, folder = grid
    checked = check_tileset(folder)
    rows = {r["id"]: r for gltf, binary in checked["contents"].values() for r in feature_table(gltf, binary)}
    for b in city.buildings:
        row = rows[b.id]
        assert row["lod"] == "1" and row["height"] == b.height and row["status"] == "ok"
        assert row["flat"] is b.attributes["flat"]  # a boolean every building has
        assert row.get("floors") == b.attributes["floors"]  # missing on some: noData
    gltf, _ = next(iter(checked["contents"].values()))
    props = gltf["extensions"]["EXT_structural_metadata"]["schema"]["classes"]["building"]["properties"]
    assert props["flat"]["type"] == "BOOLEAN" and props["floors"]["componentType"] == "FLOAT64"
    assert props["floors"]["noData"] == -9999.0 and props["id"]["required"] is True


def test_3dtiles_colours_normals_and_attributes(tmp_path):
    write_3dtiles(make_city(), tmp_path / "t")
    (content,) = check_tileset(tmp_path / "t")["contents"].values()
    gltf, binary = content
    normals = accessor(gltf, binary, 1).astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert len(np.unique(accessor(gltf, binary, 2), axis=0)) == 3  # roof, wall, ground
    up = (normals @ Y_UP_TO_Z_UP.T)[:, 2]
    assert np.isclose(up, 1.0, atol=1e-3).any() and np.isclose(up, -1.0, atol=1e-3).any()  # roofs, grounds
    rows = feature_table(gltf, binary)
    assert [r["id"] for r in rows] == ["cube", "ell", "yard"]  # the failed one has no solid
    assert rows[1]["name"] == NAME and rows[1]["lod"] == "2.2" and "gap" not in rows[1]
    assert gltf["nodes"][0]["extras"]["buildings"] == ["cube", "ell", "yard"]


def test_3dtiles_bytes_are_deterministic(grid, tmp_path):
    folder = grid[1]
    again = tmp_path / "again"
    write_3dtiles(grid_city(), again, max_buildings=25)
    files = sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert all((folder / f).read_bytes() == (again / f).read_bytes() for f in files)


def test_3dtiles_without_crs_or_solids(tmp_path):
    from recon3d.errors import CRSError

    city = make_city(crs=None)
    with pytest.raises(CRSError, match="no CRS"):
        write_3dtiles(city, tmp_path / "none")
    assert not (tmp_path / "none").exists() and not list(tmp_path.iterdir())
    failed = make_city()
    failed.buildings = failed.buildings[3:]  # only the failed building: no solid
    write_3dtiles(failed, tmp_path / "empty")
    doc = check_tileset(tmp_path / "empty")["tileset"]
    assert "content" not in doc["root"] and doc["extras"]["recon3d"]["buildings"] == 0


def test_3dtiles_official_schema_when_provided(grid):
    """Against the 3D Tiles 1.1 JSON schema files, where ../shared/data provides them.

    No npm package ships them or the official validator (2026-12: ``3d-tiles-validator``
    and ``@cesium/3d-tiles-validator`` are not in the registry; ``3d-tiles-tools`` 0.5.4
    has no validate command and no schema files); they live in the CesiumGS/3d-tiles
    repository, ``specification/schema/``.
    """
    import jsonschema
    from referencing import Registry, Resource

    if not (OFFICIAL_SCHEMA / "tileset.schema.json").is_file():
        pytest.skip(f"the official 3D Tiles 1.1 schema is not in {OFFICIAL_SCHEMA}")
    resources = [(p.relative_to(OFFICIAL_SCHEMA).as_posix(), Resource.from_contents(json.loads(p.read_text())))
                 for p in OFFICIAL_SCHEMA.rglob("*.schema.json")]
    registry = Registry().with_resources(resources)
    schema = json.loads((OFFICIAL_SCHEMA / "tileset.schema.json").read_text())
    doc = json.loads((grid[1] / "tileset.json").read_text())
    errors = list(jsonschema.Draft202012Validator(schema, registry=registry).iter_errors(doc))
    assert not errors, errors[0]


# --------------------------------------------------------------------------- real runs


@pytest.mark.slow
@pytest.mark.parametrize("fixture", ["delft_run", "ign_run"])
def test_3dtiles_of_a_run(fixture, request, tmp_path):
    state = request.getfixturevalue(fixture)
    folder = state.out_dir / "buildings_3dtiles"
    checked = check_contents(folder)
    assert len(checked["contents"]) == 1  # a village fits one tile of 32 buildings
    check_placement(folder, state.city)
    split = tmp_path / "split"
    write_3dtiles(state.city, split, max_buildings=2)
    checked = check_contents(split)
    assert len(checked["contents"]) >= 2
    check_placement(split, state.city)


@pytest.mark.slow
def test_export_3dtiles_command(delft_run, tmp_path):
    from recon3d.cli import cli

    dest = tmp_path / "tiles"
    result = CliRunner().invoke(cli, ["export", str(delft_run.out_dir), "--format", "3dtiles", "-o", str(dest)])
    assert result.exit_code == 0, result.output
    rows = [r for gltf, binary in check_tileset(dest)["contents"].values() for r in feature_table(gltf, binary)]
    assert sorted(r["id"] for r in rows) == sorted(b.id for b in delft_run.city if b.solids)
    assert {r["parent"] for r in rows if "parent" in r} == set(delft_run.city.blocks())
    again = CliRunner().invoke(cli, ["export", str(delft_run.out_dir), "--format", "3dtiles", "-o", str(dest)])
    assert again.exit_code == 1 and "--overwrite" in again.output
    over = CliRunner().invoke(cli, ["export", str(delft_run.out_dir), "--format", "3dtiles", "-o", str(dest),
                                    "--overwrite"])
    assert over.exit_code == 0, over.output
    check_placement(dest, delft_run.city)  # from the CityJSON's millimetres: the same places
