"""RPC camera model on the real Pleiades Giza pair (CNES shareloc test data)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning
from rasterio.transform import Affine, RPCTransformer

from conftest import shared
from recon3d.errors import InputError
from recon3d.io.rpc import RPCCamera, RPCModel, read_rpc_camera

IMG1 = "stereo/pleiades_gizeh/img1.tif"
IMG2 = "stereo/pleiades_gizeh/img2.tif"
GEOM1 = "stereo/pleiades_gizeh/img1.geom"
OFFSETS = {IMG1: (20500.0, 5000.0), IMG2: (20501.0, 5476.0)}  # (col0, row0) in the full scene


@pytest.fixture(scope="module")
def cams():
    return {rel: read_rpc_camera(shared(rel)) for rel in (IMG1, IMG2)}


def _pixel_grid(cam: RPCCamera, n: int = 21):
    rows, cols = np.meshgrid(
        np.linspace(-0.5, cam.height - 0.5, n), np.linspace(-0.5, cam.width - 0.5, n), indexing="ij"
    )
    return rows, cols


def test_reads_the_crops(cams):
    for rel, (col0, row0) in OFFSETS.items():
        cam = cams[rel]
        assert (cam.col0, cam.row0) == (col0, row0)
        with rasterio.open(shared(rel)) as src:
            assert (cam.width, cam.height) == (src.width, src.height)
        assert cam.model.height_range == (10.0, 270.0)
        assert cam.name == rel.rsplit("/", 1)[1].removesuffix(".tif")


@pytest.mark.parametrize("rel", [IMG1, IMG2])
def test_localize_then_project_round_trip(cams, rel):
    cam = cams[rel]
    rows, cols = _pixel_grid(cam)
    for h in (10.0, 60.0, 140.0, 270.0):
        lon, lat = cam.localize(rows, cols, h)
        assert lon.shape == rows.shape and np.all(np.isfinite(lon)) and np.all(np.isfinite(lat))
        r, c = cam.project(lon, lat, h)
        assert np.abs(r - rows).max() < 0.01
        assert np.abs(c - cols).max() < 0.01
    # heights varying per point broadcast too
    hs = np.linspace(10.0, 270.0, rows.size).reshape(rows.shape)
    lon, lat = cam.localize(rows, cols, hs)
    r, c = cam.project(lon, lat, hs)
    assert max(np.abs(r - rows).max(), np.abs(c - cols).max()) < 0.01


@pytest.mark.parametrize("rel", [IMG1, IMG2])
def test_project_then_localize_round_trip(cams, rel):
    cam = cams[rel]
    rows, cols = _pixel_grid(cam, 11)
    lon0, lat0 = cam.localize(rows, cols, 100.0)
    # perturb the ground points so they are not exactly the localised ones
    lon = lon0 + 1e-5 * np.sin(np.arange(lon0.size)).reshape(lon0.shape)
    lat = lat0 + 1e-5 * np.cos(np.arange(lat0.size)).reshape(lat0.shape)
    for h in (20.0, 100.0, 250.0):
        r, c = cam.project(lon, lat, h)
        lon2, lat2 = cam.localize(r, c, h)
        assert np.abs(lon2 - lon).max() < 1e-7
        assert np.abs(lat2 - lat).max() < 1e-7


def test_matches_gdal_rpc_transformer():
    """Independent check of term order and pixel convention: GDAL's RPC transformer
    puts (0, 0) at the top-left pixel corner, recon3d at its centre."""
    model = RPCModel.from_geom(shared(GEOM1))
    lon = np.array([31.13, 31.10, 31.20, 31.05])
    lat = np.array([29.978, 29.95, 30.00, 29.93])
    h = np.array([60.0, 10.0, 250.0, 140.0])
    row, col = model.project(lon, lat, h)
    with RPCTransformer(model.to_rasterio()) as gdal:
        grow, gcol = gdal.rowcol(lon, lat, zs=h, op=lambda x: x)
        glon, glat = gdal.xy(row, col, zs=h, offset="center")
    np.testing.assert_allclose(np.asarray(grow) - 0.5, row, atol=1e-6)
    np.testing.assert_allclose(np.asarray(gcol) - 0.5, col, atol=1e-6)
    np.testing.assert_allclose(glon, lon, atol=1e-6)  # GDAL's own inverse is looser
    np.testing.assert_allclose(glat, lat, atol=1e-6)


def test_crop_offset_applied(cams):
    rows, cols = np.array([0.0, 400.0, 800.0]), np.array([0.0, 400.0, 799.0])
    lon, lat = cams[IMG1].localize(rows, cols, 80.0)
    for rel, (col0, row0) in OFFSETS.items():
        cam = cams[rel]
        full_row, full_col = cam.model.project(lon, lat, 80.0)
        row, col = cam.project(lon, lat, 80.0)
        np.testing.assert_array_equal(row, full_row - row0)
        np.testing.assert_array_equal(col, full_col - col0)
        # localize from crop pixels equals localize from the full-scene pixels
        lon2, lat2 = cam.model.localize(full_row, full_col, 80.0)
        lon3, lat3 = cam.localize(row, col, 80.0)
        np.testing.assert_allclose(lon3, lon2, atol=1e-10)
        np.testing.assert_allclose(lat3, lat2, atol=1e-10)


def test_both_crops_see_the_plateau(cams):
    """The central part of img1, localised at plateau heights, falls inside img2."""
    c1, c2 = cams[IMG1], cams[IMG2]
    rows, cols = np.meshgrid(np.linspace(200, 600, 5), np.linspace(200, 600, 5), indexing="ij")
    for h in (60.0, 80.0, 100.0, 140.0, 200.0):
        lon, lat = c1.localize(rows, cols, h)
        assert np.all(c1.in_domain(lon, lat, h))
        r2, col2 = c2.project(lon, lat, h)
        assert np.all(c2.contains(r2, col2))
        # the pair is offset mostly along rows (an along-track stereo pair)
        assert np.all(np.abs(col2 - cols) < 10.0)
        assert np.all((r2 - rows > 10.0) & (r2 - rows < 70.0))
    # the epipolar direction: one img1 pixel at rising heights moves down the rows of img2
    hs = np.array([0.0, 100.0, 200.0])
    lon, lat = c1.localize(np.full(3, 400.0), np.full(3, 400.0), hs)
    r2, col2 = c2.project(lon, lat, hs)
    drow, dcol = np.diff(r2), np.diff(col2)
    assert np.all((drow > 15.0) & (drow < 18.0))  # ~16.35 px per 100 m
    assert np.all(np.abs(dcol) < 1.0)


def test_ground_sample_distance(cams):
    for cam in cams.values():
        rows, cols = np.array([400.0, 400.0, 401.0]), np.array([400.0, 401.0, 400.0])
        lon, lat = cam.localize(rows, cols, 80.0)
        m_lat = 111_320.0
        m_lon = m_lat * np.cos(np.radians(lat[0]))
        step_col = np.hypot((lon[1] - lon[0]) * m_lon, (lat[1] - lat[0]) * m_lat)
        step_row = np.hypot((lon[2] - lon[0]) * m_lon, (lat[2] - lat[0]) * m_lat)
        assert 0.45 < step_col < 0.65 and 0.45 < step_row < 0.65  # Pleiades panchromatic ~0.5 m


def test_in_domain_flags_outside_points(cams):
    model = cams[IMG1].model
    lon0, lat0, h0 = model.lon_off, model.lat_off, model.height_off
    lon = np.array([lon0, lon0 + 2 * model.lon_scale, lon0, lon0, lon0 + 1.005 * model.lon_scale])
    lat = np.array([lat0, lat0, lat0 - 2 * model.lat_scale, lat0, lat0])
    h = np.array([h0, h0, h0, 1000.0, h0])
    np.testing.assert_array_equal(model.in_domain(lon, lat, h), [True, False, False, False, True])
    strict = model.in_domain(lon, lat, h, margin=0.0)
    np.testing.assert_array_equal(strict, [True, False, False, False, False])
    assert not model.in_domain(lon0, lat0, -500.0)


def test_localize_handles_nan_and_scalars(cams):
    cam = cams[IMG1]
    lon, lat = cam.localize(np.array([np.nan, 10.0]), np.array([5.0, 10.0]), 60.0)
    assert np.isnan(lon[0]) and np.isnan(lat[0]) and np.isfinite(lon[1])
    lon, lat = cam.localize(10.0, 20.0, 60.0)
    assert np.ndim(lon) == 0
    r, c = cam.project(lon, lat, 60.0)
    assert abs(r - 10.0) < 1e-6 and abs(c - 20.0) < 1e-6


def test_deterministic(cams):
    cam = read_rpc_camera(shared(IMG1))
    rows, cols = _pixel_grid(cam, 7)
    a = cam.localize(rows, cols, 75.0)
    b = cams[IMG1].localize(rows, cols, 75.0)
    np.testing.assert_array_equal(a, b)
    assert cam.model.same_as(cams[IMG1].model)
    assert not cam.model.same_as(cams[IMG2].model)


def _write_tif(path, *, transform=Affine.identity(), rpcs=None):
    profile = dict(driver="GTiff", width=8, height=6, count=1, dtype="float32", transform=transform)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)  # identity transform
        with rasterio.open(path, "w", rpcs=rpcs, **profile) as dst:
            dst.write(np.zeros((1, 6, 8), dtype=np.float32))


def test_image_without_rpc_is_an_input_error(tmp_path):
    path = tmp_path / "plain.tif"
    _write_tif(path)
    with pytest.raises(InputError, match="plain.tif.*no RPC"):
        read_rpc_camera(path)


def test_geom_with_missing_keys_is_an_input_error(tmp_path):
    text = shared(GEOM1).read_text()
    bad = tmp_path / "bad.geom"
    kept = [line for line in text.splitlines() if not line.startswith("samp_num_coeff_07")]
    bad.write_text("\n".join(kept))
    with pytest.raises(InputError, match=r"bad\.geom.*samp_num_coeff_07"):
        RPCModel.from_geom(bad)
    nonnum = tmp_path / "nonnum.geom"
    nonnum.write_text(text.replace("height_scale:  130", "height_scale:  abc"))
    with pytest.raises(InputError, match=r"nonnum\.geom.*height_scale"):
        RPCModel.from_geom(nonnum)
    # a .geom beside an image is found; its broken key is reported naming the .geom
    img = tmp_path / "bad.tif"
    _write_tif(img)
    with pytest.raises(InputError, match=r"bad\.geom"):
        read_rpc_camera(img)


def test_geom_beside_image_and_rpc_tags(tmp_path):
    model = RPCModel.from_geom(shared(GEOM1))
    # .geom beside a crop with a pure pixel-offset geotransform
    img = tmp_path / "crop.tif"
    _write_tif(img, transform=Affine.translation(100.0, 40.0))
    (tmp_path / "crop.geom").write_text(shared(GEOM1).read_text())
    cam = read_rpc_camera(img)
    assert (cam.col0, cam.row0, cam.width, cam.height) == (100.0, 40.0, 8, 6)
    assert cam.model.same_as(model)
    # RPC written as GeoTIFF tags, with a georeferenced (non pixel-offset) transform: offset 0
    tagged = tmp_path / "tagged.tif"
    utm_like = Affine(0.5, 0.0, 300000.0, 0.0, -0.5, 3300000.0)
    _write_tif(tagged, transform=utm_like, rpcs=model.to_rasterio())
    cam = read_rpc_camera(tagged)
    assert (cam.col0, cam.row0) == (0.0, 0.0)
    lon, lat = model.localize(np.array([6821.5, 100.0]), np.array([19999.5, 30000.0]), 140.0)
    r0, c0 = model.project(lon, lat, 140.0)
    r1, c1 = cam.project(lon, lat, 140.0)
    np.testing.assert_allclose(r1, r0, atol=1e-6)  # tags are written as text: tiny rounding
    np.testing.assert_allclose(c1, c0, atol=1e-6)
