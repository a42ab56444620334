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

__all__ = ["read_dem", "read_raster", "write_raster"]


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


def read_dem(path: str | Path, *, crs: pyproj.CRS, bounds) -> Raster:
    """Read an elevation model and bring it into ``crs`` (bilinear), over ``bounds``.

    Parameters
    ----------
    path : path-like
        Single-band GeoTIFF (or any raster GDAL reads) of heights, with a CRS.
    crs : pyproj.CRS
        The CRS of the products.
    bounds : ((xmin, ymin, ...), (xmax, ymax, ...))
        The area needed, in ``crs``; the raster must cover part of it.

    Raises
    ------
    InputError
        Unreadable file, no CRS, or no overlap with ``bounds``.
    """
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    dem = read_raster(path)
    if dem.crs is None:
        raise InputError(f"{path}: the elevation model has no CRS")
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    if not dem.crs.equals(crs):
        src, dst = to_rasterio_crs(dem.crs), to_rasterio_crs(crs)
        rows, cols = dem.shape
        transform, width, height = calculate_default_transform(src, dst, cols, rows, *dem.bounds)
        data = np.full((height, width), np.nan, np.float32)
        reproject(dem.data, data, src_transform=dem.transform, src_crs=src, src_nodata=np.nan,
                  dst_transform=transform, dst_crs=dst, dst_nodata=np.nan, resampling=Resampling.bilinear)
        dem = Raster(data, transform, crs, dem.tags)
    x0, y0, x1, y1 = dem.bounds
    if x1 < lo[0] or x0 > hi[0] or y1 < lo[1] or y0 > hi[1] or not np.isfinite(dem.data).any():
        raise InputError(
            f"{path}: the elevation model ({x0:.0f}..{x1:.0f}, {y0:.0f}..{y1:.0f}) does not cover the "
            f"scene ({lo[0]:.0f}..{hi[0]:.0f}, {lo[1]:.0f}..{hi[1]:.0f}); check its CRS"
        )
    return dem
