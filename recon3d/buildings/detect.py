"""Building candidates: blobs of the nDSM, with trees kept out.

Detection follows the classic photogrammetric capture rules, each a
:class:`~recon3d.config.BuildingsConfig` value:

* a building is a connected region of cells at least ``min_height`` (2.5 m) above the
  terrain, at least ``min_width`` wide, covering at least ``min_area`` (25 m2; a
  quarter of it for a blob cut by the edge of the data). Lower attached roofs (annexes,
  lean-tos at least ``grow_height``, smooth, not vegetation) join a building
  (hysteresis between the two heights);
* a block of connected roofs is split where the heights of neighbouring cells jump by
  more than ``split_height`` (2 m): the coarse level (raised cells) finds blocks, the
  fine level (regions whose neighbouring cells differ by less than 2 m: a graph cut
  rather than fixed height bins, so a sloped roof crossing a bin boundary stays whole)
  separates adjacent buildings and large superstructures; parts smaller than
  ``min_area`` (chimneys, dormers) rejoin the part they share the longest border with
  (:mod:`recon3d.buildings.blocks` groups the parts of a block);
* trees never become buildings: cells whose upper points are mostly vegetation
  (:mod:`recon3d.buildings.vegetation`) leave the mask; a blob with many vegetation
  points, or rough (a crown) with some, is rejected;
* outlines are delineated on a grid of half a cell from the points themselves
  (:func:`refine_labels`) and regularised (:mod:`recon3d.buildings.outline`).

Footprints given instead are aligned with the data by :mod:`recon3d.buildings.align`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import rasterio.features
import shapely
from affine import Affine
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from recon3d.buildings import outline as outline_mod
from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.terrain.dsm import cell_index

log = logging.getLogger(__name__)

__all__ = [
    "Blobs",
    "FineSurface",
    "blob_descriptors",
    "building_evidence",
    "building_mask",
    "detect_buildings",
    "find_blobs",
    "fine_surface",
    "label_footprints",
    "refine_labels",
    "smooth_cells",
    "split_at_steps",
    "split_by_height",
    "step_strength",
    "vegetation_mask",
]


# --------------------------------------------------------------------------- raster


def building_mask(ndsm: Raster, vegetation: np.ndarray, config: BuildingsConfig, units: Units) -> np.ndarray:
    """(rows, cols) bool: raised, non-vegetation cells after an opening of ``min_width``.

    The opening removes walls' fringes, wires and spikes narrower than ``min_width``
    (3 cells at 0.5 m) and cuts thin bridges between neighbouring blobs. Lower roofs
    attached to a building (annexes, lean-tos at least ``grow_height`` high, smooth, not
    vegetation) join it: hysteresis between ``grow_height`` and ``min_height``, so a
    building needs ``min_height`` somewhere but keeps its low parts. Holes of raised
    cells inside a blob (a tree over the roof, a dark patch) are filled.
    """
    return _building_mask(ndsm, vegetation, config, units, smooth_cells(ndsm, config, units))


def smooth_cells(ndsm: Raster, config: BuildingsConfig, units: Units) -> np.ndarray:
    """(rows, cols) bool: cells in at least one planar 3 x 3 window of the nDSM.

    Ridges and eaves of narrow gable roofs stay smooth this way; a tree crown is rough
    in every window.
    """
    rough = ndimage.minimum_filter(_roughness(ndsm.data), size=3, mode="nearest")
    return rough <= units.height(config.roof_roughness)


def _building_mask(
    ndsm: Raster, vegetation: np.ndarray, config: BuildingsConfig, units: Units, smooth: np.ndarray
) -> np.ndarray:
    height = np.nan_to_num(ndsm.data)
    veg = vegetation_mask(vegetation)
    size = max(1, int(round(units.length(config.min_width) / ndsm.resolution)))
    structure = np.ones((size, size), bool)

    def opened(m: np.ndarray) -> np.ndarray:
        if size <= 1:
            return m
        # the grid's edge is not the building's: replicate it so edge cells survive
        padded = np.pad(m, size, mode="edge")
        return ndimage.binary_opening(padded, structure=structure)[size:-size, size:-size]

    raised = height >= units.height(config.min_height)
    mask = opened(raised & ~veg)
    grow = units.height(config.grow_height)
    if grow < units.height(config.min_height):
        low = opened((height >= grow) & ~veg & smooth)
        labels, n = ndimage.label(low | mask)
        seeded = np.zeros(n + 1, bool)
        seeded[np.unique(labels[mask])] = True
        seeded[0] = False
        raised = height >= grow
        mask = seeded[labels]
    return ndimage.binary_fill_holes(mask) & raised | mask


def vegetation_mask(vegetation: np.ndarray) -> np.ndarray:
    """Vegetation cells from a bool mask or a share of vegetation points (> 0.5)."""
    vegetation = np.asarray(vegetation)
    return vegetation if vegetation.dtype == bool else np.nan_to_num(vegetation) > 0.5


def building_evidence(ndsm: Raster, vegetation: np.ndarray, config: BuildingsConfig, units: Units) -> Raster:
    """The building mask as a raster for :func:`align_footprints`: 1 building, 0 not, NaN no data."""
    mask = building_mask(ndsm, vegetation, config, units)
    data = np.where(np.isfinite(ndsm.data), mask.astype(np.float32), np.nan)
    return ndsm.like(data, product="building evidence")


def _roughness(height: np.ndarray) -> np.ndarray:
    """(rows, cols) RMS of the 3 x 3 neighbourhood about its least-squares plane.

    Computed :data:`STRIP_ROWS` rows at a time, with a row of neighbours above and
    below: its float64 temporaries are a strip's, not the area's."""
    rows = height.shape[0]
    out = np.empty(height.shape, np.float64)
    for start in range(0, rows, STRIP_ROWS):
        stop = min(start + STRIP_ROWS, rows)
        lo, hi = max(start - 1, 0), min(stop + 1, rows)
        out[start:stop] = _strip_roughness(height[lo:hi])[start - lo : stop - lo]
    return out


def _strip_roughness(height: np.ndarray) -> np.ndarray:
    """:func:`_roughness` of a strip (its first and last rows see only the strip)."""
    z = np.nan_to_num(height.astype(np.float64))
    k = np.ones((3, 3)) / 9.0
    kx = np.array([[-1, 0, 1]] * 3, np.float64)
    mean = ndimage.correlate(z, k, mode="nearest")
    mean_sq = ndimage.correlate(z * z, k, mode="nearest")
    bx = ndimage.correlate(z, kx, mode="nearest") / 6.0
    by = ndimage.correlate(z, kx.T, mode="nearest") / 6.0
    rss = 9.0 * (mean_sq - mean * mean) - 6.0 * (bx * bx + by * by)
    return np.sqrt(np.clip(rss, 0.0, None) / 9.0)


def split_by_height(height: np.ndarray, mask: np.ndarray, split: float) -> tuple[np.ndarray, int]:
    """Components of ``mask`` whose 4-neighbours connect only when heights differ by <= split.

    Parameters
    ----------
    height : (rows, cols) float
    mask : (rows, cols) bool
    split : float
        Largest height step inside one component; 0 or less: plain connected components.

    Returns
    -------
    labels : (rows, cols) int32
        1..n per component, 0 outside ``mask``.
    n : int
    """
    if split <= 0:
        labels, n = ndimage.label(mask)
        return labels.astype(np.int32), n
    # each component lies inside one blob of the mask: split the blobs a window at a
    # time, then number the components in the order of their first cells, as one
    # labelling of the whole grid would
    blobs, n = ndimage.label(mask)
    labels = np.zeros(mask.shape, np.int32)
    firsts, count = [], 0
    for window, ids in _windows(blobs, SPLIT_WINDOW, margin=0):
        here = _marked(ids, n)[blobs[window]]
        components, first = _height_components(np.asarray(height)[window], here, split)
        rows, cols = np.divmod(first, here.shape[1])
        labels[window][here] = components[here] + count
        count += len(first)
        firsts.append((window[0].start + rows) * mask.shape[1] + window[1].start + cols)
    if not firsts:
        return labels, 0
    firsts = np.concatenate(firsts)
    rank = np.zeros(len(firsts) + 1, np.int32)
    rank[1:][np.argsort(firsts)] = np.arange(1, len(firsts) + 1)
    return rank[labels], len(firsts)


def _height_components(height: np.ndarray, mask: np.ndarray, split: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`split_by_height` of a window: (rows, cols) int32 components 1..k, and
    (k,) the flat index of each one's first cell."""
    rows, cols = mask.shape
    ids = np.flatnonzero(mask.ravel())
    h = np.nan_to_num(height.astype(np.float64))
    pairs = []
    for a, b, step in ((np.s_[:, :-1], np.s_[:, 1:], 1), (np.s_[:-1, :], np.s_[1:, :], cols)):
        both = mask[a] & mask[b] & (np.abs(h[a] - h[b]) <= split)
        r, c = np.nonzero(both)
        first = r * cols + c
        pairs.append(np.column_stack([first, first + step]))
    edges = np.concatenate(pairs)
    pos = np.full(rows * cols, -1, np.int64)
    pos[ids] = np.arange(len(ids))
    g = sparse.coo_matrix((np.ones(len(edges)), (pos[edges[:, 0]], pos[edges[:, 1]])), shape=(len(ids), len(ids)))
    n, comp = csgraph.connected_components(g, directed=False)
    labels = np.zeros(rows * cols, np.int32)
    labels[ids] = comp + 1
    _, first = np.unique(comp, return_index=True)
    return labels.reshape(rows, cols), ids[first]


def step_strength(height: np.ndarray, labels: np.ndarray, *, min_step: float) -> np.ndarray:
    """(rows, cols) float32: per cell, the largest height step to a 4-neighbour its roof's slope does not explain.

    The step between two neighbouring cells of one part is explained when no step at
    all is there (it is under ``min_step``), or when it continues the slope on either
    side: the height change from the cell behind it, over one cell or as the mean over
    two (a ridge, a valley or a roof plane crossing the cell edge). What is left is the
    smallest of those misfits; a party wall between houses of different heights leaves
    it, a sloped roof does not.

    Parameters
    ----------
    height : (rows, cols) float
        The nDSM (NaN counts as 0).
    labels : (rows, cols) int
        Parts (0 none): only neighbours of one part are compared.
    min_step : float
        Misfits up to this are 0.

    Returns
    -------
    (rows, cols) float32
        0 on cells without such a step and outside ``labels``.
    """
    h = np.nan_to_num(np.asarray(height, np.float64))
    lab = np.asarray(labels)
    out = np.zeros(h.shape, np.float64)
    for hh, ll, oo in ((h, lab, out), (h.T, lab.T, out.T)):  # along rows, then along columns
        if hh.shape[1] < 2:
            continue
        for start in range(0, hh.shape[0], STRIP_ROWS):  # rows are independent: memory of a strip
            rows = slice(start, start + STRIP_ROWS)
            _row_steps(hh[rows], ll[rows], oo[rows], min_step)
    return out.astype(np.float32)


#: Rows :func:`step_strength` works on at a time (its temporaries are a dozen strips).
STRIP_ROWS = 256


def _row_steps(hh: np.ndarray, ll: np.ndarray, oo: np.ndarray, min_step: float) -> None:
    """:func:`step_strength` along the rows of a strip, raising ``oo`` (a view) in place."""
    # pad two cells of "no part" so the slopes behind each cell of an edge can be read
    hp = np.pad(hh, ((0, 0), (2, 2)))
    lp = np.pad(ll, ((0, 0), (2, 2)))
    a, b = np.s_[:, 2:-3], np.s_[:, 3:-2]  # the two cells of each edge, a left of b
    same = (lp[a] == lp[b]) & (lp[a] > 0)
    dz = hp[b] - hp[a]
    misfit = np.abs(dz)
    # the slope behind a (from its left neighbours) and behind b (to its right ones)
    behind = (
        (hp[a] - hp[:, 1:-4], lp[:, 1:-4], (hp[a] - hp[:, 0:-5]) / 2, lp[:, 0:-5], lp[a]),
        (hp[:, 4:-1] - hp[b], lp[:, 4:-1], (hp[:, 5:] - hp[b]) / 2, lp[:, 5:], lp[b]),
    )
    for s1, l1, s2, l2, own in behind:
        one = l1 == own
        misfit = np.where(one, np.minimum(misfit, np.abs(dz - s1)), misfit)
        misfit = np.where(one & (l2 == own), np.minimum(misfit, np.abs(dz - s2)), misfit)
    misfit = np.where(same & (misfit > min_step), misfit, 0.0)
    oo[:, :-1] = np.maximum(oo[:, :-1], misfit)
    oo[:, 1:] = np.maximum(oo[:, 1:], misfit)


def valley_depth(height: np.ndarray, labels: np.ndarray, *, reach: int, min_drop: float) -> np.ndarray:
    """(rows, cols) float32: per cell, how far the roof rises on both sides of it, ``reach`` cells away.

    A valley between two roofs (gables side by side, each house its own) is a line of
    cells lower than the cells on both sides of it, along a row or a column of the grid,
    where the two roofs slope down towards each other: their slopes, ``reach`` cells
    away on either side, point more than :data:`VALLEY_OPPOSITE` degrees apart. The
    valleys of one house's roof, where two wings meet at right angles (an L, a T, a
    cross gable), join slopes about 90 degrees apart and are no such line. The smaller
    of the two rises is the depth, kept above ``min_drop`` (0 elsewhere). Only cells of
    one part are compared.

    Parameters
    ----------
    height : (rows, cols) float
    labels : (rows, cols) int
    reach : int
        Cells to either side (at least 1).
    min_drop : float
    """
    h = np.nan_to_num(np.asarray(height, np.float64))
    lab = np.asarray(labels)
    k = max(1, int(reach))
    out = np.zeros(h.shape, np.float64)
    if min(h.shape) < 2:
        return out.astype(np.float32)
    slope = _part_slope(h, lab)
    cos_max = np.cos(np.radians(VALLEY_OPPOSITE))
    for hh, ll, oo, (g0, g1) in ((h, lab, out, slope), (h.T, lab.T, out.T, (slope[1].T, slope[0].T))):
        if hh.shape[1] <= 2 * k:
            continue
        c = np.s_[:, k:-k]
        a, b = np.s_[:, : -2 * k], np.s_[:, 2 * k :]  # the cells reach before and after
        same = (ll[c] > 0) & (ll[a] == ll[c]) & (ll[b] == ll[c])
        rise = np.minimum(hh[a] - hh[c], hh[b] - hh[c])
        dot = g0[a] * g0[b] + g1[a] * g1[b]
        opposite = dot < cos_max * np.hypot(g0[a], g1[a]) * np.hypot(g0[b], g1[b])
        oo[c] = np.maximum(oo[c], np.where(same & opposite & (rise > min_drop), rise, 0.0))
    return out.astype(np.float32)


def _part_slope(h: np.ndarray, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) float64 twice: the height's slope along the grid's columns (axis 0)
    and rows (axis 1), from the neighbours of the cell's own part only (the mean of the
    differences to both; the one of its part at a wall; 0 with neither). A slope taken
    across a wall would point at the ground.

    Parameters
    ----------
    h : (rows, cols) float64
    lab : (rows, cols) int
    """
    slope = []
    for axis in (0, 1):
        d = np.diff(h, axis=axis)
        same = np.diff(lab, axis=axis) == 0
        d = np.where(same, d, 0.0)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 0)
        before, n_before = np.pad(d, pad), np.pad(same, pad)
        pad[axis] = (0, 1)
        after, n_after = np.pad(d, pad), np.pad(same, pad)
        slope.append((before + after) / np.maximum(n_before.astype(np.int8) + n_after, 1))
    return slope[0], slope[1]


#: Angle (degrees) between the slopes on both sides of a valley above which it parts
#: two roofs (:func:`valley_depth`); a roof's own valleys join slopes about 90 degrees apart.
VALLEY_OPPOSITE = 135.0


def split_at_steps(
    height: np.ndarray,
    labels: np.ndarray,
    cell: float,
    *,
    min_step: float,
    min_area: float,
    min_width: float,
    max_shared: float = 0.8,
    min_evidence: float = 0.5,
    border: float = 1.0,
    valley_drop: float | None = None,
    valley_reach: float = 1.0,
) -> tuple[np.ndarray, int]:
    """Cut parts into buildings along lines of height steps crossing them from wall to wall.

    Step cells (:func:`step_strength`, widened by a cell to close gaps in the line) and
    a rim of ``border`` along the walls (where a step that fades out at the eaves
    still ends) leave cores: the connected regions left of a part. A part with two or
    more cores is flooded from them, across the lowest steps first (scikit-image's
    watershed of the step strength, inside the part), so the pieces meet on the step
    lines. A cut is kept only where it is real; otherwise its pieces join again:

    * at least ``min_evidence`` of the border two pieces share lies on step cells (two
      cores parted only by the rim, at a narrow waist, are one building), and that
      border runs straight (RMS off its line at most :data:`MAX_CUT_WIGGLE`: a party
      wall, not a path between the dormers and chimneys of one roof);
    * each piece covers ``min_area`` (a dormer, a chimney stays with its roof), is at
      least ``min_width`` wide (an annex, the fringe of a wall) and shares less than
      ``max_shared`` of its border with the other pieces (a higher part enclosed by
      the rest: a tower, a superstructure). A failing piece joins the neighbour it
      shares the longest border with.

    The steps, cores and rejoining are worked out a square of the grid at a time
    (:data:`SPLIT_WINDOW`), each part from its own cells and their neighbours, so the
    memory follows the square and the largest block, not the area; only the flood runs
    once over the box of every part cut (the watershed settles ties by the order it
    meets the cells in, and one flood over that box keeps the cuts whatever the
    windows). scipy's ``watershed_ift`` is no substitute: on a 2-D plateau of equal
    cost one marker floods the whole grid, across higher walls too.

    Parameters
    ----------
    height : (rows, cols) float
    labels : (rows, cols) int
        Parts (:func:`split_by_height`), 0 background.
    cell : float
        Cell size (CRS units).
    min_step : float
        Height step (CRS units) that marks a party wall.
    min_area, min_width : float
        Smallest piece cut off (CRS units squared; CRS units).
    max_shared, min_evidence : float
        Shares of a piece's border, see above.
    border : float
        Width (CRS units) of the rim along the walls that is no core.
    valley_drop : float, optional
        Valleys whose sides rise more than this (CRS units) within ``valley_reach``
        (CRS units; :func:`valley_depth`) cut too, as steps do: two roof plane sets, one
        house each.

    Returns
    -------
    labels : (rows, cols) int32
        1..n, the parts not cut keep their cells.
    n : int
    """
    lab = np.asarray(labels).astype(np.int32)  # int32 labels: every whole-area copy below at half the memory
    if not lab.any():
        return _consecutive(lab)
    windows = _windows(lab, SPLIT_WINDOW, margin=WINDOW_MARGIN + int(round(valley_reach / cell)))
    cores = _cores(height, lab, windows, cell, min_step=min_step, min_area=min_area, border=border,
                   valley_drop=valley_drop, valley_reach=valley_reach)
    if cores is None:
        return _consecutive(lab)
    cut = cores.split[lab]
    # work in the box of the parts cut
    (r0, c0), (r1, c1) = np.argwhere(cut).min(axis=0), np.argwhere(cut).max(axis=0) + 1
    box = np.s_[max(r0 - 1, 0) : r1 + 1, max(c0 - 1, 0) : c1 + 1]
    sub = lab[box]
    # the flood crosses steps last (cores.cost), and another part only at the highest cost
    cost = np.where(cut[box], cores.cost[box], np.uint16(65535))
    markers = np.where(cut[box], cores.labels[box], 0).astype(np.int32)
    cores.cost = cores.labels = None  # let go of the whole-area copies before the flood's own memory
    from skimage.segmentation import watershed  # here: its import is for the coordinator's detection only

    flooded = watershed(cost, markers, mask=cut[box])  # int32, as the markers
    del cost, markers
    # cells of a part's rim taken by a neighbouring part's core take a neighbour's core of their own part
    part_of = cores.part_of
    wrong = cut[box] & (part_of[flooded] != sub)
    for _ in range(4):
        if not wrong.any():
            break
        for here, there in map(_neighbours, NEIGHBOURS):
            take = wrong[here] & ~wrong[there] & (sub[there] == sub[here])
            flooded[here][take] = flooded[there][take]
            wrong[here][take] = False
    # pieces: a core's flood inside its part; parts not cut stay whole
    pieces = lab.copy() if int(lab.max()) + 1 + len(part_of) <= np.iinfo(np.int32).max else lab.astype(np.int64)
    keep = cut[box] & ~wrong
    pieces[box][keep] = flooded[keep] + (int(lab.max()) + 1)
    blocked = np.zeros(lab.shape, bool)  # rim cells no core of their own part reached
    blocked[box] = wrong
    del flooded, wrong, keep
    on_step = cut & cores.level & ~blocked
    # each window rewrites its own parts' cells in place: the level pass and the
    # rejoining read only the cells of the part they work on
    for window, ids in windows:
        mine = _marked(ids, len(cores.split) - 1) & cores.split
        if not mine.any():
            continue
        here = mine[lab[window]]
        cells = _level_with(np.asarray(height)[window], lab[window], pieces[window], on_step[window] & here,
                            blocked[window])
        compact, numbers = _compact(cells)
        cells = numbers[_join_pieces(compact, lab[window], cores.step[window], cores.inner[window], cell,
                                     min_area=min_area, min_width=min_width, max_shared=max_shared,
                                     min_evidence=min_evidence)]
        pieces[window][here] = cells[here]
    return _consecutive(pieces)


#: RMS distance (CRS units) of a cut between two pieces of a block from a straight line
#: above which it is no party wall (:func:`split_at_steps`).
MAX_CUT_WIGGLE = 1.0


#: Side (cells) of the squares of the grid whose parts :func:`split_at_steps` handles
#: together: its floating-point temporaries (tens of bytes a cell) follow the square
#: and the largest block in it, not the area.
SPLIT_WINDOW = 512


#: Cells around a window's parts that its box also holds: the neighbours a part's
#: steps and cores are judged by (the slope two cells behind a step, the valleys'
#: reach on top of that), also for the cells of the next part.
WINDOW_MARGIN = 4


def _windows(labels: np.ndarray, size: int, *, margin: int) -> list[tuple[tuple[slice, slice], np.ndarray]]:
    """(box, part ids) for each ``size`` square of the grid holding a part's top-left
    cell: the box spans those parts and ``margin`` cells around them."""
    objects = ndimage.find_objects(labels)
    ids = np.array([i + 1 for i, o in enumerate(objects) if o is not None], np.int64)
    if not len(ids):
        return []
    extent = np.array([(o[0].start, o[0].stop, o[1].start, o[1].stop) for o in objects if o is not None])
    square = (extent[:, 0] // size) * (-(-labels.shape[1] // size)) + extent[:, 2] // size
    order = np.argsort(square, kind="stable")
    _, starts = np.unique(square[order], return_index=True)
    out = []
    for group in np.split(order, starts[1:]):
        e = extent[group]
        out.append(((slice(max(int(e[:, 0].min()) - margin, 0), int(e[:, 1].max()) + margin),
                     slice(max(int(e[:, 2].min()) - margin, 0), int(e[:, 3].max()) + margin)), ids[group]))
    return out


def _marked(ids: np.ndarray, n: int) -> np.ndarray:
    """(n + 1,) bool, True at the labels ``ids``: a lookup of a window's parts."""
    out = np.zeros(n + 1, bool)
    out[ids] = True
    return out


@dataclass
class _Cores:
    """The grids :func:`split_at_steps` floods from, built a window at a time."""

    labels: np.ndarray  # (rows, cols) int32: each core's number (1..m, in raster order of first cells), 0 elsewhere
    part_of: np.ndarray  # (m + 1,) int64: the part of each core (0: none)
    split: np.ndarray  # (parts + 1,) bool: parts with two cores or more
    cost: np.ndarray  # (rows, cols) uint16: the flood's cost
    level: np.ndarray  # (rows, cols) bool: cells of a height step
    step: np.ndarray  # (rows, cols) bool: cells of a step or a valley
    inner: np.ndarray  # (rows, cols) bool: cells more than ``border`` inside their part


def _cores(height, lab, windows, cell, *, min_step, min_area, border, valley_drop, valley_reach) -> _Cores | None:
    """Step strengths, flood costs and cores of every part, computed window by window
    (each looks only at its part's cells and their neighbours), numbered as one
    labelling of the whole grid would number them. None when no cell is on a step."""
    shape = lab.shape
    # at each core cell: 1 + the grid index of its core's first cell
    first = np.zeros(shape, np.int32 if lab.size < np.iinfo(np.int32).max else np.int64)
    cost = np.full(shape, 65535, np.uint16)
    level, step, inner = (np.zeros(shape, bool) for _ in range(3))
    starts, sizes, parts = [], [], []
    min_core = max(1, int(round(min_area / 4 / cell**2)))
    n = int(lab.max())
    for window, ids in windows:
        sub = lab[window]
        here = _marked(ids, n)[sub]
        h = np.asarray(height)[window]
        strength = step_strength(h, sub, min_step=min_step)
        level[window][here] = (strength > 0)[here]
        if valley_drop is not None:
            strength = np.maximum(strength, valley_depth(h, sub, reach=int(round(valley_reach / cell)),
                                                             min_drop=valley_drop))
        step[window][here] = (strength > 0)[here]
        inside = (sub > 0) & (_distance(~_piece_border(sub)) * cell > border)
        inner[window][here] = inside[here]
        c = np.clip(np.round(strength * 100.0), 0, 65000).astype(np.uint16)
        c[_piece_border(sub, touching=True)] = 65534
        cost[window][here] = c[here]
        core = inside & here & ~ndimage.binary_dilation(strength > 0, structure=np.ones((3, 3), bool))
        numbers, m = ndimage.label(core)
        if not m:
            continue
        found, index, count = np.unique(numbers.ravel(), return_index=True, return_counts=True)
        rows, cols = np.divmod(index[1:], numbers.shape[1])
        start = (window[0].start + rows) * shape[1] + window[1].start + cols
        starts.append(start)
        sizes.append(count[1:])
        parts.append(sub.ravel()[index[1:]])
        cell_start = np.zeros(m + 1, np.int64)
        cell_start[found[1:]] = start + 1
        first[window][core] = cell_start[numbers[core]]
    if not step.any() or not starts:
        return None
    starts, sizes, parts = np.concatenate(starts), np.concatenate(sizes), np.concatenate(parts)
    order = np.argsort(starts)  # the cores' numbers in one labelling of the grid
    kept = np.zeros(len(starts) + 1, bool)
    kept[1:] = sizes[order] >= min_core
    part_of = np.zeros(len(starts) + 1, np.int64)
    part_of[1:] = np.where(kept[1:], parts[order], 0)
    labels = np.zeros(shape, np.int32)
    at = first > 0
    number = np.searchsorted(starts[order], first[at] - 1) + 1
    labels[at] = np.where(kept[number], number, 0)
    del first, at, number
    split = np.bincount(part_of[kept], minlength=n + 1) >= 2
    split[0] = False
    if not split.any():
        return None
    return _Cores(labels, part_of, split, cost, level, step, inner)


def _level_with(height: np.ndarray, parts: np.ndarray, pieces: np.ndarray, on_step: np.ndarray,
                blocked: np.ndarray) -> np.ndarray:
    """The pieces with each cell of a step (``on_step``) moved to the piece of the
    4-neighbour of its part (not ``blocked``) it is most level with: the flood splits a
    step anywhere between its two sides, the wall stands between the two cells of a
    step edge."""
    hb = np.nan_to_num(np.asarray(height, np.float64))
    for _ in range(2):
        best, choice = np.full(hb.shape, np.inf), pieces.copy()
        for here, there in map(_neighbours, NEIGHBOURS):
            dz = np.where((parts[there] == parts[here]) & ~blocked[there], np.abs(hb[here] - hb[there]), np.inf)
            better = on_step[here] & (dz < best[here])
            best[here][better], choice[here][better] = dz[better], pieces[there][better]
        pieces = choice
    return pieces


def _compact(pieces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pieces numbered 0..k in the order of their numbers (``_join_pieces`` counts
    by number), and the numbers, to map back."""
    values, compact = np.unique(pieces, return_inverse=True)
    return (compact.reshape(pieces.shape).astype(np.int32), values)


#: The four neighbours of a cell, as (rows, cols) shifts, in the order they are tried.
NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0))


def _neighbours(shift: tuple[int, int]) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Views pairing each cell with its neighbour ``shift`` cells back: ``a[here][k]`` and
    ``a[there][k]`` are a cell and the cell (rows, cols) before it, for every cell that has
    one (no padded copy of the grid)."""
    def axis(k: int) -> tuple[slice, slice]:
        return slice(max(k, 0), k if k < 0 else None), slice(max(-k, 0), -k if k > 0 else None)

    (r_here, r_there), (c_here, c_there) = axis(shift[0]), axis(shift[1])
    return (r_here, c_here), (r_there, c_there)


def _distance(mask: np.ndarray) -> np.ndarray:
    """(rows, cols) float64 Euclidean distance (cells) of each True cell to the nearest
    False one: OpenCV's exact transform, in a quarter of scipy's working memory."""
    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float64)


def _consecutive(labels: np.ndarray) -> tuple[np.ndarray, int]:
    """Labels (>= 0) renumbered 1..n in order of their old values (0 stays 0), and n."""
    ids, inv = _unique_labels(labels, np.int32)
    if ids[0] != 0:
        inv += 1
    return inv, int(inv.max())


def _unique_labels(labels: np.ndarray, dtype=np.int64) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(labels, return_inverse=True)`` of a grid of labels >= 0, the inverse in
    the grid's shape: from a count of the labels present instead of a sort of the grid."""
    present = np.bincount(labels.ravel()) > 0
    return np.flatnonzero(present).astype(labels.dtype), (np.cumsum(present) - 1).astype(dtype)[labels]


def _piece_border(labels: np.ndarray, *, touching: bool = False) -> np.ndarray:
    """(rows, cols) bool: labelled cells with a 4-neighbour of another label (or none, at the grid's edge).

    ``touching``: only neighbours of another non-zero label count.
    """
    p = np.pad(labels, 1)
    c = p[1:-1, 1:-1]
    edge = np.zeros(c.shape, bool)
    for n in (p[:-2, 1:-1], p[2:, 1:-1], p[1:-1, :-2], p[1:-1, 2:]):
        edge |= (c != n) & ((n > 0) if touching else True)
    return edge & (c > 0)


def _join_pieces(pieces, parts, step, inner, cell, *, min_area, min_width, max_shared, min_evidence):
    """Rejoin the pieces of a step cut that are no buildings (:func:`split_at_steps`).

    Each part is judged on its own (one whose cut no step explains rejoins across it
    first, and only then are its small and thin pieces judged), so that the parts of a
    window come out as they would alone."""
    for _ in range(20):
        ids, p = _unique_labels(pieces, np.int32)  # int32: half the memory of the whole-area grids
        n = len(ids)
        part_of = np.zeros(n, np.int64)
        part_of[p.ravel()] = parts.ravel()
        cells = np.bincount(p.ravel(), minlength=n)
        # the border of every piece (pairs of 4-neighbours in different pieces, kept
        # alone: a few percent of the cells), and the share it has with each other piece of its part
        la, lb, on_step, at = [], [], [], []
        for (a, b), half in zip(((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])), ((0.0, 0.5), (0.5, 0.0)),
                                strict=True):
            diff = p[a] != p[b]
            la.append(p[a][diff].astype(np.int64))
            lb.append(p[b][diff].astype(np.int64))
            on_step.append(step[a][diff] | step[b][diff])
            at.append(np.argwhere(diff) + half)  # the middle of each border edge (row, col)
        la, lb, on_step, at = np.concatenate(la), np.concatenate(lb), np.concatenate(on_step), np.concatenate(at)
        perimeter = np.bincount(np.r_[la, lb], minlength=n).astype(np.float64)
        # the grid's edge is a border too
        for line in (p[0], p[-1], p[:, 0], p[:, -1]):
            perimeter += np.bincount(line, minlength=n)
        pair = (part_of[la] == part_of[lb]) & (part_of[la] > 0)
        src, dst, ev = np.r_[la[pair], lb[pair]], np.r_[lb[pair], la[pair]], np.r_[on_step[pair], on_step[pair]]
        if not len(src):
            break
        key, count = np.unique(src * n + dst, return_counts=True)
        which = np.searchsorted(key, src * n + dst)
        evidence = np.bincount(which, weights=ev, minlength=len(key)) / count
        wiggle = _off_line(np.r_[at[pair], at[pair]], which, count) * cell
        s, d = key // n, key % n
        mapping = np.arange(n)
        weak = (evidence < min_evidence) | (wiggle > MAX_CUT_WIGGLE)
        # each part on its own: one with a cut that no step explains rejoins across it first
        joining = np.zeros(int(part_of.max()) + 1, bool)
        joining[part_of[s[weak]]] = True
        if weak.any():  # join both sides of such a cut
            g = sparse.coo_matrix((np.ones(int(weak.sum())), (s[weak], d[weak])), shape=(n, n))
            _, comp = csgraph.connected_components(g, directed=False)
            lowest = np.full(n, n)
            np.minimum.at(lowest, comp, np.arange(n))
            mapping = lowest[comp]
        if not joining[part_of[s]].all():
            shared = np.bincount(s, weights=count, minlength=n)
            dist = _distance(~_piece_border(p) & (p > 0))
            deepest = np.zeros(n)  # per piece (0 where it has no cell, as ndimage.maximum gives)
            np.maximum.at(deepest, p.ravel(), dist.ravel())  # ndimage.maximum sorts every cell: 10 x slower
            width = 2.0 * (deepest + 0.5) * cell
            inner_share = np.bincount(p.ravel(), weights=inner.ravel(), minlength=n) / np.maximum(cells, 1)
            cut = np.zeros(n, bool)
            cut[s] = True
            bad = cut & ~joining[part_of] & (
                (cells * cell**2 < min_area)
                | (width < min_width)
                | (shared >= max_shared * np.maximum(perimeter, 1))
                | (inner_share < 0.25)
            )
            # each failing piece joins the neighbour it shares the longest border with;
            # ties go to the larger neighbour; only the worst of two failing neighbours moves
            order = np.lexsort((-cells[d], -count, s))
            s2, d2 = s[order], d[order]
            head = np.r_[True, s2[1:] != s2[:-1]]
            target = np.arange(n)
            target[s2[head]] = d2[head]
            move = bad & (target != np.arange(n))
            mutual = move & move[target] & (target[target] == np.arange(n))
            keep = (cells > cells[target]) | ((cells == cells[target]) & (np.arange(n) < target))
            move &= ~(mutual & keep)
            mapping = np.where(move, target, mapping)
            for _ in range(8):
                mapping = mapping[mapping]
        if (mapping == np.arange(n)).all():
            break
        pieces = ids[mapping][p]
    return pieces


def _off_line(points: np.ndarray, group: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(k,) RMS distance (cells) of each group's points from the straight line fitting
    them best: the square root of the smaller eigenvalue of their covariance.

    Parameters
    ----------
    points : (m, 2) float
    group : (m,) int
        0..k-1.
    count : (k,) int
        Points per group.
    """
    k = len(count)
    mean = np.stack([np.bincount(group, weights=points[:, i], minlength=k) for i in (0, 1)], 1) / count[:, None]
    d = points - mean[group]
    sxx, syy, sxy = (np.bincount(group, weights=w, minlength=k) / count for w in (d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1]))
    smaller = (sxx + syy) / 2 - np.sqrt(((sxx - syy) / 2) ** 2 + sxy**2)
    return np.sqrt(np.maximum(smaller, 0.0))


def _label_medians(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n,) median of ``values`` over each label 1..n, in ``values``' dtype, equal to
    ``ndimage.median``'s (0 for a label without cells, where that gives an arbitrary
    value): one sort of the labelled cells instead of a median per label.

    Parameters
    ----------
    values : (rows, cols) float
    labels : (rows, cols) int
    n : int
    """
    keep = labels > 0
    v, lab = values[keep], labels[keep]
    v = v[np.lexsort((v, lab))]  # by label, then by value
    count = np.bincount(lab, minlength=n + 1)[1 : n + 1]
    start = (np.cumsum(count) - count)[count > 0]
    held = count[count > 0]
    out = np.zeros(n, values.dtype)
    out[count > 0] = (v[start + (held - 1) // 2] + v[start + held // 2]) / values.dtype.type(2)
    return out


def _merge_small(labels: np.ndarray, n: int, min_cells: int) -> np.ndarray:
    """Parts smaller than ``min_cells`` join the touching part they share the longest border with."""
    for _ in range(20):
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        small = (sizes < min_cells) & (sizes > 0)
        small[0] = False
        if not small.any():
            break
        pairs = []
        for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])):
            la, lb = labels[a].ravel(), labels[b].ravel()
            diff = (la != lb) & (la > 0) & (lb > 0)
            pairs += [np.column_stack([la[diff], lb[diff]]), np.column_stack([lb[diff], la[diff]])]
        pairs = np.concatenate(pairs)
        pairs = pairs[small[pairs[:, 0]]]
        if not len(pairs):
            break
        key, counts = np.unique(pairs[:, 0] * (n + 1) + pairs[:, 1], return_counts=True)
        src, dst = key // (n + 1), key % (n + 1)
        # the longest shared border; ties go to the larger neighbour
        order = np.lexsort((-sizes[dst], -counts, src))
        src, dst = src[order], dst[order]
        first = np.r_[True, src[1:] != src[:-1]]
        mapping = np.arange(n + 1, dtype=np.int32)  # int32 like the labels: no int64 copy of the grid
        mapping[src[first]] = dst[first]
        # a small part absorbed by another small part that itself moves: follow the chain
        for _ in range(8):
            mapping = mapping[mapping]
        labels = mapping[labels]
    return labels


@dataclass
class Blobs:
    """Building candidates of one nDSM.

    Attributes
    ----------
    labels : (rows, cols) int32
        1 + blob index per cell, 0 elsewhere (rejected blobs included).
    area : (m,) float
        Blob areas (CRS units squared).
    height : (m,) float
        Median nDSM of each blob.
    smooth_share : (m,) float
        Share of the blob's inner cells whose DSM is smooth (``roof_roughness``).
    vegetation_share : (m,) float
        Mean share of vegetation points over the blob's cells (NaN when only vegetation
        cells, not shares, were given).
    planar_share : (m,) float
        Mean share of the upper points on a local plane over the blob's inner cells
        (NaN without per-point planarity).
    reason : list of str
        Empty for kept blobs, else why the blob is not a building: "small", or
        "vegetation" (a tree crown: rough, or with many vegetation points).
    mask : (rows, cols) bool
        The building mask the blobs were cut from (:func:`building_mask`).
    """

    labels: np.ndarray
    area: np.ndarray
    height: np.ndarray
    smooth_share: np.ndarray
    vegetation_share: np.ndarray
    reason: list[str] = field(default_factory=list)
    planar_share: np.ndarray | None = None
    mask: np.ndarray | None = None

    @property
    def kept(self) -> np.ndarray:
        """(m,) bool: blobs that are buildings."""
        return np.array([not r for r in self.reason], bool)


#: Rise (m) of the roof within :data:`VALLEY_REACH` on both sides of a valley that makes
#: it a cut between two houses (17 degrees): terraces with a gable per house meet in
#: valleys, not steps. The inner valleys of L-shaped gable houses (the Delft strip has
#: them) are told apart by the direction of their slopes (:data:`VALLEY_OPPOSITE`), not
#: by a steeper rule (0.8 m within 1 m kept every terrace under 39 degrees whole).
VALLEY_DROP = 0.45
#: Distance (m) on both sides of a valley at which its rise is read: far enough that the
#: cell nearest the valley line, up to half a cell off it, still sees most of the rise.
VALLEY_REACH = 1.5
#: Mean share of vegetation points above which a blob is a tree whatever its shape.
VEGETATION_BLOB_SHARE = 0.3
#: Mean share of vegetation points above which a rough blob is a tree; below it a rough
#: blob with no vegetation evidence is a steep roof (a spire, a tower's pyramid).
ROUGH_VEGETATION_SHARE = 0.05
#: Mean share of a blob's upper points on local planes below which it is a cluster of
#: crowns, with or without vegetation evidence: roofs are planes, crowns are not (on
#: the random LiDAR family from 2 points per m2, tree blobs measure 0 to 0.40, buildings
#: 0.64 to 1, the lowest half under a crown). Not applied to a survey with colours,
#: where a crown's points are green whatever their shape: the roofs of a stereo cloud
#: measure 0.35-0.49 on smooth gables of the frame family.
MIN_PLANAR_SHARE = 0.5
#: Below this planar share, a blob with any vegetation point at all is a tree.
PLANAR_SHARE_WITH_EVIDENCE = 0.55
#: Mean share of vegetation points that counts as "any" for PLANAR_SHARE_WITH_EVIDENCE.
SOME_VEGETATION_SHARE = 0.005
#: Points per square metre below which both planar shares are lowered in proportion: a
#: point's 10 neighbours then span more than 1.3 m, across ridges and eaves.
PLANAR_DENSITY = 2.0


def find_blobs(
    ndsm: Raster,
    vegetation: np.ndarray,
    config: BuildingsConfig,
    units: Units,
    *,
    planar: np.ndarray | None = None,
    point_density: float | None = None,
    colour: bool = False,
) -> Blobs:
    """Building candidates: the mask, split at height jumps, small parts merged, trees rejected.

    A blob needs ``min_area`` (a quarter of it when it touches the edge of the grid:
    the rest of the building may lie outside the data). A blob is a tree crown when its
    cells hold many vegetation points (mean share above 0.3), or when its DSM is rough
    (fewer than ``min_smooth_share`` of its inner cells smooth) and some of its points
    are vegetation (share above 0.05); a rough blob without any vegetation point is a
    steep roof. Given only vegetation cells (bool), roughness alone decides. Given the
    share of planar points per cell (``planar``), a blob whose inner cells hold on
    average fewer than :data:`MIN_PLANAR_SHARE` points on local planes is vegetation
    too, evidence or not: a dense cluster of crowns scanned without multiple returns or
    colours (a steep roof's points still lie on planes), unless the survey has colours;
    so is one below :data:`PLANAR_SHARE_WITH_EVIDENCE` with any vegetation point.

    Parameters
    ----------
    ndsm : Raster
    vegetation : (rows, cols) bool or float
        Vegetation cells, or the share of vegetation points per cell
        (:func:`vegetation_cells`, ``share=True``).
    config : BuildingsConfig
    units : Units
    planar : (rows, cols) float, optional
        Share of each cell's upper points on a local plane (:func:`planar_cells`).
    point_density : float, optional
        Points per square metre of the survey; below :data:`PLANAR_DENSITY` the planar
        shares needed fall in proportion.
    colour : bool
        The vegetation shares come from a colour index too: a crown's points are
        vegetation whatever their shape, so planarity alone rejects no blob. The points
        of a stereo cloud are noisier about their local planes than a LiDAR scan's, and
        smooth roofs with no vegetation point at all fell under
        :data:`MIN_PLANAR_SHARE` (frame family at 1000 px: 4 surveys of 25 lost 6-12 %
        of their buildings so).
    """
    smooth_all = smooth_cells(ndsm, config, units)
    mask = _building_mask(ndsm, vegetation, config, units, smooth_all)
    res = ndsm.resolution
    min_cells = max(1, int(math.ceil(units.area(config.min_area) / res**2)))
    labels, n = split_by_height(ndsm.data, mask, units.height(config.split_height))
    if n and config.split_step > 0 and config.split_height > 0:  # split_height 0: blocks whole
        labels, n = split_at_steps(
            ndsm.data, labels, res, min_step=units.height(config.split_step), min_area=units.area(config.min_area),
            min_width=units.length(config.min_split_width), valley_drop=units.height(VALLEY_DROP),
            valley_reach=units.length(VALLEY_REACH),
        )
    if n:
        labels, n = _consecutive(_merge_small(labels, n, min_cells))
    cells = np.bincount(labels.ravel(), minlength=n + 1)[1:].astype(np.float64)
    smooth = smooth_all & mask
    inner = ndimage.grey_erosion(labels, size=3) == labels  # away from walls and the blob's border
    inner &= labels > 0
    inner_cells = np.bincount(labels[inner], minlength=n + 1)[1:].astype(np.float64)
    smooth_inner = np.bincount(labels[inner & smooth], minlength=n + 1)[1:].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth_share = np.where(inner_cells > 0, smooth_inner / inner_cells, 0.0)
    height = _label_medians(np.nan_to_num(ndsm.data), labels, n).astype(np.float64)
    vegetation = np.asarray(vegetation)
    if vegetation.dtype == bool:
        veg_share = np.full(n, np.nan)
    else:
        sums = np.bincount(labels.ravel(), weights=np.nan_to_num(vegetation).ravel().astype(np.float64), minlength=n + 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            veg_share = np.where(cells > 0, sums[1:] / cells, 0.0)
    planar_share = np.full(n, np.nan)
    if planar is not None and n:
        where = inner if inner.any() else labels > 0
        sums = np.bincount(labels[where], weights=np.asarray(planar, np.float64)[where], minlength=n + 1)[1:]
        counts = np.bincount(labels[where], minlength=n + 1)[1:]
        # a blob too thin for inner cells is judged on all of its cells
        thin = counts == 0
        if thin.any():
            all_sums = np.bincount(labels.ravel(), weights=np.asarray(planar, np.float64).ravel(), minlength=n + 1)[1:]
            sums, counts = np.where(thin, all_sums, sums), np.where(thin, cells, counts)
        with np.errstate(invalid="ignore", divide="ignore"):
            planar_share = np.where(counts > 0, sums / counts, np.nan)
    # a blob cut by the edge of the data may be a corner of a larger building: judge it
    # against a quarter of the minimal area, so tiles give the same buildings as the whole
    edge = np.zeros(n + 1, bool)
    edge[np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))] = True
    need = np.where(edge[1:], min_cells / 4.0, min_cells)
    scale = 1.0 if point_density is None else min(1.0, point_density / PLANAR_DENSITY)
    min_planar, planar_with_evidence = MIN_PLANAR_SHARE * scale, PLANAR_SHARE_WITH_EVIDENCE * scale
    reason = []
    for i in range(n):
        rough = smooth_share[i] < config.min_smooth_share
        if cells[i] < need[i]:
            reason.append("small")
        elif np.isnan(veg_share[i]) and rough:
            reason.append("vegetation")
        elif veg_share[i] > VEGETATION_BLOB_SHARE or (rough and veg_share[i] > ROUGH_VEGETATION_SHARE):
            reason.append("vegetation")
        elif (planar_share[i] < min_planar and not colour) or (
            planar_share[i] < planar_with_evidence and veg_share[i] > SOME_VEGETATION_SHARE
        ):
            reason.append("vegetation")
        else:
            reason.append("")
    blobs = Blobs(labels, cells * res**2, height, smooth_share, veg_share, reason, planar_share, mask)
    log.info(
        "%d blobs: %d buildings, %d small, %d vegetation",
        n, int(blobs.kept.sum()), reason.count("small"), reason.count("vegetation"),
    )
    return blobs


# --------------------------------------------------------------------------- polygons


def blob_descriptors(polygon: shapely.Polygon) -> dict[str, float]:
    """Shape descriptors of a footprint.

    Returns
    -------
    dict
        ``area``, ``perimeter``; ``compactness`` U^2 / (4 pi A) (1 for a disc, 1.27 for a
        square, large for ragged or thin shapes); ``elongation`` long over short side of
        the minimum rotated rectangle; ``rectangularity`` area over that rectangle's area;
        ``fill_ratio`` area over the axis-aligned bounding box's area.
    """
    a, u = polygon.area, polygon.length
    rect = shapely.minimum_rotated_rectangle(polygon)
    xy = np.asarray(rect.exterior.coords)
    sides = np.hypot(*np.diff(xy[:3], axis=0).T) if len(xy) >= 3 else np.zeros(2)
    minx, miny, maxx, maxy = polygon.bounds
    box = (maxx - minx) * (maxy - miny)
    return {
        "area": float(a),
        "perimeter": float(u),
        "compactness": float(u * u / (4 * math.pi * a)) if a > 0 else math.inf,
        "elongation": float(sides.max() / sides.min()) if sides.min() > 0 else math.inf,
        "rectangularity": float(a / rect.area) if rect.area > 0 else 0.0,
        "fill_ratio": float(a / box) if box > 0 else 0.0,
    }


def detect_buildings(
    ndsm: Raster,
    vegetation: np.ndarray,
    config: BuildingsConfig,
    units: Units,
    *,
    cloud: PointCloud | None = None,
    dtm: Raster | None = None,
    point_vegetation: np.ndarray | None = None,
    planar: np.ndarray | None = None,
    point_density: float | None = None,
    fine: FineSurface | None = None,
    mapper=None,
    blobs: Blobs | None = None,
) -> list[shapely.Polygon]:
    """Footprint polygons of building blobs, largest first.

    Each kept blob (:func:`find_blobs`) is outlined along its cell edges (holes smaller
    than ``min_area`` filled: gaps in the data, not courtyards) and regularised
    (:func:`recon3d.buildings.outline.regularize`); parts of one block are then cut
    apart where their regularised outlines overlap, larger parts first.

    With the cloud and the terrain, outlines are delineated on a grid of half a cell
    (:func:`refine_labels`): the nDSM decides which buildings exist, the points where
    their walls stand.

    Parameters
    ----------
    ndsm : Raster
    vegetation : (rows, cols) bool or float
        Vegetation cells, or better the share of vegetation points per cell
        (:func:`vegetation_cells` with ``share=True``), also used as per-blob evidence.
    config : BuildingsConfig
    units : Units
    cloud : PointCloud, optional
    dtm : Raster, optional
        Both needed for the finer delineation (or ``fine`` and ``dtm``).
    point_vegetation : (n,) bool, optional
        Vegetation points (:func:`classify_vegetation`), kept out of the outlines.
    planar : (rows, cols) float, optional
        Share of each cell's upper points on a local plane (:func:`planar_cells`): blobs
        mostly off planes are trees (:func:`find_blobs`).
    point_density : float, optional
        Points per square metre (:func:`find_blobs`).
    fine : FineSurface, optional
        The cloud's first returns on the half-cell grid (:func:`fine_surface`),
        instead of ``cloud`` and ``point_vegetation``.
    mapper : callable, optional
        ``mapper(func, jobs)`` -> ``[func(job) for job in jobs]``, for outlining the blobs
        elsewhere (worker processes); in this process by default.
    blobs : Blobs, optional
        The candidates when the caller has found them already (:func:`find_blobs` with
        the same arguments): their mask serves it too.

    Returns
    -------
    list of shapely.Polygon
        Valid polygons, counter-clockwise exteriors.
    """
    if blobs is None:
        blobs = find_blobs(ndsm, vegetation, config, units, planar=planar, point_density=point_density)
    labels = np.where(np.r_[False, blobs.kept][blobs.labels], blobs.labels, 0)
    coarse = labels
    transform, res = ndsm.transform, ndsm.resolution
    if fine is None and cloud is not None:
        fine = fine_surface(cloud, ndsm, point_vegetation)
    if fine is not None and dtm is not None and labels.any():
        labels, transform = refine_labels(labels, ndsm, fine, dtm, config, units)
        res = transform.a
    min_area = units.area(config.min_area)
    min_edge = max(units.length(config.min_edge), 2 * res)
    extent = ndsm.bounds
    # blocks: touching kept blobs, found on the DSM grid (a whole-area labelling of the finer grid costs 4 x)
    blocks, n_blocks = ndimage.label(coarse > 0)
    block_of = np.zeros(int(coarse.max()) + 1, np.int64)
    block_of[coarse[coarse > 0]] = blocks[coarse > 0]
    shared = np.flatnonzero(np.bincount(block_of[1:], minlength=n_blocks + 1)[1:] >= 2) + 1
    # each piece, and each block of several pieces whole (on the DSM grid: outlined on the
    # pieces' finer grid it kept their bulges, the Delft strip's model DSM inside roofs
    # 0.71 m RMS against 0.62 m): the block's outline bounds its pieces'
    rest = (min_area, min_edge, config.regularize, extent)
    boxes = ndimage.find_objects(labels)
    pieces = [i + 1 for i, box in enumerate(boxes) if box is not None]
    jobs = [_outline_job(labels, i, boxes[i - 1], transform, res, rest) for i in pieces]
    block_boxes = ndimage.find_objects(blocks)
    jobs += [_outline_job(blocks, b, block_boxes[b - 1], ndsm.transform, ndsm.resolution, rest) for b in shared]
    outlines = (mapper or _serial)(outline_blob, jobs)
    bounds = dict(zip(shared.tolist(), outlines[len(pieces):], strict=True))
    polygons, owners = _within_blocks(outlines[: len(pieces)], pieces, block_of, bounds)
    polygons = _remove_overlaps(polygons, min_area / 4, res, owners=owners, labels=labels, transform=transform)
    if config.split_step > 0:
        polygons = _close_block_gaps(polygons, blocks, ndsm, ndsm.resolution)
    # the cuts between the parts of a block can leave zero-width needles on an outline
    polygons = [q for q in map(outline_mod.remove_spikes, polygons) if q is not None and q.area >= min_area / 4]
    polygons = [shapely.orient_polygons(q) for q in polygons]
    polygons.sort(key=lambda p: (-p.area, p.centroid.x, p.centroid.y))
    log.info("detected %d buildings", len(polygons))
    return polygons


def _serial(func, jobs: list) -> list:
    return [func(job) for job in jobs]


def _within_blocks(outlines: list, pieces: list[int], block_of: np.ndarray,
                   bounds: dict[int, shapely.Polygon | None]) -> tuple[list[shapely.Polygon], list[int]]:
    """The pieces' outlines (None dropped), each clipped to its block's outline, and their labels.

    A piece regularised on its own may carry a corner or a wall out past its block's
    wall (a step cut leaves it a short side to fit).

    Parameters
    ----------
    outlines : list of shapely.Polygon or None
        The regularised outline of each piece.
    pieces : list of int
        Their labels; ``block_of[label]`` is the piece's block.
    bounds : dict of int to shapely.Polygon or None
        The regularised outline of each block of several pieces.
    """
    polygons, owners = [], []
    for i, p in zip(pieces, outlines, strict=True):
        edge = bounds.get(int(block_of[i]))
        if p is not None and edge is not None and not edge.contains(p):
            p = outline_mod._valid_polygon(p.intersection(edge))
        if p is not None:
            polygons.append(shapely.orient_polygons(p))
            owners.append(i)
    return polygons, owners


def _outline_job(grid: np.ndarray, value: int, box: tuple[slice, slice], transform: Affine, res: float,
                 rest: tuple) -> tuple:
    """The :func:`outline_blob` job of the cells of ``grid`` equal to ``value``, whose
    box is ``box``, on the grid of ``transform`` and cell ``res``: a window one cell
    wider, then ``rest`` (smallest hole and edge, regularise, extent)."""
    box = tuple(slice(max(s.start - 1, 0), min(s.stop + 1, n)) for s, n in zip(box, grid.shape, strict=True))
    return (grid[box] == value, transform @ Affine.translation(box[1].start, box[0].start), res, *rest)


def outline_blob(job: tuple) -> shapely.Polygon | None:
    """The regularised outline of one blob (a job of :func:`detect_buildings`): its cells
    (a bool window), the window's transform, the cell, the smallest hole and edge kept,
    whether to regularise, and the data's extent (straight walls are not extended past it)."""
    sub, transform, res, min_area, min_edge, regularize, extent = job
    raw = outline_mod.raster_outline(sub, transform, min_hole_area=min_area)
    if raw is None:
        return None
    if regularize:
        poly = outline_mod.regularize(raw, cell=res, min_edge=min_edge, min_hole_area=min_area)
    else:
        poly = outline_mod._valid_polygon(raw.simplify(res, preserve_topology=True)) or raw
    box = shapely.box(*extent)
    if not box.contains(poly):  # straight walls extended past the edge of the data
        poly = outline_mod._valid_polygon(poly.intersection(box)) or raw
    return shapely.orient_polygons(poly)


#: How many times finer than the DSM's the grid is on which outlines are delineated.
FINE = 2


@dataclass
class FineSurface:
    """One first return (not noise) in each cell of a grid :data:`FINE` times finer
    than the DSM's (:func:`fine_surface`), and whether that point is vegetation.

    Attributes
    ----------
    z : (rows * FINE, cols * FINE) float64
        NaN where no first return fell.
    vegetation : (rows * FINE, cols * FINE) bool

    Both are only ever read a window at a time (``z[rows, cols]``), so anything indexed
    that way serves, such as a tiled run's
    :class:`~recon3d.pipeline.run.TileMosaic`.
    """

    z: np.ndarray
    vegetation: np.ndarray


def fine_surface(cloud: PointCloud, grid: Raster, vegetation: np.ndarray | None = None,
                 *, order: np.ndarray | None = None, pick: str = "nearest") -> FineSurface:
    """:class:`FineSurface` of ``cloud`` on ``grid`` (a window of the DSM grid, or all of it).

    Each fine cell takes the first return nearest its centre (``pick="nearest"``), so
    that the cells, and the outlines drawn along them, split the ground between the
    points as a Voronoi diagram does: a cell an eave crosses is raised as often as it is
    not. Taking the highest return instead (``pick="highest"``) raises it whenever one
    roof point fell in it, which moved LiDAR outlines out by a sixth of a fine cell on
    average (0.1-0.4 m at 1-7 points/m2, measured on the random LiDAR family); matched
    stereo clouds want it still, their roof edges being torn by occlusion and filled
    low.

    Parameters
    ----------
    cloud : PointCloud
    grid : Raster
    vegetation : (n,) bool, optional
    order : (n,) int, optional
        The points' order in the survey (default: as given): ties go to the earlier
        point (``"nearest"``) or the later one (``"highest"``).
    pick : {"nearest", "highest"}
    """
    rows, cols = grid.shape
    keep = np.ones(len(cloud), bool)
    a = cloud.attributes
    if "return_number" in a:
        keep &= np.asarray(a["return_number"]) <= 1
    if cloud.classification is not None:
        keep &= cloud.classification != ASPRS.NOISE
    transform = grid.transform @ Affine.scale(1.0 / FINE)  # exact: the cell halves
    origin = (grid.origin[0] * FINE, grid.origin[1] * FINE)
    shape = (rows * FINE, cols * FINE)
    z = np.full(shape[0] * shape[1], np.nan)
    veg = np.zeros(shape[0] * shape[1], bool)
    idx = np.flatnonzero(keep)
    cell, ok = cell_index(cloud.xyz[idx], transform, shape, origin=origin)
    if ok is not None:
        idx, cell = idx[ok], cell[ok]
    if len(idx):
        rank = np.arange(len(cloud)) if order is None else np.asarray(order)
        if pick == "highest":
            sort = np.lexsort((rank[idx], cloud.xyz[idx, 2], cell))  # by cell, height, survey order
        else:
            col = (cloud.xyz[idx, 0] - transform.c) / transform.a
            row = (cloud.xyz[idx, 1] - transform.f) / transform.e
            off = (col - np.floor(col) - 0.5) ** 2 + (row - np.floor(row) - 0.5) ** 2
            sort = np.lexsort((-rank[idx], -off, cell))  # by cell, distance from the centre (farthest first)
        idx, cell = idx[sort], cell[sort]
        last = np.r_[cell[1:] != cell[:-1], True]  # each cell's chosen point
        z[cell[last]] = cloud.xyz[idx[last], 2]
        if vegetation is not None:
            veg[cell[last]] = np.asarray(vegetation, bool)[idx[last]]
    return FineSurface(z.reshape(shape), veg.reshape(shape))


def refine_labels(
    labels: np.ndarray,
    grid: Raster,
    fine: FineSurface,
    dtm: Raster,
    config: BuildingsConfig,
    units: Units,
) -> tuple[np.ndarray, Affine]:
    """Blob labels on a grid :data:`FINE` times finer, delineated by the points.

    A highest-point DSM marks a cell raised when any of its points is on the roof, so a
    blob's border wanders by up to a cell. Each fine cell within one coarse cell of a
    blob takes instead its own first return (:func:`fine_surface`), or, when empty, that
    of the nearest filled fine cell (a Voronoi cut of the surface seen from above, on the
    grid); it belongs to the blob when that point stands at least
    ``min(grow_height, min_height)`` above the terrain and is not vegetation.
    Fine cells with no point within a coarse cell keep the coarse answer. A 3 x 3
    majority vote then removes speckle without moving the border.

    Parameters
    ----------
    labels : (rows, cols) int
        Blob labels on ``grid`` (0 background).
    grid : Raster
    fine : FineSurface
        On ``grid`` (:func:`fine_surface`).
    dtm : Raster
    config : BuildingsConfig
    units : Units

    Returns
    -------
    fine_labels : (rows * FINE, cols * FINE) int32
    fine_transform : Affine
    """
    factor = FINE
    rows, cols = labels.shape
    transform = grid.transform @ Affine.scale(1.0 / factor)
    out = np.zeros((rows * factor, cols * factor), np.int32)
    if not labels.any():
        return out, transform
    # work in the blobs' bounding box (plus a margin of two coarse cells), a strip of
    # rows at a time: memory bounded by the strip, not the survey
    r0, c0 = np.maximum(np.argwhere(labels > 0).min(axis=0) - 2, 0)
    r1, c1 = np.minimum(np.argwhere(labels > 0).max(axis=0) + 3, (rows, cols))
    min_height = units.height(min(config.grow_height, config.min_height))
    for top in range(r0, r1, REFINE_STRIP):
        bottom = min(top + REFINE_STRIP, r1)
        lo, hi = max(top - REFINE_HALO, r0), min(bottom + REFINE_HALO, r1)
        part = _refine_window(labels, fine, dtm, (lo, hi, c0, c1), min_height)
        out[top * factor:bottom * factor, c0 * factor:c1 * factor] = part[(top - lo) * factor:(bottom - lo) * factor]
    return out, transform


#: Coarse rows :func:`refine_labels` delineates at a time, and the rows it reads beyond
#: them on either side: a fine cell's answer depends on cells up to 4 coarse cells away
#: (the zone around a blob, the points near it, the nearest filled cell, the vote).
REFINE_STRIP = 256
REFINE_HALO = 8


def _refine_window(labels: np.ndarray, fine: FineSurface, dtm: Raster, box: tuple[int, int, int, int],
                   min_height: float) -> np.ndarray:
    """:func:`refine_labels` over the coarse cells ``[r0:r1, c0:c1]`` of ``box``: their fine labels."""
    factor = FINE
    r0, r1, c0, c1 = box
    lab = labels[r0:r1, c0:c1]
    zone = np.where(lab > 0, lab, ndimage.grey_dilation(lab, size=3))
    coarse = lab.repeat(factor, 0).repeat(factor, 1)
    zone = zone.repeat(factor, 0).repeat(factor, 1)
    window = (slice(r0 * factor, r1 * factor), slice(c0 * factor, c1 * factor))
    near = ndimage.binary_dilation(zone > 0, iterations=factor)  # the points that can matter
    top = np.where(near, fine.z[window], np.nan)
    raised = coarse > 0
    empty = ~np.isfinite(top)
    if not empty.all():
        # an empty cell takes its nearest filled cell within one coarse cell (a Voronoi
        # cut of the surface, on the grid)
        dist, (nr, nc) = ndimage.distance_transform_edt(empty, return_indices=True)
        found = dist <= factor
        nr, nc = nr[found], nc[found]
        ground = dtm.data[r0 + nr // factor, c0 + nc // factor].astype(np.float64)
        h = top[nr, nc] - ground
        up = np.nan_to_num(h, nan=-np.inf) >= min_height
        up &= ~fine.vegetation[window][nr, nc]
        raised[found] = up
    mask = raised & (zone > 0)
    # the blob is decided: only speckle goes, by a 3 x 3 majority vote (an opening would
    # shave the ragged Voronoi border and bias every outline inwards)
    votes = ndimage.uniform_filter(mask.astype(np.float32), size=3, mode="nearest") * 9.0
    mask = (votes >= 4.5) & (zone > 0)
    part = np.where(mask, zone, 0)
    # a blob must not lose its core to a neighbour's ring: coarse cells keep their own label
    return np.where(mask & (coarse > 0), coarse, part)


def _close_block_gaps(polygons: list[shapely.Polygon], regions: np.ndarray, grid: Raster, gap: float) -> list[shapely.Polygon]:
    """Fill the gaps narrower than ``2 * gap`` left between the regularised parts of one block.

    Each part is regularised on its own, so two parts of a block need not share their
    wall exactly; a slit between them (along at least ``2 * gap`` of both) joins the
    one it shares the longest border with, when that leaves a clean polygon.
    Blocks are the labelled ``regions`` (touching kept blobs, on ``grid``); buildings
    apart stay apart.
    """
    if len(polygons) < 2:
        return polygons
    pts = shapely.point_on_surface(polygons)
    inv = ~grid.transform
    x, y = shapely.get_x(pts), shapely.get_y(pts)
    col = inv.a * x + inv.b * y + inv.c
    row = inv.d * x + inv.e * y + inv.f
    row = np.clip(np.floor(row).astype(int), 0, regions.shape[0] - 1)
    col = np.clip(np.floor(col).astype(int), 0, regions.shape[1] - 1)
    region = regions[row, col]
    out = list(polygons)
    for r in np.unique(region[region > 0]):
        members = np.flatnonzero(region == r)
        if len(members) < 2:
            continue
        block = shapely.union_all([out[i] for i in members])
        closed = block.buffer(gap, join_style="mitre").buffer(-gap, join_style="mitre")
        gaps = closed.difference(block)
        for g in getattr(gaps, "geoms", [gaps]):
            if g.is_empty or g.geom_type != "Polygon":
                continue
            near = g.buffer(gap * 1e-3)
            shared = np.array([out[i].boundary.intersection(near).length for i in members])
            if np.sort(shared)[-2] < 2 * gap:  # a slit along a wall between two parts, not a notch
                continue
            k = members[int(np.argmax(shared))]
            # an opening of a centimetre drops the zero-width spikes a union can leave
            grown = out[k].union(g).buffer(-gap * 0.02, join_style="mitre").buffer(gap * 0.02, join_style="mitre")
            # only a clean fill: one ring as simple as before, no new hole, no pinch
            if (
                grown.geom_type == "Polygon" and grown.is_valid and grown.exterior.is_simple
                and len(grown.interiors) == len(out[k].interiors)
                and abs(grown.area - out[k].area - g.area) <= 1e-3 * max(grown.area, 1.0)
            ):
                out[k] = shapely.orient_polygons(shapely.simplify(grown, gap * 0.02))
    return out


def _remove_overlaps(polygons: list[shapely.Polygon], min_area: float, cell: float, *, owners: list[int] | None = None,
                     labels: np.ndarray | None = None, transform: Affine | None = None) -> list[shapely.Polygon]:
    """Cut each overlap of two polygons out of one of them: the one with fewer of its own
    cells in it (``labels`` equal to its ``owners`` entry, on the grid of ``transform``),
    or without cells, the smaller. Regularised outlines of touching parts overlap
    along their shared wall; the cells say whose wall it is. ``cell``: the grid's cell
    (CRS units), a fiftieth of which is the narrowest part a cut polygon keeps.
    """
    eps = 0.02 * cell
    n = len(polygons)
    if n < 2:
        return polygons
    area = np.array([p.area for p in polygons])
    left, right = shapely.STRtree(polygons).query(polygons, predicate="intersects")
    keep = left < right
    cut: list[list[int]] = [[] for _ in range(n)]
    for a, b in zip(left[keep], right[keep], strict=True):
        overlap = polygons[a].intersection(polygons[b])
        if overlap.area <= 0:
            continue
        ca, cb = (_cells_in(overlap, owners[k], labels, transform) for k in (a, b)) if owners else (0, 0)
        if (ca, area[a], -a) > (cb, area[b], -b):  # a keeps the overlap
            cut[b].append(a)
        else:
            cut[a].append(b)
    out = []
    for k in np.lexsort((np.arange(n), -area)):  # larger first, as before
        p = polygons[k]
        if cut[k]:
            p = p.difference(shapely.union_all([polygons[j] for j in cut[k]]))
            # an opening of a fiftieth of a cell drops the slivers a cut along a nearly shared wall leaves
            p = outline_mod._valid_polygon(p.buffer(-eps, join_style="mitre").buffer(eps, join_style="mitre"))
            if p is None or p.area < min_area:
                continue
            p = shapely.orient_polygons(shapely.simplify(p, eps))
        out.append(p)
    return out


def _cells_in(region: shapely.Geometry, value: int, labels: np.ndarray, transform: Affine) -> int:
    """Cells of ``labels`` equal to ``value`` whose centres lie in ``region``."""
    inv = ~transform
    x0, y0, x1, y1 = region.bounds
    corners = np.array([inv @ (x, y) for x in (x0, x1) for y in (y0, y1)])  # (4, 2) col, row
    c0, r0 = np.maximum(np.floor(corners.min(axis=0)).astype(int), 0)
    c1, r1 = np.ceil(corners.max(axis=0)).astype(int) + 1
    r, c = np.nonzero(labels[r0:r1, c0:c1] == value)
    x = transform.a * (c + c0 + 0.5) + transform.b * (r + r0 + 0.5) + transform.c
    y = transform.d * (c + c0 + 0.5) + transform.e * (r + r0 + 0.5) + transform.f
    return int(shapely.contains_xy(region, x, y).sum())


def label_footprints(polygons: list[shapely.Polygon], grid: Raster, *, all_touched: bool = False) -> np.ndarray:
    """(rows, cols) int32 image: 1 + index of the footprint covering each cell, 0 elsewhere."""
    if not polygons:
        return np.zeros(grid.shape, np.int32)
    shapes = ((p, i + 1) for i, p in enumerate(polygons))
    return rasterio.features.rasterize(
        shapes, out_shape=grid.shape, transform=grid.transform, fill=0, dtype="int32", all_touched=all_touched
    )


