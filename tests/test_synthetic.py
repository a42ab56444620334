"""Synthetic cities: geometry truth, rendered stereo pair, COLMAP model and scene folder."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest
import shapely
from conftest import CITYJSON_SCHEMA, shared

from recon3d.io.checkpoints import read_checkpoints
from recon3d.io.geotiff import read_raster
from recon3d.synthetic.city import ROOF_TYPES, make_city, nice_cell_size
from recon3d.synthetic.render import Lighting, check_coverage, render, stereo_cameras
from recon3d.synthetic.scene import write_scene

SMALL = {"seed": 3, "size": 120.0, "gsd": 0.5, "image_size": (400, 300), "n_sparse": 150}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthetic") / "scene"
    return write_scene(folder, **SMALL)


def _project(rec: pycolmap.Reconstruction, image_id: int, xyz: np.ndarray) -> np.ndarray:
    """(n, 2) pixel coordinates of local points through pycolmap's own projection."""
    image = rec.image(image_id)
    cam = image.cam_from_world() * xyz
    return rec.camera(image.camera_id).img_from_cam(cam)


def test_city_contents():
    city = make_city(1, size=150.0)
    assert len(city.buildings) == 16
    assert {b.roof_type for b in city.buildings} == set(ROOF_TYPES)
    assert {b.plan for b in city.buildings} >= {"rectangle", "L", "T", "courtyard"}
    assert any(len(b.footprint.interiors) == 1 for b in city.buildings)
    polys = [b.footprint for b in city.buildings]
    gaps = [a.distance(b) for i, a in enumerate(polys) for b in polys[i + 1 :]]
    assert min(gaps) > 4.0  # separate buildings, with streets or gardens between
    for b in city.buildings:
        mesh = b.solid.to_trimesh()
        assert mesh.is_watertight and mesh.volume > 0
        assert 4.0 <= b.eave_z - b.ground_z and b.height <= 25.0 + 1e-9
        assert b.footprint.bounds[0] > 500000.0  # world coordinates, UTM-sized
    assert len(city.trees) > 5


def test_camera_pair_not_rectified_and_fits():
    city = make_city(0, size=120.0)
    cams = stereo_cameras(np.array([60.0, 60.0, 50.0]), gsd=0.5, width=400, height=300)
    check_coverage(city, cams)
    assert not np.allclose(cams[0].R, cams[1].R)
    with pytest.raises(ValueError, match="does not fit"):
        check_coverage(make_city(0, size=200.0), cams)


def test_pixel_samples_integrate_the_light_over_the_pixel():
    """With ``pixel_samples`` 3 a pixel is close to the mean light over its area (a 7 x 7
    ray render as reference), as a sensor records it; one ray per pixel centre is not:
    the scene's finest texture aliases (a wide-angle view, 0.5 m pixels on 0.4 m texture).
    Measured: 1.6 DN RMS from the reference with 3 x 3 rays, 6.9 DN with one ray."""
    city = make_city(3, size=120.0)
    cam = stereo_cameras(np.array([60.0, 60.0, 0.0]), gsd=0.5, width=160, height=120, focal=120, base_to_height=0.8)[0]
    renders = {k: render(city, cam, lighting=Lighting(pixel_samples=k), seed=1) for k in (1, 3, 7)}
    rms = {k: float(np.sqrt(np.mean((renders[k].image.astype(float) - renders[7].image) ** 2))) for k in (1, 3)}
    assert rms[3] < 2.5 < 5.0 < rms[1]
    assert np.array_equal(renders[3].xyz, renders[1].xyz, equal_nan=True)  # surface points at pixel centres
    with pytest.raises(ValueError, match="pixel_samples"):
        Lighting(pixel_samples=0)


def test_pixel_convention_against_pycolmap(scene):
    """The surface point rendered at pixel (row, col) projects to (col + 0.5, row + 0.5)."""
    rec = pycolmap.Reconstruction(scene.folder / "sparse")
    rng = np.random.default_rng(0)
    for image_id, r in enumerate(scene.renders, start=1):
        rows = rng.integers(0, r.image.shape[0], 50)
        cols = rng.integers(0, r.image.shape[1], 50)
        xyz = r.xyz[rows, cols].astype(np.float64)
        uv = _project(rec, image_id, xyz)
        expected = np.column_stack([cols + 0.5, rows + 0.5])
        assert np.abs(uv - expected).max() < 0.01


def test_colmap_model(scene):
    rec = pycolmap.Reconstruction(scene.folder / "sparse")
    assert rec.num_images() == 2 and rec.num_points3D() >= 100
    names = {im.name for im in rec.images.values()}
    assert names == {"left.png", "right.png"}
    assert all(c.model_name == "PINHOLE" for c in rec.cameras.values())
    worst = 0.0
    for pid, point in rec.points3D.items():
        assert point.track.length() == 2
        for el in point.track.elements:
            observed = rec.image(el.image_id).points2D[el.point2D_idx].xy
            uv = _project(rec, el.image_id, point.xyz[None])
            worst = max(worst, float(np.abs(uv - observed).max()))
    assert worst < 0.01
    # not rectified: the rows of corresponding points differ
    assert np.abs(scene.sparse_uv[0, :, 1] - scene.sparse_uv[1, :, 1]).max() > 1.0
    georef = json.loads((scene.folder / "georef.json").read_text())
    assert georef["crs"] == "EPSG:32631" and georef["offset"][:2] == [500000.0, 5400000.0]


def test_truth_rasters(scene):
    dsm = read_raster(scene.folder / "truth" / "dsm.tif")
    dtm = read_raster(scene.folder / "truth" / "dtm.tif")
    assert dsm.transform == dtm.transform and dsm.resolution == nice_cell_size(0.5) == 0.5
    assert dsm.crs.to_epsg() == 32631
    assert np.isfinite(dsm.data).all() and np.isfinite(dtm.data).all()
    assert (dsm.data >= dtm.data - 1e-3).all()
    x, y = dsm.cell_centers()
    gx, gy = np.meshgrid(x, y)
    for b in scene.city.buildings:
        inside = shapely.contains_xy(b.footprint, gx, gy)
        assert inside.any()
        ndsm = dsm.data[inside] - dtm.data[inside]
        assert ndsm.min() >= 4.0
        assert abs(float(dsm.data[inside].max()) - b.ridge_z) < 0.6  # the ridge, to within a cell
    near = [shapely.contains_xy(b.footprint.buffer(1.0), gx, gy) for b in scene.city.buildings]
    free = ~np.any(near, axis=0)
    assert np.mean(np.abs(dsm.data[free] - dtm.data[free]) < 1e-3) > 0.7  # mostly bare ground


def test_truth_grids_in_row_blocks(scene, monkeypatch):
    """The truth grids are computed in blocks of rows to bound memory on large surveys:
    blocks of a few rows give the same cells as one block (and as the written files)."""
    from recon3d.synthetic import city as city_module
    from recon3d.synthetic.city import row_blocks, truth_dsm, truth_dtm
    from recon3d.synthetic.scene import views

    blocks = row_blocks((10, 7), cells=20)
    assert [(b.start, b.stop) for b in blocks] == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]
    assert [(b.start, b.stop) for b in row_blocks((3, 50), cells=20)] == [(0, 1), (1, 2), (2, 3)]
    dsm = read_raster(scene.folder / "truth" / "dsm.tif")
    grid = (scene.city, dsm.transform, dsm.shape)
    whole = truth_dsm(*grid), truth_dtm(*grid), views(scene.city, scene.cameras, dsm.data, dsm.transform)
    monkeypatch.setattr(city_module, "BLOCK_CELLS", 3 * dsm.shape[1] + 5)  # 3 rows at a time, a short last block
    assert len(row_blocks(dsm.shape)) > 10
    blocked = truth_dsm(*grid), truth_dtm(*grid), views(scene.city, scene.cameras, dsm.data, dsm.transform)
    for a, b in zip(whole, blocked, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(whole[0], dsm.data)
    np.testing.assert_array_equal(whole[2], read_raster(scene.folder / "truth" / "views.tif").data)


def test_checkpoints(scene):
    cp = read_checkpoints(scene.folder / "truth" / "checkpoints.csv")
    assert set(cp.kinds) == {"ground", "roof"}
    assert (cp.kinds == "roof").sum() == len(scene.city.buildings)
    ground = cp.kinds == "ground"
    assert ground.sum() >= 5
    z = scene.city.ground_height(cp.xyz[ground, 0], cp.xyz[ground, 1])
    assert np.abs(z - cp.xyz[ground, 2]).max() < 1e-3
    dsm = read_raster(scene.folder / "truth" / "dsm.tif")
    roof = ~ground
    top = dsm.sample(cp.xyz[roof, 0], cp.xyz[roof, 1], bilinear=False)
    assert np.abs(top - cp.xyz[roof, 2]).max() < 0.6


def test_cityjson_and_footprints_truth(scene):
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(shared(CITYJSON_SCHEMA).read_text())
    doc = json.loads((scene.folder / "truth" / "buildings.city.json").read_text())
    errors = list(jsonschema.Draft7Validator(schema).iter_errors(doc))
    assert not errors, errors[0].message
    lods = {g["lod"] for o in doc["CityObjects"].values() for g in o["geometry"]}
    assert lods == {"1", "2.2"}
    fp = json.loads((scene.folder / "truth" / "footprints.geojson").read_text())
    props = [f["properties"] for f in fp["features"]]
    assert {p["roof_type"] for p in props} <= set(ROOF_TYPES)
    assert all(p["ridge_z"] >= p["eave_z"] > p["ground_z"] for p in props)


def test_deterministic(scene, tmp_path):
    again = write_scene(tmp_path / "again", **SMALL)
    names = [
        "images/left.png",
        "images/right.png",
        "sparse/images.txt",
        "sparse/points3D.txt",
        "truth/dsm.tif",
        "truth/buildings.city.json",
        "truth/checkpoints.csv",
        "truth/trees.csv",
    ]
    for name in names:
        assert (scene.folder / name).read_bytes() == (again.folder / name).read_bytes(), name
    # write_features names the GeoJSON layer after its temporary file: compare the rest
    a, b = (json.loads((s.folder / "truth/footprints.geojson").read_text()) for s in (scene, again))
    a.pop("name", None), b.pop("name", None)
    assert a == b
    other = write_scene(tmp_path / "other", **{**SMALL, "seed": 4})
    assert (other.folder / names[0]).read_bytes() != (scene.folder / names[0]).read_bytes()
