"""GeoTIFF rasters through rasterio: float32, NaN nodata, tiled and compressed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyproj
import rasterio

from recon3d.core.geo import to_rasterio_crs
from recon3d.core.raster import Raster
from recon3d.errors import InputError
from recon3d.io import atomic_path, require_file

__all__ = ["read_raster", "write_raster"]


def write_raster(raster: Raster, path: str | Path) -> None:
    """Write a single-band float32 GeoTIFF (tiled 256, deflate with float predictor)."""
    rows, cols = raster.shape
    profile = {
        "driver": "GTiff",
        "width": cols,
        "height": rows,
        "count": 1,
        "dtype": "float32",
        "crs": to_rasterio_crs(raster.crs),
        "transform": raster.transform,
        "nodata": np.nan,
        "compress": "deflate",
        "predictor": 3,
    }
    if rows >= 256 and cols >= 256:
        profile.update(tiled=True, blockxsize=256, blockysize=256)
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(raster.data.astype(np.float32), 1)
            if raster.tags:
                dst.update_tags(**raster.tags)


def read_raster(path: str | Path) -> Raster:
    """Read band 1 of a raster; its nodata value becomes NaN."""
    path = require_file(path, "raster")
    try:
        with rasterio.open(path) as src:
            data = src.read(1, masked=True).astype(np.float32).filled(np.nan)
            crs = pyproj.CRS.from_wkt(src.crs.to_wkt()) if src.crs else None
            return Raster(data, src.transform, crs, dict(src.tags()))
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"{path}: cannot read raster ({exc})") from None
