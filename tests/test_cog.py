"""The rasters are Cloud Optimized GeoTIFFs (tiles, overviews, DEFLATE), NaN nodata kept,
with the same bytes for the same raster."""

import re

import numpy as np
import pyproj
import pytest
import rasterio
from affine import Affine

from recon3d.core.raster import Raster

RASTERS = ("dsm", "dtm", "ndsm", "model_dsm")


def _check_cog_layout(path):
    with rasterio.open(path) as src:
        assert src.profile["tiled"] and src.block_shapes[0][0] == src.block_shapes[0][1] >= 128
        assert src.overviews(1), "no overview"
        assert src.compression.name == "deflate" and src.tags(ns="IMAGE_STRUCTURE")["PREDICTOR"] == "3"
        assert src.dtypes[0] == "float32" and np.isnan(src.nodata)
        assert "TIFFTAG_DATETIME" not in src.tags()
        data = src.read(1)
        small = src.read(1, out_shape=(1, *(max(1, s // 2) for s in src.shape)))  # from the overview
    assert np.isnan(data).any() == np.isnan(small).any()
    assert np.nanmin(data) <= np.nanmin(small) <= np.nanmax(small) <= np.nanmax(data)  # averaged heights


def test_rasters_of_a_run_are_cogs(autzen_run):
    for name in RASTERS:
        path = autzen_run.out_dir / f"{name}.tif"
        _check_cog_layout(path)
        with rasterio.open(path) as src:
            assert src.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"


def test_rasters_of_a_run_pass_cog_validate(autzen_run):
    cogeo = pytest.importorskip("rio_cogeo.cogeo", reason="rio-cogeo is in the dev extras")
    for name in RASTERS:
        valid, errors, warnings = cogeo.cog_validate(str(autzen_run.out_dir / f"{name}.tif"))
        assert valid and not errors and not warnings, (name, errors, warnings)


def _raster(rows=700, cols=900, tags=None):
    rng = np.random.default_rng(7)
    data = (rng.normal(10, 3, (rows, cols))).astype(np.float32)
    data[100:140, 200:260] = np.nan
    return Raster(data, Affine(0.5, 0, 85000.0, 0, -0.5, 447600.0), pyproj.CRS("EPSG:7415"), tags or {"product": "DSM"})


def test_cog_same_raster_same_bytes(tmp_path):
    from recon3d.io.geotiff import read_raster, write_raster

    raster = _raster()
    write_raster(raster, tmp_path / "a.tif")
    write_raster(raster, tmp_path / "b.tif")
    data = (tmp_path / "a.tif").read_bytes()
    assert data == (tmp_path / "b.tif").read_bytes()
    assert not re.search(rb"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", data)  # no TIFF DateTime
    back = read_raster(tmp_path / "a.tif")
    np.testing.assert_array_equal(back.data, raster.data)  # lossless, NaN kept
    assert back.tags["product"] == "DSM"


def test_tiled_copy_without_cog_driver(tmp_path, monkeypatch):
    """Where rasterio's GDAL has no COG driver the GeoTIFF driver makes the same layout."""
    from recon3d.io import geotiff

    monkeypatch.setattr(geotiff, "_has_cog_driver", lambda: False)
    raster = _raster()
    geotiff.write_raster(raster, tmp_path / "a.tif")
    _check_cog_layout(tmp_path / "a.tif")
    with rasterio.open(tmp_path / "a.tif") as src:
        assert src.overviews(1) == geotiff.overview_factors(raster.shape, geotiff.block_size(raster.shape))
    geotiff.write_raster(raster, tmp_path / "b.tif")
    assert (tmp_path / "a.tif").read_bytes() == (tmp_path / "b.tif").read_bytes()
    cogeo = pytest.importorskip("rio_cogeo.cogeo")
    assert cogeo.cog_validate(str(tmp_path / "a.tif"))[0]


def test_class_rasters_keep_their_codes_in_overviews(tmp_path):
    from recon3d.io.geotiff import write_raster

    codes = np.where(np.arange(600 * 600).reshape(600, 600) % 7 < 3, 1.0, 4.0).astype(np.float32)
    raster = Raster(codes, Affine(1, 0, 0, 0, -1, 600), pyproj.CRS("EPSG:2154"), {"codes": "1 new, 4 demolished"})
    write_raster(raster, tmp_path / "c.tif")
    with rasterio.open(tmp_path / "c.tif") as src:
        assert src.overviews(1)
        small = src.read(1, out_shape=(1, 150, 150))
    assert set(np.unique(small)) <= {1.0, 4.0}


def test_block_size_and_overviews():
    from recon3d.io.geotiff import block_size, overview_factors

    assert block_size((113, 236)) == 128 and overview_factors((113, 236), 128) == [2]
    assert block_size((3000, 2000)) == 256 and overview_factors((3000, 2000), 256) == [2, 4, 8, 16]
    assert block_size((10000, 5000)) == 512
    assert overview_factors((100, 100), 128) == []


def test_read_for_display_averages_the_valid_cells(tmp_path):
    from recon3d.io.geotiff import read_raster, write_raster

    rng = np.random.default_rng(3)
    data = rng.normal(20, 5, (900, 2400)).astype(np.float32)
    data[100:400, 300:900] = np.nan  # a gap wider than a coarse cell
    raster = Raster(data, Affine(0.5, 0, 1000.0, 0, -0.5, 2000.0), pyproj.CRS.from_epsg(2154))
    write_raster(raster, tmp_path / "dsm.tif")
    full = read_raster(tmp_path / "dsm.tif")
    small = read_raster(tmp_path / "dsm.tif", max_side=600)
    assert small.shape == (225, 600)  # a factor of 4 on both axes
    assert small.transform == Affine(2.0, 0, 1000.0, 0, -2.0, 2000.0)  # the same extent
    blocks = data.reshape(225, 4, 600, 4)
    count = np.isfinite(blocks).sum(axis=(1, 3))
    with np.errstate(invalid="ignore"):
        want = np.nansum(blocks, axis=(1, 3)) / count
    assert np.array_equal(np.isnan(small.data), np.isnan(want))  # NaN only where every cell is
    np.testing.assert_allclose(small.data, want, atol=1e-3)
    assert read_raster(tmp_path / "dsm.tif", max_side=5000).shape == full.shape == data.shape
