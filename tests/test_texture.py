"""The building model textured from the images: which image each surface takes, where
its texture coordinates land, and the GLB that carries them (recon3d.stereo.texture,
recon3d.io.gltf.write_textured_glb).

The views are exact pinhole cameras whose images are colour ramps (red = column, green
= row), so the colour a texture coordinate picks tells the pixel it points at.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pyproj
import pytest
import shapely
from affine import Affine

from recon3d.buildings.extrude import lod1_solid
from recon3d.core.city import Building, CityModel
from recon3d.core.geo import LocalFrame
from recon3d.core.raster import Raster
from recon3d.io.gltf import GLTF_FROM_LOCAL, write_textured_glb
from recon3d.stereo.ortho import OrthoImage, View
from recon3d.stereo.texture import hidden, texture_city

TESTS = Path(__file__).parent
ORIGIN = np.array([500_000.0, 4_000_000.0, 100.0])
BOX = shapely.box(500_010.0, 4_000_010.0, 500_022.0, 4_000_018.0)  # 12 m east-west, 8 m north-south
GROUND, ROOF = 100.0, 109.0


def ramp(w: int, h: int) -> np.ndarray:
    """(h, w, 3) uint8: red the column, green the row, each over 0..255."""
    cols, rows = np.meshgrid(np.linspace(0, 255, w), np.linspace(0, 255, h))
    return np.dstack([cols, rows, np.full_like(cols, 128)]).round().astype(np.uint8)


def decode(texture: np.ndarray, uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(n, 2) pixel (col, row) of a ramp of ``size`` (w, h) read at texture coordinates ``uv``."""
    h, w = texture.shape[:2]
    c = np.clip(np.floor(uv[:, 0] * w).astype(int), 0, w - 1)
    r = np.clip(np.floor(uv[:, 1] * h).astype(int), 0, h - 1)
    rgb = texture[r, c].astype(float)
    return np.column_stack([rgb[:, 0] / 255 * (size[0] - 1), rgb[:, 1] / 255 * (size[1] - 1)])


def pinhole(name: str, centre, target, size=(400, 300), focal=300.0) -> View:
    """A pinhole camera at ``centre`` looking at ``target`` (world CRS), its image a ramp."""
    centre, target = np.asarray(centre, float), np.asarray(target, float)
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # world to camera: x right, y down, z forward
    w, h = size

    def project(x, y, z):
        xyz = np.stack([np.ravel(x), np.ravel(y), np.ravel(z)], axis=1) - centre
        cam = xyz @ rotation.T
        col = focal * cam[:, 0] / cam[:, 2] + (w - 1) / 2
        row = focal * cam[:, 1] / cam[:, 2] + (h - 1) / 2
        return col.reshape(np.shape(x)), row.reshape(np.shape(x))

    return View(name, ramp(w, h), project)


def ortho_ramp(cols: int = 300, rows: int = 200, cell: float = 0.2) -> OrthoImage:
    """An orthophoto over the box's surroundings whose colours are a ramp too."""
    data = np.moveaxis(ramp(cols, rows), -1, 0)
    transform = Affine(cell, 0.0, 500_000.0, 0.0, -cell, 4_000_030.0)
    return OrthoImage(data, np.ones((rows, cols), bool), np.zeros((rows, cols), np.int16), transform)


@pytest.fixture(scope="module")
def city() -> CityModel:
    frame = LocalFrame(tuple(ORIGIN))
    building = Building("b1", BOX, GROUND, ROOF, solids={"1": lod1_solid(BOX, GROUND, ROOF, frame)})
    return CityModel([building], pyproj.CRS.from_epsg(32631), frame)


# Both cameras stand south of the box, 60 m up: one to the east, one to the west.
EAST = ((500_060.0, 3_999_990.0, 160.0), (500_016.0, 4_000_014.0, 104.0))
WEST = ((499_972.0, 3_999_990.0, 160.0), (500_016.0, 4_000_014.0, 104.0))


def wall_normals(part) -> np.ndarray:
    """(m, 3) unit outward normals of a part's triangles (world axes)."""
    v = part.vertices[part.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_each_wall_takes_the_image_that_sees_it_and_points_at_it(city):
    views = [pinhole("east", *EAST), pinhole("west", *WEST)]
    model = texture_city(city, views, ortho_ramp())
    names = [t.name for t in model.textures]
    assert names[0] == "ortho"
    parts = {(model.textures[p.texture].name if p.texture >= 0 else None): p for p in model.parts["b1"]}
    # outward normals of the walls each image got: east image east (+x) and south (-y) walls
    east = wall_normals(parts["east"]).round(6)
    west = wall_normals(parts["west"]).round(6)
    assert {tuple(n) for n in east} <= {(1.0, 0.0, 0.0), (0.0, -1.0, 0.0)} and (east[:, 0] == 1).any()
    assert {tuple(n) for n in west} == {(-1.0, 0.0, 0.0)}  # the south wall went to the east image, seen larger
    # the north wall faces away from both cameras; the ground faces down: both untextured
    plain = wall_normals(parts[None]).round(6)
    assert {tuple(n) for n in plain} == {(0.0, 1.0, 0.0), (0.0, 0.0, -1.0)}
    # every textured corner points at the pixel its camera sees it in (ramps: 400 x 300)
    for view in views:
        part = parts[view.name]
        world = part.vertices + ORIGIN
        expected = np.column_stack(view.project(world[:, 0], world[:, 1], world[:, 2]))
        got = decode(model.textures[part.texture].image, part.uv, (400, 300))
        assert np.abs(got - expected).max() <= 1.5, np.abs(got - expected).max()
    # roof corners point at their place in the orthophoto (300 x 200 cells of 0.2 m)
    roof = parts["ortho"]
    world = roof.vertices + ORIGIN
    expected = np.column_stack([(world[:, 0] - 500_000.0) / 0.2 - 0.5, (4_000_030.0 - world[:, 1]) / 0.2 - 0.5])
    got = decode(model.textures[0].image, roof.uv, (300, 200))
    assert np.abs(got - expected).max() <= 1.5
    assert model.info["wall_surfaces"] == 4 and model.info["wall_surfaces_textured"] == 3
    assert model.info["wall_surfaces_from_ortho"] == 0  # 9 m walls are no steps


def dsm_with(*blocks) -> Raster:
    """A 0.5 m DSM of flat ground (height GROUND) with the box and ``blocks``
    ((xmin, ymin, xmax, ymax, top) each) standing on it."""
    cell, x0, y1 = 0.5, 499_990.0, 4_000_040.0
    rows, cols = 120, 160
    x = x0 + (np.arange(cols) + 0.5) * cell
    y = y1 - (np.arange(rows) + 0.5) * cell
    xx, yy = np.meshgrid(x, y)
    z = np.full((rows, cols), GROUND, np.float32)
    for xmin, ymin, xmax, ymax, top in [(*BOX.bounds, ROOF), *blocks]:
        z[(xx >= xmin) & (xx <= xmax) & (yy >= ymin) & (yy <= ymax)] = top
    return Raster(z, Affine(cell, 0.0, x0, 0.0, -cell, y1), pyproj.CRS.from_epsg(32631))


def test_a_wall_hidden_in_its_best_image_takes_the_next(city):
    """The south wall goes to the east image, which sees it larger. A 20 m hedge 3 m in
    front of it, to the east, stands on most lines of sight from the wall to the east
    camera and on none to the west one (nor on those from the east wall): given the DSM,
    the wall takes the west image. The box's own DSM hides none of its walls."""
    views = [pinhole("east", *EAST), pinhole("west", *WEST)]

    def south_wall_image(dsm):
        model = texture_city(city, views, ortho_ramp(), dsm=dsm)
        for p in model.parts["b1"]:
            if p.texture >= 0 and (wall_normals(p).round(6) == (0.0, -1.0, 0.0)).all(axis=1).any():
                return model.textures[p.texture].name, model.info["wall_surfaces_textured"]
        return None, model.info["wall_surfaces_textured"]

    assert south_wall_image(None) == south_wall_image(dsm_with()) == ("east", 3)
    hedge = (500_017.0, 4_000_006.0, 500_026.0, 4_000_007.0, GROUND + 20.0)
    assert south_wall_image(dsm_with(hedge)) == ("west", 3)
    assert not hidden(views[1], np.array([[500_016.0, 4_000_009.5, 104.0]]), dsm_with(hedge))[0]
    assert hidden(views[0], np.array([[500_016.0, 4_000_009.5, 104.0]]), dsm_with(hedge))[0]


def test_textures_over_the_limit_are_reduced_and_still_point_right(city):
    views = [pinhole("east", *EAST, size=(1600, 1200), focal=1200.0)]
    model = texture_city(city, views, ortho_ramp(), max_size=128)
    for texture, part in ((t, p) for p in model.parts["b1"] if p.texture >= 0 for t in [model.textures[p.texture]]):
        assert max(texture.image.shape[:2]) <= 128 and texture.reduced > 1
        if texture.name == "east":
            world = part.vertices + ORIGIN
            expected = np.column_stack(views[0].project(world[:, 0], world[:, 1], world[:, 2]))
            got = decode(texture.image, part.uv, (1600, 1200))
            # a reduced texel spans `reduced` pixels; the ramp's step is 1600 / 255 px
            assert np.abs(got - expected).max() <= texture.reduced + 1600 / 255, np.abs(got - expected).max()
    assert all(t["reduced"] > 1 for t in model.info["textures"])


def test_a_wall_seen_nearly_edge_on_stays_plain(city):
    """A camera 10 m east of the box and 100 m up sees its east wall from 84 degrees off
    its normal (a tenth of its frontal size): a smear, left untextured."""
    above = pinhole("above", (500_032.0, 4_000_014.0, 200.0), (500_016.0, 4_000_014.0, 100.0))
    model = texture_city(city, [above], ortho_ramp())
    assert model.info["wall_surfaces_textured"] == 0
    assert [model.textures[p.texture].name for p in model.parts["b1"] if p.texture >= 0] == ["ortho"]
    # walls of at most 1 m (steps between roof parts, parapets) take the orthophoto instead
    low = Building("b2", BOX, GROUND, GROUND + 0.8, solids={"1": lod1_solid(BOX, GROUND, GROUND + 0.8, city.frame)})
    model = texture_city(CityModel([low], city.crs, city.frame), [above], ortho_ramp())
    assert model.info["wall_surfaces_textured"] == model.info["wall_surfaces_from_ortho"] == 4
    (ortho_part,) = [p for p in model.parts["b2"] if p.texture == 0]
    assert len(ortho_part.faces) == 2 + 4 * 2  # the roof's two triangles and the four walls'


def read_glb(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and total == len(data)
    n, _ = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20:20 + n])
    if len(data) == 20 + n:  # no BIN chunk: nothing to store
        return doc, b""
    m, _ = struct.unpack_from("<II", data, 20 + n)
    return doc, data[28 + n:28 + n + m]


def test_textured_glb_is_valid_and_closes_the_solid_by_position(city, tmp_path):
    import trimesh

    views = [pinhole("east", *EAST), pinhole("west", *WEST)]
    model = texture_city(city, views, ortho_ramp())
    path = tmp_path / "textured.glb"
    write_textured_glb(city, model, path)
    doc, _ = read_glb(path)
    assert [n["name"] for n in doc["nodes"]] == ["b1"] and doc["nodes"][0]["extras"]["id"] == "b1"
    assert len(doc["images"]) == 3 and all(i["mimeType"] == "image/jpeg" for i in doc["images"])
    assert doc["scenes"][0]["extras"]["recon3d"]["origin"] == list(ORIGIN)
    scene = trimesh.load(path, force="scene")
    textured = [g for g in scene.geometry.values() if isinstance(g.visual, trimesh.visual.TextureVisuals)
                and g.visual.uv is not None]
    assert len(textured) == 3
    # welded by position, the primitives close the box again
    whole = trimesh.util.concatenate(list(scene.geometry.values()))
    whole.merge_vertices(merge_tex=True, merge_norm=True)
    assert whole.is_watertight and whole.is_winding_consistent
    assert whole.volume == pytest.approx(12.0 * 8.0 * 9.0, rel=1e-6)
    back = whole.vertices @ GLTF_FROM_LOCAL + ORIGIN  # glTF axes back to the CRS
    assert back.min(axis=0) == pytest.approx([500_010.0, 4_000_010.0, GROUND])
    node = shutil.which("node")
    if node is None or not (TESTS.parent / "tools" / "node_modules" / "gltf-validator").exists():
        pytest.skip("node or the gltf-validator package is missing (npm ci --prefix tools)")
    done = subprocess.run([node, str(TESTS / "gltf_validate.mjs"), str(path)], capture_output=True, text=True,
                          check=True)
    report = json.loads(done.stdout)[0]
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]


def test_a_city_without_solids_gives_an_empty_model_and_file(tmp_path):
    city = CityModel([Building("b1", BOX, GROUND, ROOF)], pyproj.CRS.from_epsg(32631), LocalFrame(tuple(ORIGIN)))
    model = texture_city(city, [pinhole("east", *EAST)], ortho_ramp())
    assert model.parts == {} and model.info["wall_surfaces"] == 0
    write_textured_glb(city, model, tmp_path / "empty.glb")
    doc, _ = read_glb(tmp_path / "empty.glb")
    assert doc["scenes"][0]["nodes"] == [] and "recon3d" in doc["scenes"][0]["extras"]
