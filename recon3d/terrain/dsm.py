"""Gridding a point cloud into a digital surface model (DSM)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from recon3d.core.geo import Units
from recon3d.core.pointcloud import PointCloud, column_bounds
from recon3d.core.raster import Raster, grid_for_bounds

log = logging.getLogger(__name__)

__all__ = [
    "SpacingGrid",
    "cell_index",
    "choose_resolution",
    "fill_small_holes",
    "grid_points",
    "grid_stereo",
    "make_dsm",
    "mean_and_count",
    "point_spacing",
    "seen_by_all",
    "surface_points",
]

#: "Nice" cell sizes, in CRS units, from which the automatic resolution is picked.
NICE_STEPS = (0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 2.5, 5.0, 10.0, 20.0)


def point_spacing(xy: np.ndarray) -> float:
    """Mean spacing of points (CRS units): sqrt(covered area / number of points).

    The covered area counts the cells of a coarse grid that hold at least one point, so
    an irregular strip is not charged for the empty corners of its bounding box.

    Parameters
    ----------
    xy : (n, 2) float
    """
    grid = SpacingGrid.over(*column_bounds(xy))
    return grid.spacing(grid.occupancy(xy), len(xy))


@dataclass(frozen=True)
class SpacingGrid:
    """The coarse grid of :func:`point_spacing` (64 cells across the longer side), which a
    survey read in chunks fills chunk by chunk (:meth:`occupancy` of each, OR-ed)."""

    lo: tuple[float, float]
    cell: float
    shape: tuple[int, int]  # (nx, ny)
    extent: float

    @classmethod
    def over(cls, lo, hi) -> SpacingGrid:
        """The grid over the box from ``lo`` to ``hi`` (x, y)."""
        extent = max(float(np.max(np.asarray(hi[:2]) - np.asarray(lo[:2]))), 1e-9)
        cell = extent / 64.0  # coarse enough that every covered cell holds points
        nx = int(np.floor((hi[0] - lo[0]) / cell)) + 1
        ny = int(np.floor((hi[1] - lo[1]) / cell)) + 1
        return cls((float(lo[0]), float(lo[1])), cell, (nx, ny), extent)

    def occupancy(self, xy: np.ndarray) -> np.ndarray:
        """(nx, ny) bool: the cells holding at least one of the points (outliers clipped in)."""
        nx, ny = self.shape
        i = np.clip(_floor_index(xy[:, 0], self.lo[0], self.cell), 0, nx - 1)
        j = np.clip(_floor_index(xy[:, 1], self.lo[1], self.cell), 0, ny - 1)
        i *= ny
        i += j
        return np.bincount(i, minlength=nx * ny).reshape(nx, ny) > 0

    def spacing(self, covered: np.ndarray, n: int) -> float:
        """Mean point spacing of ``n`` points covering the cells ``covered``."""
        cell = self.cell
        for _ in range(4):
            occupied = int(np.count_nonzero(covered))
            if n / occupied >= 16 or cell >= self.extent:
                break
            cell *= 2.0  # a cell twice as wide covers 2 x 2 of the finer cells
            rows, cols = (covered.shape[0] + 1) // 2 * 2, (covered.shape[1] + 1) // 2 * 2
            covered = np.pad(covered, ((0, rows - covered.shape[0]), (0, cols - covered.shape[1])))
            covered = covered.reshape(rows // 2, 2, cols // 2, 2).any(axis=(1, 3))
        return math.sqrt(occupied * cell * cell / n)


def choose_resolution(spacing: float, units: Units) -> tuple[float, str]:
    """DSM cell size: the nice step nearest (in log scale) to twice the point spacing.

    Two spacings per cell leave about four points per cell, enough for a highest-point
    DSM with few holes; nice steps make grids of different runs line up.
    """
    target = 2.0 * spacing
    res = min(NICE_STEPS, key=lambda s: abs(math.log(s / target)))
    reason = (
        f"mean point spacing {spacing * units.horizontal:.2f} m; "
        f"nearest nice cell size to 2 x spacing ({target:.2f} {units.name})"
    )
    return res, reason


def grid_points(
    xyz: np.ndarray, transform, shape: tuple[int, int], *, reducer: str = "max", origin: tuple[int, int] = (0, 0),
    keep: np.ndarray | None = None,
) -> np.ndarray:
    """Reduce point heights per grid cell.

    Parameters
    ----------
    xyz : (n, 3) float
    transform : affine.Affine
    shape : (rows, cols)
    reducer : {"max", "min", "mean", "count"}
    origin : (row, col)
        The grid is the window of ``transform``'s grid starting at this cell (see
        :class:`~recon3d.core.raster.Raster`), so a tile's cells are those of the whole grid.
    keep : (n,) bool, optional
        The points to use (all by default): the others' cells are left out, the points
        are not copied out.

    Returns
    -------
    (rows, cols) float64
        NaN in cells without points (0 for "count").
    """
    if reducer not in ("max", "min", "mean", "count"):
        raise ValueError(f"reducer {reducer!r}: expected 'max', 'min', 'mean' or 'count'")
    rows, cols = shape
    idx, z = _kept_cells(xyz, transform, shape, origin, keep)
    if reducer == "count":
        return np.bincount(idx, minlength=rows * cols).reshape(shape).astype(np.float64)
    if reducer == "mean":
        return _mean(idx, z, shape)[0]
    out = np.full(rows * cols, -np.inf if reducer == "max" else np.inf)
    (np.maximum if reducer == "max" else np.minimum).at(out, idx, z)
    out[~np.isfinite(out)] = np.nan
    return out.reshape(shape)


def mean_and_count(
    xyz: np.ndarray, transform, shape: tuple[int, int], *, origin: tuple[int, int] = (0, 0),
    keep: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean height per cell (NaN without points) and the number of points, (rows, cols)
    float64 each, the points' cells found once (as :func:`grid_points`)."""
    return _mean(*_kept_cells(xyz, transform, shape, origin, keep), shape)


def _kept_cells(xyz, transform, shape, origin, keep) -> tuple[np.ndarray, np.ndarray]:
    """(m,) flat cells and heights of the points of ``keep`` (all by default) on the grid."""
    idx, ok = cell_index(xyz, transform, shape, origin=origin)
    if keep is not None:
        ok = keep if ok is None else ok & keep
    z = xyz[:, 2]
    return (idx, z) if ok is None else (idx[ok], z[ok])


def _mean(idx: np.ndarray, z: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    total = np.bincount(idx, weights=z, minlength=shape[0] * shape[1])
    count = np.bincount(idx, minlength=shape[0] * shape[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / count, np.nan)
    return mean.reshape(shape), count.reshape(shape).astype(np.float64)


def cell_index(
    xyz: np.ndarray, transform, shape: tuple[int, int], *, origin: tuple[int, int] = (0, 0)
) -> tuple[np.ndarray, np.ndarray | None]:
    """Flat cell index (row * cols + col) of each point, and which points fall on the grid.

    Parameters
    ----------
    xyz : (n, 2+) float
    transform : affine.Affine
    shape : (rows, cols)
    origin : (row, col)
        First cell of the window of ``transform``'s grid that ``shape`` spans.

    Returns
    -------
    idx : (n,) int64
        Meaningless where ``ok`` is False.
    ok : (n,) bool or None
        None when every point is on the grid (the usual case: a grid over the cloud's bounds).
    """
    rows, cols = shape
    col = _floor_index(xyz[:, 0], transform.c, transform.a)
    row = _floor_index(xyz[:, 1], transform.f, transform.e)
    if origin != (0, 0):
        row -= origin[0]
        col -= origin[1]
    # negative indices wrap to huge unsigned ones: one comparison per axis tests both ends
    ok = (col.view(np.uint64) < cols) & (row.view(np.uint64) < rows)
    row *= cols
    row += col
    return row, None if ok.all() else ok


def _floor_index(v: np.ndarray, origin: float, step: float) -> np.ndarray:
    """(n,) int64 floor((v - origin) / step), with one temporary."""
    t = np.subtract(v, origin)
    t /= step
    np.floor(t, out=t)
    return t.astype(np.int64)


def grid_stereo(
    xyz: np.ndarray, transform, shape: tuple[int, int], *, observed: np.ndarray, source: np.ndarray | None = None,
    per_source: str | tuple[str, ...] = "max", origin: tuple[int, int] = (0, 0),
) -> np.ndarray | tuple[np.ndarray, ...]:
    """Highest point per cell from stereo: observations first, pairs outvoting each other.

    Each source (a stereo pair) gives the highest of its observed points in a cell, and
    the cell takes the median over the sources that observed it, so one pair's spill
    at a building edge is outvoted by the others. Of an even number of sources, frame
    stereo (``per_source="max"``) takes the higher of the two middle values, not their
    mean: two pairs that disagree (a roof, and a long-base pair's match cut short by its
    image edge, below the ground) would average to a height neither saw. A cell no
    source observed takes the median over the sources of each one's highest guessed
    point (a disparity filled in, not confirmed by the images): a guess never outweighs
    an observation, and one pair's guess of a raised surface is outvoted by two pairs
    that took the cell for ground.

    Parameters
    ----------
    xyz : (n, 3) float
    transform : affine.Affine
    shape : (rows, cols)
    observed : (n,) bool
    source : (n,) int, optional
        Which pair each point comes from (one source when omitted).
    per_source : {"max", "median", "upper_median"} or a tuple of them
        What a source gives a cell: its highest observed point (frame stereo: a
        building's edge stays on the roof); the median of them (several points of one
        pair per cell, as satellite GSD against the cell size gives: the highest of
        noisy heights would stand a noise sigma too high); or the higher of the two
        middle points of an even count, a height the pair saw (frame stereo outside the
        buildings: the points of a roof carried onto the street do not set the cell,
        and a cell of one roof and one street point is not put halfway between). A
        tuple grids the points once per entry.
    origin : (row, col)
        As in :func:`grid_points`.

    Returns
    -------
    (rows, cols) float64, or a tuple of them (one per ``per_source`` entry)
        NaN in cells without points.
    """
    rows, cols = shape
    col = _floor_index(xyz[:, 0], transform.c, transform.a) - origin[1]
    row = _floor_index(xyz[:, 1], transform.f, transform.e) - origin[0]
    inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    src = np.zeros(len(xyz), np.int64) if source is None else np.asarray(source, np.int64)
    observed = np.asarray(observed, bool)
    reducers = (per_source,) if isinstance(per_source, str) else tuple(per_source)
    out = np.full((len(reducers), rows * cols), np.nan)
    # observations overwrite guesses; a source's guesses count by their highest point
    guessed = inside & ~observed
    cell, heights = _median_over_sources((row * cols + col)[guessed], src[guessed], xyz[guessed, 2], ("max",))
    out[:, cell] = heights
    seen = inside & observed
    cell, heights = _median_over_sources((row * cols + col)[seen], src[seen], xyz[seen, 2], reducers)
    out[:, cell] = heights
    grids = tuple(g.reshape(shape) for g in out)
    return grids[0] if isinstance(per_source, str) else grids


def _median_over_sources(cell: np.ndarray, src: np.ndarray, z: np.ndarray, reducers: tuple[str, ...]):
    """(cells, (len(reducers), cells) heights): for each reducer, each source's point
    per cell it picks, then the median over the sources (of an even count, but for
    ``"median"``, the higher middle value: a height a pair saw)."""
    if not len(z):
        return cell, np.empty((len(reducers), 0))
    order = np.lexsort((z, src, cell))  # by cell, then source, then height
    cell, src, z = cell[order], src[order], z[order]
    first = np.r_[0, np.flatnonzero((cell[1:] != cell[:-1]) | (src[1:] != src[:-1])) + 1]
    n = np.diff(np.r_[first, len(cell)])  # points of each (cell, source)
    cell = cell[first]
    start = np.r_[0, np.flatnonzero(cell[1:] != cell[:-1]) + 1]
    count = np.diff(np.r_[start, len(cell)])
    heights = np.empty((len(reducers), len(start)))
    for k, reducer in enumerate(reducers):
        if reducer == "max":
            zs = z[first + n - 1]
        elif reducer == "median":
            zs = 0.5 * (z[first + (n - 1) // 2] + z[first + n // 2])
        elif reducer == "upper_median":
            zs = z[first + n // 2]
        else:
            raise ValueError(f"per_source {reducer!r}: expected 'max', 'median' or 'upper_median'")
        zs = zs[np.lexsort((zs, cell))]  # the sources of a cell by height; cells stay in order
        if reducer == "median":
            heights[k] = 0.5 * (zs[start + (count - 1) // 2] + zs[start + count // 2])
        else:
            heights[k] = zs[start + count // 2]
    return cell[start], heights


def fill_small_holes(
    data: np.ndarray, max_cells: int, *, rim: str = "mean", area: np.ndarray | None = None
) -> np.ndarray:
    """Fill NaN regions of at most ``max_cells`` cells that do not touch the border.

    Each hole cell takes one value of the valid cells on the hole's rim (its one-cell
    dilation). ``rim="mean"`` suits LiDAR, whose holes are gaps between scan lines on
    one surface. ``rim="low"`` (the rim's 25th percentile) suits stereo, whose large
    holes are ground hidden from one image behind a building: their rim is part roof
    edge, part ground. Larger or border-touching holes stay NaN.

    With ``area``, the cells the data should cover (the ground two images both see),
    only holes inside it are filled, and a hole may touch its edge or the border: ground
    hidden behind a building at the edge of the images is as much a hole as one in the
    middle.

    Parameters
    ----------
    data : (rows, cols) float
    max_cells : int
    rim : {"mean", "low"}
    area : (rows, cols) bool, optional

    Returns
    -------
    (rows, cols) float, a copy.
    """
    out = data.copy()
    holes = ~np.isfinite(out) if area is None else ~np.isfinite(out) & area
    labels, n = ndimage.label(holes)
    if n == 0:
        return out
    sizes = np.bincount(labels.ravel())
    keep = (sizes <= max_cells) & (np.arange(n + 1) > 0)
    if area is None:
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        keep[border] = False
    fill = keep[labels]
    if not fill.any():
        return out
    rim_labels = (ndimage.grey_dilation(np.where(fill, labels, 0), size=3) * np.isfinite(out)).ravel()
    values = np.nan_to_num(out).ravel()
    counts = np.bincount(rim_labels, minlength=n + 1)
    if rim == "low":
        on = rim_labels > 0
        order = np.lexsort((values[on], rim_labels[on]))  # by hole, then height
        val = values[on][order]
        start = np.concatenate([[0, 0], np.cumsum(counts[1:])])[: n + 1]  # first rim value of each hole in val
        pick = np.clip(start + np.maximum(counts - 1, 0) // 4, 0, max(len(val) - 1, 0))
        fills = np.where(counts > 0, val[pick] if len(val) else np.nan, np.nan)
    else:
        sums = np.bincount(rim_labels, weights=values, minlength=n + 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            fills = sums / counts
    out[fill] = fills[labels[fill]]
    return out


def surface_points(cloud: PointCloud) -> np.ndarray:
    """(n,) bool: the points a DSM is gridded from (all but those classified noise, 7)."""
    c = cloud.classification
    return np.ones(len(cloud), bool) if c is None else c != 7


def make_dsm(
    cloud: PointCloud,
    resolution: float,
    *,
    max_hole_cells: int,
    rim: str = "mean",
    observed: np.ndarray | None = None,
    source: np.ndarray | None = None,
    area=None,
    extent: tuple[np.ndarray, np.ndarray] | None = None,
    per_source: str = "max",
) -> Raster:
    """Highest point per cell, small holes filled, on a grid snapped to the resolution.

    Points classified as noise (7) are left out; ``rim`` as in :func:`fill_small_holes`.
    With ``observed`` (and ``source``), per-point (n,) arrays of a stereo cloud, the
    cells are gridded by :func:`grid_stereo`. ``area(raster)``, given the DSM before
    hole filling, returns the (rows, cols) bool cells the data should cover (see
    :func:`fill_small_holes`). ``extent`` (lowest, highest corner) replaces the cloud's
    bounds as the area of the grid. ``per_source`` as in :func:`grid_stereo`.
    """
    keep = surface_points(cloud)
    xyz = cloud.xyz if keep.all() else cloud.xyz[keep]  # no copy of the cloud when it has no noise
    lo, hi = cloud.bounds if extent is None else extent
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], resolution)
    if observed is None:
        dsm, method = grid_points(xyz, transform, shape, reducer="max"), "highest point per cell"
    else:
        source = None if source is None else np.asarray(source)[keep]
        dsm = grid_stereo(xyz, transform, shape, observed=np.asarray(observed, bool)[keep], source=source,
                          per_source=per_source)
        method = f"{'highest' if per_source == 'max' else 'median'} observed point per cell and pair, median over the pairs"
    raw = Raster(dsm, transform, cloud.crs)
    dsm = fill_small_holes(dsm, max_hole_cells, rim=rim, area=None if area is None else area(raw))
    return Raster(dsm, transform, cloud.crs, {"product": "DSM", "method": method})


def seen_by_all(
    dsm: Raster, cells: np.ndarray, cameras: np.ndarray, *, tolerance: float, in_frame=None,
    heights: np.ndarray | None = None,
) -> np.ndarray:
    """Which of ``cells``, at their DSM height (or ``heights``), every camera would see over the DSM.

    Walks from each cell towards each camera one cell at a time and looks for a DSM
    cell above the ray (by more than ``tolerance``), until the ray clears the highest
    cell of the DSM. A stereo DSM cell that no pixel matched but that every camera sees
    at its filled-in height contradicts the failed match: the surface there is lower,
    hidden from one view (the floor of a courtyard filled at roof height).

    Parameters
    ----------
    dsm : Raster
    cells : (rows, cols) bool
        Cells to test.
    cameras : (m, 3) float
        Projection centres, in the DSM's CRS coordinates.
    tolerance : float
        Height (CRS units) an occluder must stand above the ray.
    in_frame : callable, optional
        ``in_frame(i, xyz)`` -> (n,) bool: whether camera ``i`` images the (n, 3)
        points at all (inside its picture); a point outside a picture is not seen.
    heights : (rows, cols) float, optional
        Heights to test the cells at (default: their DSM heights); the DSM still
        decides what hides them.

    Returns
    -------
    (rows, cols) bool
        True at the tested cells with a finite height that no DSM cell hides from any camera.
    """
    z_all = np.where(np.isfinite(dsm.data), dsm.data, -np.inf)
    heights = dsm.data if heights is None else heights
    rows, cols = np.nonzero(cells & np.isfinite(heights))
    t = dsm.transform  # north-up grid, as everywhere in recon3d
    x, y = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
    z = heights[rows, cols].astype(np.float64)
    if not z.size:
        return np.zeros(cells.shape, bool)
    top = float(np.max(z_all))
    step = dsm.resolution
    visible = np.ones(rows.size, bool)
    for i, (cx, cy, cz) in enumerate(np.asarray(cameras, np.float64)):
        if in_frame is not None:
            visible &= in_frame(i, np.column_stack([x, y, z]))
        dx, dy = cx - x, cy - y
        dist = np.maximum(np.hypot(dx, dy), 1e-9)
        ux, uy = dx / dist, dy / dist
        slope = (cz - z) / dist  # rise of the ray per unit of horizontal distance
        reach = np.minimum(dist, (top - z) / np.maximum(slope, 1e-9))
        for k in range(1, int(np.ceil(reach.max() / step)) + 1):
            s = k * step
            live = visible & (s <= reach)
            if not live.any():
                break
            c = np.floor((x[live] + s * ux[live] - t.c) / t.a).astype(np.int64)
            r = np.floor((y[live] + s * uy[live] - t.f) / t.e).astype(np.int64)
            inside = (r >= 0) & (r < z_all.shape[0]) & (c >= 0) & (c < z_all.shape[1])
            above = np.zeros(live.sum(), bool)
            above[inside] = z_all[r[inside], c[inside]] > z[live][inside] + s * slope[live][inside] + tolerance
            visible[np.flatnonzero(live)[above]] = False
    out = np.zeros(cells.shape, bool)
    out[rows, cols] = visible
    return out
