"""GeoTIFF rasters through rasterio: float32, NaN nodata, as Cloud Optimized GeoTIFFs.

Every raster is written as a COG: internal tiles, overviews, DEFLATE with the
floating-point predictor, the image structure first so a reader fetching ranges over
HTTP needs one request for the header. GDAL's ``COG`` driver writes it when rasterio's
GDAL has one (GDAL >= 3.1), else the GeoTIFF driver copies a tiled file with its
overviews (``COPY_SRC_OVERVIEWS``), the layout the COG driver makes. No time of writing
gets into the file (GDAL writes a TIFF DateTime only when asked): the same raster gives
the same bytes.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pyproj
import rasterio
import rasterio.shutil
from affine import Affine
from rasterio.enums import Resampling

from recon3d.core.geo import to_rasterio_crs
from recon3d.core.raster import Raster
from recon3d.errors import InputError
from recon3d.io import atomic_path, require_file

__all__ = ["block_size", "overview_factors", "read_dem", "read_raster", "write_image", "write_raster"]

#: Compression of every raster: DEFLATE with the floating-point predictor (lossless).
COMPRESSION = {"compress": "deflate", "predictor": 3}

#: GDAL compresses the tiles on every core; the file's bytes are the same as with one.
THREADS = {"num_threads": "ALL_CPUS"}


def block_size(shape: tuple[int, int]) -> int:
    """Tile side (pixels) for a raster of ``shape``: 128 below 1024 pixels on the longer
    side, so the small rasters of a city block still get tiles and an overview; 256
    below 4096; 512 (GDAL's COG default, fewer requests over HTTP) beyond."""
    longest = max(shape)
    return 128 if longest < 1024 else 256 if longest < 4096 else 512


def overview_factors(shape: tuple[int, int], block: int) -> list[int]:
    """Decimation factors 2, 4, 8... until the overview fits in one tile, as the COG
    driver's ``OVERVIEWS=AUTO`` does; none for a raster that fits in one tile."""
    factors, longest = [], max(shape)
    while longest > block:
        factors.append(2 ** (len(factors) + 1))
        longest = -(-longest // 2)
    return factors


def _resampling(raster: Raster) -> str:
    """Overview resampling: heights are averaged (NaN cells left out); a raster of class
    codes (its ``codes`` tag gives their legend) keeps the nearest code."""
    return "nearest" if "codes" in raster.tags else "average"


@functools.cache
def _has_cog_driver() -> bool:
    with rasterio.Env() as env:
        return "COG" in env.drivers()


def write_raster(raster: Raster, path: str | Path) -> None:
    """Write a single-band float32 Cloud Optimized GeoTIFF, NaN nodata, atomically.

    Parameters
    ----------
    raster : Raster
        Its tags become GeoTIFF metadata.
    path : path-like
    """
    rows, cols = raster.shape
    profile = {
        "width": cols,
        "height": rows,
        "count": 1,
        "dtype": "float32",
        "crs": to_rasterio_crs(raster.crs),
        "transform": raster.transform,
        "nodata": np.nan,
        **COMPRESSION,
    }
    with atomic_path(path) as tmp:
        if _has_cog_driver():
            _write_cog(raster, tmp, profile)
        else:
            _write_tiled_copy(raster, tmp, profile)


def _write_cog(raster: Raster, path: Path, profile: dict) -> None:
    """The COG driver (rasterio writes in memory, GDAL copies it as a COG on close)."""
    options = {"blocksize": block_size(raster.shape), "overviews": "AUTO",
               "overview_resampling": _resampling(raster), **THREADS}
    with rasterio.open(path, "w", driver="COG", **profile, **options) as dst:
        dst.write(raster.data.astype(np.float32), 1)
        if raster.tags:
            dst.update_tags(**raster.tags)


def _write_tiled_copy(raster: Raster, path: Path, profile: dict) -> None:
    """Without the COG driver: a tiled GeoTIFF in memory, its overviews built, copied
    with them ahead of the full-resolution tiles."""
    block = block_size(raster.shape)
    with rasterio.MemoryFile() as mem:
        with mem.open(driver="GTiff", **profile) as ds:
            ds.write(raster.data.astype(np.float32), 1)
            if raster.tags:
                ds.update_tags(**raster.tags)
            factors = overview_factors(raster.shape, block)
            if factors:
                ds.build_overviews(factors, Resampling[_resampling(raster)])
        with mem.open() as src:
            rasterio.shutil.copy(src, path, driver="GTiff", tiled=True, blockxsize=block, blockysize=block,
                                 copy_src_overviews=True, **COMPRESSION, **THREADS)


def write_image(data: np.ndarray, grid: Raster, path: str | Path, *, mask: np.ndarray | None = None) -> None:
    """Write an image (an orthophoto) as a Cloud Optimized GeoTIFF, atomically.

    Parameters
    ----------
    data : (bands, rows, cols) uint8 or float32
        RGB or one grey band. uint8 images get an alpha band from ``mask`` (0 where
        nothing is known, so QGIS shows it transparent); float32 ones keep NaN nodata.
    grid : Raster
        Gives the transform, CRS and tags (its data is not written).
    mask : (rows, cols) bool, optional
        Cells holding a value (uint8 images).
    """
    from rasterio.enums import ColorInterp

    bands, rows, cols = data.shape
    byte = data.dtype == np.uint8
    if byte:
        alpha = (np.ones((rows, cols), bool) if mask is None else mask).astype(np.uint8) * 255
        data = np.concatenate([data, alpha[None]])
    profile = {"width": cols, "height": rows, "count": len(data), "dtype": "uint8" if byte else "float32",
               "crs": to_rasterio_crs(grid.crs), "transform": grid.transform, "compress": "deflate",
               "predictor": 2 if byte else 3}
    if not byte:
        profile["nodata"] = np.nan
    colours = ([ColorInterp.red, ColorInterp.green, ColorInterp.blue] if bands == 3 else [ColorInterp.gray] * bands)
    colours += [ColorInterp.alpha] if byte else []
    block = block_size((rows, cols))
    with atomic_path(path) as tmp, rasterio.MemoryFile() as mem:
        with mem.open(driver="GTiff", **profile) as ds:
            ds.write(data)
            ds.colorinterp = colours
            if grid.tags:
                ds.update_tags(**grid.tags)
            factors = overview_factors((rows, cols), block)
            if factors:
                ds.build_overviews(factors, Resampling.average)
        with mem.open() as src:
            rasterio.shutil.copy(src, tmp, driver="GTiff", tiled=True, blockxsize=block, blockysize=block,
                                 copy_src_overviews=True, compress="deflate", predictor=profile["predictor"],
                                 photometric="RGB" if bands == 3 else "MINISBLACK", **THREADS)


#: What GDAL and rasterio raise on a damaged raster: their own errors, and undecodable
#: text in its tags (a UnicodeDecodeError, a ValueError) or CRS.
DAMAGED_RASTER = (rasterio.errors.RasterioError, pyproj.exceptions.CRSError, ValueError)


def read_raster(path: str | Path, *, max_side: int | None = None) -> Raster:
    """Read band 1 of a raster; its nodata value becomes NaN.

    With ``max_side``, a raster with more rows or columns than that is read on a grid
    coarser by a whole factor, at most that many cells on a side, each coarse cell the
    average of the valid cells it covers (from a Cloud Optimized GeoTIFF's overviews
    where they fit): a map for the screen, in memory bounded by the screen, not the area.
    """
    path = require_file(path, "raster")
    try:
        with rasterio.open(path) as src:
            factor = max(1, -(-max(src.width, src.height) // max_side)) if max_side else 1
            shape = (max(1, -(-src.height // factor)), max(1, -(-src.width // factor)))
            data = src.read(1, masked=True, out_shape=shape, resampling=Resampling.average)
            data = data.astype(np.float32).filled(np.nan)
            crs = pyproj.CRS.from_wkt(src.crs.to_wkt()) if src.crs else None
            transform = src.transform @ Affine.scale(src.width / shape[1], src.height / shape[0])
            return Raster(data, transform, crs, dict(src.tags()))
    except DAMAGED_RASTER as exc:
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
