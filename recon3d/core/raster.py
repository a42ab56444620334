"""The :class:`Raster` type: a north-up float32 grid with its georeferencing."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pyproj
from affine import Affine

__all__ = ["Raster", "grid_for_bounds"]


def grid_for_bounds(
    xmin: float, ymin: float, xmax: float, ymax: float, resolution: float
) -> tuple[Affine, tuple[int, int]]:
    """A north-up grid covering a box, its origin snapped to multiples of the resolution.

    Snapping makes every product of one run (and of two runs at the same resolution)
    share cell edges exactly, so ``a.transform == b.transform`` is a valid check.

    Returns
    -------
    transform : affine.Affine
        Pixel-corner transform (rasterio convention; cell centres at +0.5).
    shape : (rows, cols)
    """
    west = math.floor(xmin / resolution) * resolution
    north = math.ceil(ymax / resolution) * resolution
    if north <= ymax:  # a point exactly on the top edge must fall inside row 0
        north += resolution
    cols = max(1, math.floor((xmax - west) / resolution) + 1)
    rows = max(1, math.floor((north - ymin) / resolution) + 1)
    return Affine(resolution, 0.0, west, 0.0, -resolution, north), (rows, cols)


@dataclass
class Raster:
    """A georeferenced single-band grid.

    Parameters
    ----------
    data : (rows, cols) float32
        Cell values; missing cells are NaN (never 0 or -9999 in memory).
    transform : affine.Affine
        Maps pixel corner (col, row) to world (x, y), GDAL "pixel is area";
        cell centres are at (col + 0.5, row + 0.5).
    crs : pyproj.CRS or None
    tags : dict
        Free metadata written as GeoTIFF tags (product name, height reference...).
    origin : (row, col) int
        For a window of a larger grid (:meth:`window`): the cell of that grid that
        ``data[0, 0]`` is, ``transform`` being the larger grid's. Lookups of world points
        compute the larger grid's fractional cell index and subtract ``origin``, an
        exact operation, so a tile's window gives bit for bit the values the whole grid
        gives (a shifted transform would round differently at cell edges).
    """

    data: np.ndarray
    transform: Affine
    crs: pyproj.CRS | None = None
    tags: dict[str, str] = field(default_factory=dict)
    origin: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        self.data = np.asarray(self.data, dtype=np.float32)
        if self.data.ndim != 2:
            raise ValueError(f"Raster data must be 2-D, got shape {self.data.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape  # type: ignore[return-value]

    @property
    def resolution(self) -> float:
        """Cell size in CRS units (square cells)."""
        return float(self.transform.a)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the grid's outer edges."""
        rows, cols = self.shape
        r0, c0 = self.origin
        west = self.transform.c + c0 * self.transform.a
        north = self.transform.f + r0 * self.transform.e
        return (west, north + rows * self.transform.e, west + cols * self.transform.a, north)

    @property
    def own_transform(self) -> Affine:
        """The transform of ``data`` itself (the window's corner), for writing a window to a file."""
        r0, c0 = self.origin
        return self.transform @ Affine.translation(c0, r0)

    def like(self, data: np.ndarray, **tags: str) -> Raster:
        """A raster on the same grid and CRS holding ``data``."""
        return Raster(data, self.transform, self.crs, dict(tags), self.origin)

    def window(self, rows: slice, cols: slice) -> Raster:
        """The cells ``data[rows, cols]`` (a view), as a window of this grid (see ``origin``)."""
        r0, c0 = self.origin
        rows, cols = (slice(*s.indices(n)[:2]) for s, n in zip((rows, cols), self.shape, strict=True))
        return Raster(self.data[rows, cols], self.transform, self.crs, dict(self.tags),
                      (r0 + rows.start, c0 + cols.start))

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World x of each column (cols,) and y of each row (rows,) at cell centres."""
        rows, cols = self.shape
        r0, c0 = self.origin
        x = self.transform.c + (np.arange(c0, c0 + cols) + 0.5) * self.transform.a
        y = self.transform.f + (np.arange(r0, r0 + rows) + 0.5) * self.transform.e
        return x, y

    def rowcol(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer (row, col) of the cells containing world points; may be out of range."""
        col = np.floor((np.asarray(x) - self.transform.c) / self.transform.a).astype(np.int64)
        row = np.floor((np.asarray(y) - self.transform.f) / self.transform.e).astype(np.int64)
        r0, c0 = self.origin
        return row - r0, col - c0

    def sample(self, x: np.ndarray, y: np.ndarray, *, bilinear: bool = True) -> np.ndarray:
        """Values at world points, float64 of the shape of ``x`` and ``y`` broadcast
        ((n,) for (n,) arrays, 0-d for scalars); NaN outside the grid or on nodata.

        Bilinear interpolation between cell centres by default; a NaN neighbour
        makes the result NaN rather than biasing it.
        """
        shape = np.broadcast_shapes(np.shape(x), np.shape(y))
        x = np.broadcast_to(np.asarray(x, dtype=np.float64), shape).ravel()
        y = np.broadcast_to(np.asarray(y, dtype=np.float64), shape).ravel()
        rows, cols = self.shape
        # the whole grid's fractional index, then the window's (subtracting an integer is exact)
        fc = (x - self.transform.c) / self.transform.a - 0.5 - self.origin[1]
        fr = (y - self.transform.f) / self.transform.e - 0.5 - self.origin[0]
        if not bilinear:
            r, c = np.floor(fr + 0.5).astype(np.int64), np.floor(fc + 0.5).astype(np.int64)
            out = np.full(x.shape, np.nan)
            ok = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
            out[ok] = self.data[r[ok], c[ok]]
            return out.reshape(shape)
        np.clip(fr, 0, rows - 1, out=fr)
        np.clip(fc, 0, cols - 1, out=fc)
        r0 = np.minimum(np.floor(fr).astype(np.int64), max(rows - 2, 0))
        c0 = np.minimum(np.floor(fc).astype(np.int64), max(cols - 2, 0))
        fr -= r0  # the fractions dr and dc, in place
        fc -= c0
        # flat indices of the four cells (the next row and column clamped at the edge)
        row_step, flat = _flat_cells(self.data)
        i00 = r0 * row_step
        i00 += c0
        down = (r0 < rows - 1) * row_step
        right = (c0 < cols - 1).astype(np.int64)
        up, left = 1 - fr, 1 - fc
        out = _corner(flat, i00, up, left)  # term by term, in the order of the formula
        out += _corner(flat, i00 + right, up, fc)
        i00 += down
        out += _corner(flat, i00, fr, left)
        out += _corner(flat, i00 + right, fr, fc)
        inside = (
            (x >= self.bounds[0]) & (x <= self.bounds[2]) & (y >= self.bounds[1]) & (y <= self.bounds[3])
        )
        out[~inside] = np.nan
        return out.reshape(shape)


def _flat_cells(data: np.ndarray) -> tuple[int, np.ndarray]:
    """A 1-D view of a grid's cells and the step between its rows in it.

    A window of a larger row-major grid (rows and columns cut off) is viewed in place
    over the span of the larger grid's buffer it covers; any other layout is copied.

    Returns
    -------
    row_step : int
    flat : (m,) array
        Cell (r, c) is ``flat[r * row_step + c]``.
    """
    k = data.itemsize
    rows, cols = data.shape
    if data.size and data.strides[1] == k and data.strides[0] >= 0 and data.strides[0] % k == 0:
        step = data.strides[0] // k
        span = (rows - 1) * step + cols
        return step, np.lib.stride_tricks.as_strided(data, shape=(span,), strides=(k,), writeable=False)
    data = np.ascontiguousarray(data)
    return cols, data.ravel()


def _corner(flat: np.ndarray, index: np.ndarray, wr: np.ndarray, wc: np.ndarray) -> np.ndarray:
    """One bilinear term, (n,) float64: the cells ``flat[index]`` (cast per cell, not the
    whole grid) times ``wr`` times ``wc``, in that order."""
    term = flat.take(index).astype(np.float64)
    term *= wr
    term *= wc
    return term
