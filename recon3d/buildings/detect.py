"""Building candidates: blobs of the nDSM, trees told apart, or footprints given by the user.

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
  ``min_area`` (chimneys, dormers) rejoin the part they share the longest border with;
* trees never become buildings. Each point above the terrain gets covariance features
  of its neighbourhood (roughness, planarity, scattering...); a rough point that is
  also a multi-return echo or green (NDVI with a near-infrared channel, excess green
  with RGB only) is vegetation, after a majority vote among its neighbours. Cells whose
  upper points are mostly vegetation leave the mask; a blob with many vegetation points,
  or rough (a crown) with some, is rejected; vegetation points are never labelled
  building;
* outlines are delineated on a grid of half a cell from the points themselves
  (:func:`refine_labels`) and regularised (:mod:`recon3d.buildings.outline`).

With footprints given instead, :func:`align_footprints` estimates the map-to-data shift
(up to ``footprint_shift``) against the building evidence and reports footprints that
have no data or no building under them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import rasterio.features
import shapely
from affine import Affine
from scipy import ndimage, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from recon3d.buildings import outline as outline_mod
from recon3d.config import BuildingsConfig
from recon3d.core.city import Building
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.terrain.dsm import grid_points

log = logging.getLogger(__name__)

__all__ = [
    "Blobs",
    "align_footprints",
    "assign_blocks",
    "blob_descriptors",
    "building_evidence",
    "building_mask",
    "classify_vegetation",
    "detect_buildings",
    "find_blobs",
    "label_footprints",
    "point_classes",
    "point_features",
    "refine_labels",
    "split_by_height",
    "vegetation_cells",
    "vegetation_index",
]


# --------------------------------------------------------------------------- points


def point_features(xyz: np.ndarray, *, k: int = 10, workers: int = -1) -> dict[str, np.ndarray]:
    """Covariance features of each point's k nearest neighbours (the point included).

    Parameters
    ----------
    xyz : (n, 3) float
    k : int
        Neighbourhood size (clipped to n).
    workers : int
        Threads for the k-d tree query (-1: all cores).

    Returns
    -------
    dict of str to (n,) float
        ``roughness`` (square root of the smallest eigenvalue: RMS distance to the best
        plane, CRS units), ``planarity`` (l2 - l3) / l1, ``linearity`` (l1 - l2) / l1
        and ``scattering`` l3 / l1; and ``neighbours`` (n, k) int, indices of each
        point's neighbours.
    """
    xyz = np.asarray(xyz, np.float64)
    n = len(xyz)
    names = ("roughness", "planarity", "linearity", "scattering")
    out = {key: np.zeros(n) for key in names}
    if n == 0:
        out["neighbours"] = np.zeros((0, 0), np.int64)
        return out
    k = max(1, min(k, n))
    centred = xyz - xyz.mean(axis=0)
    _, nb = cKDTree(centred).query(centred, k=k, workers=workers)
    nb = nb.reshape(n, k)
    for s in range(0, n, CHUNK):  # bounded memory: (chunk, k, 3) at a time
        sl = slice(s, min(s + CHUNK, n))
        p = centred[nb[sl]]
        p -= p.mean(axis=1, keepdims=True)
        w = np.linalg.eigvalsh(np.matmul(p.transpose(0, 2, 1), p) / k)
        l3, l2, l1 = (np.clip(w[:, i], 0.0, None) for i in range(3))
        safe = np.where(l1 > 0, l1, 1.0)
        out["roughness"][sl] = np.sqrt(l3)
        out["planarity"][sl] = np.where(l1 > 0, (l2 - l3) / safe, 0.0)
        out["linearity"][sl] = np.where(l1 > 0, (l1 - l2) / safe, 0.0)
        out["scattering"][sl] = np.where(l1 > 0, l3 / safe, 0.0)
    out["neighbours"] = nb
    return out


#: Points per block of the covariance features (memory: block x k x 3 doubles).
CHUNK = 200_000


def vegetation_index(cloud: PointCloud) -> tuple[np.ndarray, str] | None:
    """(n,) colour vegetation index and its name, None for a cloud without colours.

    NDVI (nir - red) / (nir + red) when a near-infrared channel holds data, else the
    normalised excess green (2 g - r - b) / (r + g + b) of the RGB channels (IGN LiDAR
    HD files carry a ``nir`` dimension that may be all zeros).
    """
    a = cloud.attributes
    if not {"red", "green", "blue"} <= set(a):
        return None
    r, g, b = (np.asarray(a[key], np.float64) for key in ("red", "green", "blue"))
    with np.errstate(invalid="ignore", divide="ignore"):
        if "nir" in a and np.any(np.asarray(a["nir"]) > 0):
            nir = np.asarray(a["nir"], np.float64)
            return np.nan_to_num((nir - r) / (nir + r)), "ndvi"
        if not np.any(r + g + b > 0):
            return None
        return np.nan_to_num((2 * g - r - b) / (r + g + b)), "exg"


#: Colour index above which a point looks like vegetation (NDVI, excess green).
GREEN_THRESHOLDS = {"ndvi": 0.3, "exg": 0.05}
#: Stricter thresholds when colour is the only evidence (stereo): grey gravel and
#: concrete roofs reach an excess green of 0.1 in aerial images, foliage 0.2 and more.
COLOUR_ONLY_THRESHOLDS = {"ndvi": 0.3, "exg": 0.15}


def classify_vegetation(
    cloud: PointCloud, dtm: Raster, config: BuildingsConfig, units: Units, *, noise: float = 0.0
) -> np.ndarray:
    """(n,) bool: points of trees and bushes (ASPRS class 5 in cloud.laz).

    A point at least ``vegetation_min_height`` above the terrain is vegetation when its
    neighbourhood is rough (RMS about the best plane above ``vegetation_roughness``;
    roofs and walls are planar) and it carries vegetation evidence: an echo of a
    multi-return pulse (leaves let part of the pulse through, roofs do not), or a green
    colour (NDVI > 0.3, or excess green > 0.05 with RGB only). A coloured cloud without
    returns (stereo) is judged on colour alone: dense matching smooths tree crowns until
    they are as planar as roofs. A cloud with neither returns nor colours falls back on
    scattering l3 / l1 > 0.05, and its roughness threshold rises to 3 x the cloud's
    measured height ``noise`` (a noisy roof is as rough as its noise). The decision
    is then smoothed by a majority vote among the ``vegetation_neighbours`` neighbours.

    Parameters
    ----------
    cloud : PointCloud
    dtm : Raster
    config : BuildingsConfig
    units : Units
    noise : float
        Height noise of the cloud (CRS height units), e.g. the ground filter's estimate.
    """
    n = len(cloud)
    out = np.zeros(n, bool)
    if n == 0:
        return out
    xyz = cloud.xyz
    height = xyz[:, 2] - dtm.sample(xyz[:, 0], xyz[:, 1], bilinear=False)
    cand = np.nan_to_num(height, nan=-np.inf) >= units.height(config.vegetation_min_height)
    c = cloud.classification
    if c is not None:
        cand &= c != ASPRS.NOISE
    idx = np.flatnonzero(cand)
    if len(idx) < 3:
        return out
    feats = point_features(xyz[idx], k=config.vegetation_neighbours)
    evidence = np.zeros(len(idx), bool)
    a = cloud.attributes
    have_returns = "number_of_returns" in a and np.any(np.asarray(a["number_of_returns"]) > 1)
    if have_returns:
        evidence |= np.asarray(a["number_of_returns"])[idx] > 1
    colour = vegetation_index(cloud)
    if colour is not None:
        evidence |= colour[0][idx] > GREEN_THRESHOLDS[colour[1]]
    if not have_returns and colour is None:
        evidence |= feats["scattering"] > 0.05
    if colour is not None and not have_returns:
        # photogrammetric surfaces: the matcher smooths tree crowns (roughness 0.04 m,
        # like roofs' 0.035 m on the rendered city) while their colour stays green
        veg = colour[0][idx] > COLOUR_ONLY_THRESHOLDS[colour[1]]
    else:
        rough = units.height(config.vegetation_roughness)
        if not have_returns and colour is None:  # shape alone: a noisy roof is as rough as its noise
            rough = max(rough, 3.0 * noise)
        veg = (feats["roughness"] > rough) & evidence
    veg = veg[feats["neighbours"]].mean(axis=1) > 0.5
    out[idx] = veg
    log.info("vegetation: %d of %d points above %.1f m", int(veg.sum()), len(idx), config.vegetation_min_height)
    return out


def vegetation_cells(
    cloud: PointCloud,
    grid: Raster,
    vegetation: np.ndarray | None = None,
    *,
    depth: float | None = None,
    share: bool = False,
) -> np.ndarray:
    """(rows, cols) bool: cells whose upper points are mostly vegetation (or the share).

    Parameters
    ----------
    cloud : PointCloud
    grid : Raster
        The grid (usually the DSM).
    vegetation : (n,) bool, optional
        Per-point vegetation (:func:`classify_vegetation`). Without it, the cells where
        most points belong to multi-return pulses (all False without return numbers).
    depth : float, optional
        Points within this height (CRS units) of a cell's highest point vote; 1.5 cells
        by default, so ground points under a crown do not outvote it.
    share : bool
        Return the share of vegetation among the voting points instead, (rows, cols)
        float in [0, 1], 0 in empty cells; :func:`detect_buildings` takes either and
        uses the share as per-blob evidence too.
    """
    xyz = cloud.xyz
    if vegetation is None:
        a = cloud.attributes
        if "number_of_returns" not in a:
            return np.zeros(grid.shape, np.float32 if share else bool)
        multi = (np.asarray(a["number_of_returns"]) > 1).astype(np.float64)
        values = np.nan_to_num(grid_points(np.column_stack([xyz[:, :2], multi]), grid.transform, grid.shape, reducer="mean"))
        return values.astype(np.float32) if share else values > 0.5
    depth = 1.5 * grid.resolution if depth is None else depth
    top = grid_points(xyz, grid.transform, grid.shape, reducer="max")
    row, col = grid.rowcol(xyz[:, 0], xyz[:, 1])
    rows, cols = grid.shape
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    ok[ok] = xyz[ok, 2] >= top[row[ok], col[ok]] - depth
    flat = row[ok] * cols + col[ok]
    votes = np.bincount(flat, weights=np.asarray(vegetation, bool)[ok].astype(np.float64), minlength=rows * cols)
    count = np.bincount(flat, minlength=rows * cols)
    if share:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(count > 0, votes / count, 0.0).reshape(grid.shape).astype(np.float32)
    return (votes > 0.5 * count).reshape(grid.shape)


def point_classes(
    cloud: PointCloud,
    is_ground: np.ndarray,
    labels: np.ndarray,
    grid: Raster,
    dtm: Raster,
    config: BuildingsConfig,
    units: Units,
    *,
    vegetation: np.ndarray | None = None,
    with_solid: np.ndarray | None = None,
) -> np.ndarray:
    """(n,) uint8 ASPRS classes of recon3d's cloud: 2 ground, 5 vegetation, 6 building, 1 other.

    A point is building when it lies in a footprint cell (``labels`` > 0, and the
    footprint has a solid when ``with_solid`` is given), is not ground nor vegetation,
    and stands at least ``min_height / 2`` above the terrain. Vegetation wins over
    building: a crown over a roof stays a tree.

    Parameters
    ----------
    cloud : PointCloud
    is_ground : (n,) bool
    labels : (rows, cols) int
        1 + footprint index per cell (:func:`label_footprints`).
    grid, dtm : Raster
        The grid of ``labels`` and the terrain.
    config : BuildingsConfig
    units : Units
    vegetation : (n,) bool, optional
    with_solid : (m + 1,) bool, optional
        Per label value (index 0 = background) whether that footprint counts.
    """
    xyz = cloud.xyz
    classes = np.full(len(cloud), ASPRS.UNCLASSIFIED, np.uint8)
    row, col = grid.rowcol(xyz[:, 0], xyz[:, 1])
    rows, cols = grid.shape
    ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    lab = np.zeros(len(cloud), np.int64)
    lab[ok] = labels[row[ok], col[ok]]
    in_building = lab > 0 if with_solid is None else np.asarray(with_solid, bool)[lab]
    above = xyz[:, 2] - dtm.sample(xyz[:, 0], xyz[:, 1], bilinear=False)
    building = in_building & ~is_ground & (np.nan_to_num(above, nan=-np.inf) >= units.height(config.min_height / 2))
    if vegetation is not None:
        vegetation = np.asarray(vegetation, bool) & ~is_ground
        building &= ~vegetation
        classes[vegetation] = ASPRS.HIGH_VEGETATION
    classes[building] = ASPRS.BUILDING
    classes[is_ground] = ASPRS.GROUND
    return classes


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
    return _building_mask(ndsm, vegetation, config, units, _smooth_cells(ndsm, config, units))


def _smooth_cells(ndsm: Raster, config: BuildingsConfig, units: Units) -> np.ndarray:
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
    veg = _vegetation_mask(vegetation)
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


def _vegetation_mask(vegetation: np.ndarray) -> np.ndarray:
    """Vegetation cells from a bool mask or a share of vegetation points (> 0.5)."""
    vegetation = np.asarray(vegetation)
    return vegetation if vegetation.dtype == bool else np.nan_to_num(vegetation) > 0.5


def building_evidence(ndsm: Raster, vegetation: np.ndarray, config: BuildingsConfig, units: Units) -> Raster:
    """The building mask as a raster for :func:`align_footprints`: 1 building, 0 not, NaN no data."""
    mask = building_mask(ndsm, vegetation, config, units)
    data = np.where(np.isfinite(ndsm.data), mask.astype(np.float32), np.nan)
    return ndsm.like(data, product="building evidence")


def _roughness(height: np.ndarray) -> np.ndarray:
    """(rows, cols) RMS of the 3 x 3 neighbourhood about its least-squares plane."""
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
    rows, cols = mask.shape
    ids = np.flatnonzero(mask.ravel())
    if split <= 0:
        labels, n = ndimage.label(mask)
        return labels.astype(np.int32), n
    h = np.nan_to_num(height.astype(np.float64))
    pairs = []
    for a, b in (
        (np.s_[:, :-1], np.s_[:, 1:]),
        (np.s_[:-1, :], np.s_[1:, :]),
    ):
        both = mask[a] & mask[b] & (np.abs(h[a] - h[b]) <= split)
        flat = np.arange(rows * cols).reshape(rows, cols)
        pairs.append(np.column_stack([flat[a][both], flat[b][both]]))
    edges = np.concatenate(pairs)
    pos = np.full(rows * cols, -1, np.int64)
    pos[ids] = np.arange(len(ids))
    g = sparse.coo_matrix((np.ones(len(edges)), (pos[edges[:, 0]], pos[edges[:, 1]])), shape=(len(ids), len(ids)))
    n, comp = csgraph.connected_components(g, directed=False)
    labels = np.zeros(rows * cols, np.int32)
    labels[ids] = comp + 1
    return labels.reshape(rows, cols), n


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
        mapping = np.arange(n + 1)
        mapping[src[first]] = dst[first]
        # a small part absorbed by another small part that itself moves: follow the chain
        for _ in range(8):
            mapping = mapping[mapping]
        labels = mapping[labels].astype(np.int32)
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
    reason : list of str
        Empty for kept blobs, else why the blob is not a building: "small", or
        "vegetation" (a tree crown: rough, or with many vegetation points).
    """

    labels: np.ndarray
    area: np.ndarray
    height: np.ndarray
    smooth_share: np.ndarray
    vegetation_share: np.ndarray
    reason: list[str] = field(default_factory=list)

    @property
    def kept(self) -> np.ndarray:
        """(m,) bool: blobs that are buildings."""
        return np.array([not r for r in self.reason], bool)


#: Mean share of vegetation points above which a blob is a tree whatever its shape.
VEGETATION_BLOB_SHARE = 0.3
#: Mean share of vegetation points above which a rough blob is a tree; below it a rough
#: blob with no vegetation evidence is a steep roof (a spire, a tower's pyramid).
ROUGH_VEGETATION_SHARE = 0.05


def find_blobs(ndsm: Raster, vegetation: np.ndarray, config: BuildingsConfig, units: Units) -> Blobs:
    """Building candidates: the mask, split at height jumps, small parts merged, trees rejected.

    A blob needs ``min_area`` (a quarter of it when it touches the edge of the grid:
    the rest of the building may lie outside the data). A blob is a tree crown when its
    cells hold many vegetation points (mean share above 0.3), or when its DSM is rough
    (fewer than ``min_smooth_share`` of its inner cells smooth) and some of its points
    are vegetation (share above 0.05); a rough blob without any vegetation point is a
    steep roof. Given only vegetation cells (bool), roughness alone decides.

    Parameters
    ----------
    ndsm : Raster
    vegetation : (rows, cols) bool or float
        Vegetation cells, or the share of vegetation points per cell
        (:func:`vegetation_cells`, ``share=True``).
    config : BuildingsConfig
    units : Units
    """
    smooth_cells = _smooth_cells(ndsm, config, units)
    mask = _building_mask(ndsm, vegetation, config, units, smooth_cells)
    res = ndsm.resolution
    min_cells = max(1, int(math.ceil(units.area(config.min_area) / res**2)))
    labels, n = split_by_height(ndsm.data, mask, units.height(config.split_height))
    if n:
        labels = _merge_small(labels, n, min_cells)
        uniq, labels = np.unique(labels, return_inverse=True)
        labels = labels.reshape(mask.shape).astype(np.int32)
        if uniq[0] != 0:  # no background cell at all: one roof over the whole tile
            labels += 1
        n = int(labels.max())
    index = np.arange(1, n + 1)
    cells = np.bincount(labels.ravel(), minlength=n + 1)[1:].astype(np.float64)
    smooth = smooth_cells & mask
    inner = ndimage.grey_erosion(labels, size=3) == labels  # away from walls and the blob's border
    inner &= labels > 0
    inner_cells = np.bincount(labels[inner], minlength=n + 1)[1:].astype(np.float64)
    smooth_inner = np.bincount(labels[inner & smooth], minlength=n + 1)[1:].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth_share = np.where(inner_cells > 0, smooth_inner / inner_cells, 0.0)
    height = (
        np.asarray(ndimage.median(np.nan_to_num(ndsm.data), labels, index), np.float64) if n else np.zeros(0)
    )
    vegetation = np.asarray(vegetation)
    if vegetation.dtype == bool:
        veg_share = np.full(n, np.nan)
    else:
        sums = np.bincount(labels.ravel(), weights=np.nan_to_num(vegetation).ravel().astype(np.float64), minlength=n + 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            veg_share = np.where(cells > 0, sums[1:] / cells, 0.0)
    # a blob cut by the edge of the data may be a corner of a larger building: judge it
    # against a quarter of the minimal area, so tiles give the same buildings as the whole
    edge = np.zeros(n + 1, bool)
    edge[np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))] = True
    need = np.where(edge[1:], min_cells / 4.0, min_cells)
    reason = []
    for i in range(n):
        rough = smooth_share[i] < config.min_smooth_share
        if cells[i] < need[i]:
            reason.append("small")
        elif np.isnan(veg_share[i]) and rough:
            reason.append("vegetation")
        elif veg_share[i] > VEGETATION_BLOB_SHARE or (rough and veg_share[i] > ROUGH_VEGETATION_SHARE):
            reason.append("vegetation")
        else:
            reason.append("")
    blobs = Blobs(labels, cells * res**2, height, smooth_share, veg_share, reason)
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
        Both needed for the finer delineation.
    point_vegetation : (n,) bool, optional
        Vegetation points (:func:`classify_vegetation`), kept out of the outlines.

    Returns
    -------
    list of shapely.Polygon
        Valid polygons, counter-clockwise exteriors.
    """
    blobs = find_blobs(ndsm, vegetation, config, units)
    labels = np.where(np.r_[False, blobs.kept][blobs.labels], blobs.labels, 0)
    transform, res = ndsm.transform, ndsm.resolution
    if cloud is not None and dtm is not None and labels.any():
        labels, transform = refine_labels(labels, ndsm, cloud, dtm, config, units, vegetation=point_vegetation)
        res = transform.a
    min_area = units.area(config.min_area)
    min_edge = max(units.length(config.min_edge), 2 * res)
    extent = shapely.box(*ndsm.bounds)
    polygons = []
    for i, sl in enumerate(ndimage.find_objects(labels)):
        if sl is None:
            continue
        sl = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in sl)
        sub = labels[sl] == i + 1
        raw = outline_mod.raster_outline(sub, transform @ Affine.translation(sl[1].start, sl[0].start), min_hole_area=min_area)
        if raw is None:
            continue
        if config.regularize:
            poly = outline_mod.regularize(raw, cell=res, min_edge=min_edge, min_hole_area=min_area)
        else:
            poly = outline_mod._valid_polygon(raw.simplify(res, preserve_topology=True)) or raw
        if not extent.contains(poly):  # straight walls extended past the edge of the data
            poly = outline_mod._valid_polygon(poly.intersection(extent)) or raw
        polygons.append(shapely.orient_polygons(poly))
    polygons = _remove_overlaps(polygons, min_area / 4)
    polygons.sort(key=lambda p: (-p.area, p.centroid.x, p.centroid.y))
    log.info("detected %d buildings", len(polygons))
    return polygons


def refine_labels(
    labels: np.ndarray,
    grid: Raster,
    cloud: PointCloud,
    dtm: Raster,
    config: BuildingsConfig,
    units: Units,
    *,
    vegetation: np.ndarray | None = None,
    factor: int = 2,
) -> tuple[np.ndarray, Raster]:
    """Blob labels on a grid ``factor`` times finer, delineated by the points.

    A highest-point DSM marks a cell raised when any of its points is on the roof, so a
    blob's border wanders by up to a cell. Each fine cell within one coarse cell of a
    blob takes instead its highest first-return point, or, when empty, that of the
    nearest filled fine cell (a Voronoi cut of the surface seen from above, on the
    grid); it belongs to the blob when that point stands at least
    ``min(grow_height, min_height)`` above the terrain and is not vegetation.
    Fine cells with no point within a coarse cell keep the coarse answer. A 3 x 3
    majority vote then removes speckle without moving the border.

    Parameters
    ----------
    labels : (rows, cols) int
        Blob labels on ``grid`` (0 background).
    grid : Raster
    cloud : PointCloud
    dtm : Raster
    config : BuildingsConfig
    units : Units
    vegetation : (n,) bool, optional
    factor : int

    Returns
    -------
    fine_labels : (rows * factor, cols * factor) int32
    fine_grid : Raster
        An empty raster (zeros) carrying the fine grid's transform and CRS.
    """
    rows, cols = labels.shape
    fres = grid.resolution / factor
    transform = grid.transform @ Affine.scale(1.0 / factor)
    fine = np.zeros((rows * factor, cols * factor), np.int32)
    if not labels.any():
        return fine, transform
    # work in the blobs' bounding box (plus a margin of two coarse cells)
    r0, c0 = np.maximum(np.argwhere(labels > 0).min(axis=0) - 2, 0)
    r1, c1 = np.minimum(np.argwhere(labels > 0).max(axis=0) + 3, (rows, cols))
    lab = labels[r0:r1, c0:c1]
    zone = np.where(lab > 0, lab, ndimage.grey_dilation(lab, size=3))
    coarse = lab.repeat(factor, 0).repeat(factor, 1)
    zone = zone.repeat(factor, 0).repeat(factor, 1)
    frows, fcols = zone.shape
    sub = transform @ Affine.translation(c0 * factor, r0 * factor)
    keep = np.ones(len(cloud), bool)
    a = cloud.attributes
    if "return_number" in a:
        keep &= np.asarray(a["return_number"]) <= 1
    if cloud.classification is not None:
        keep &= cloud.classification != ASPRS.NOISE
    xyz = cloud.xyz
    col = np.floor((xyz[:, 0] - sub.c) / fres).astype(np.int64)
    row = np.floor((xyz[:, 1] - sub.f) / -fres).astype(np.int64)
    keep &= (row >= 0) & (row < frows) & (col >= 0) & (col < fcols)
    idx = np.flatnonzero(keep)
    near = ndimage.binary_dilation(zone > 0, iterations=factor)  # the points that can matter
    idx = idx[near[row[idx], col[idx]]]
    raised = coarse > 0
    if len(idx):
        # the highest first return of each fine cell; an empty cell takes its nearest
        # filled cell within one coarse cell (a Voronoi cut of the surface, on the grid)
        idx = idx[np.argsort(xyz[idx, 2], kind="stable")]
        top = np.full(frows * fcols, -1, np.int64)
        top[row[idx] * fcols + col[idx]] = idx
        top = top.reshape(frows, fcols)
        empty = top < 0
        dist, (nr, nc) = ndimage.distance_transform_edt(empty, return_indices=True)
        pid = top[nr, nc]
        found = (dist <= factor) & (pid >= 0)
        p = pid[found]
        h = xyz[p, 2] - dtm.sample(xyz[p, 0], xyz[p, 1], bilinear=False)
        up = np.nan_to_num(h, nan=-np.inf) >= units.height(min(config.grow_height, config.min_height))
        if vegetation is not None:
            up &= ~np.asarray(vegetation, bool)[p]
        raised[found] = up
    mask = raised & (zone > 0)
    # the blob is decided: only speckle goes, by a 3 x 3 majority vote (an opening would
    # shave the ragged Voronoi border and bias every outline inwards)
    votes = ndimage.uniform_filter(mask.astype(np.float32), size=3, mode="nearest") * 9.0
    mask = (votes >= 4.5) & (zone > 0)
    part = np.where(mask, zone, 0)
    # a blob must not lose its core to a neighbour's ring: coarse cells keep their own label
    part = np.where(mask & (coarse > 0), coarse, part)
    fine[r0 * factor : r1 * factor, c0 * factor : c1 * factor] = part
    return fine, transform


def _remove_overlaps(polygons: list[shapely.Polygon], min_area: float) -> list[shapely.Polygon]:
    """Cut later (smaller) polygons where they overlap earlier (larger) ones."""
    polygons = sorted(polygons, key=lambda p: -p.area)
    tree = shapely.STRtree(polygons) if polygons else None
    out: list[shapely.Polygon] = []
    for i, p in enumerate(polygons):
        near = [j for j in tree.query(p, predicate="intersects") if j < i] if tree is not None else []
        if near:
            cut = p.difference(shapely.union_all([polygons[j] for j in near]))
            cut = outline_mod._valid_polygon(cut)
            if cut is None or cut.area < min_area:
                continue
            p = shapely.orient_polygons(cut)
        out.append(p)
    return out


def label_footprints(polygons: list[shapely.Polygon], grid: Raster, *, all_touched: bool = False) -> np.ndarray:
    """(rows, cols) int32 image: 1 + index of the footprint covering each cell, 0 elsewhere."""
    if not polygons:
        return np.zeros(grid.shape, np.int32)
    shapes = ((p, i + 1) for i, p in enumerate(polygons))
    return rasterio.features.rasterize(
        shapes, out_shape=grid.shape, transform=grid.transform, fill=0, dtype="int32", all_touched=all_touched
    )


# --------------------------------------------------------------------------- footprints


def align_footprints(
    polygons: list[shapely.Polygon],
    evidence: Raster,
    max_shift: float,
    *,
    per_footprint: bool = True,
    min_gain: float = 0.05,
) -> tuple[list[shapely.Polygon], np.ndarray, np.ndarray]:
    """Shift given footprints onto the buildings seen in the data.

    The footprints are sampled on a grid of half a cell; for every shift on a grid of
    half a cell within ``max_shift`` (a disc), each footprint scores the sum of
    (2 evidence - 1) under its shifted samples (cross-correlation of the rasterised
    footprints with the building mask, non-building cells counting against). The best
    common shift (refined to sub-step by a parabola) moves every footprint; with
    ``per_footprint``, a footprint whose own best shift within ``max_shift`` raises the
    share of its samples on building cells by more than ``min_gain`` takes it instead
    (maps digitised from orthophotos shift each building by its own lean).

    Parameters
    ----------
    polygons : list of shapely.Polygon
        Footprints in the evidence's CRS; invalid ones are repaired (largest part).
    evidence : Raster
        1 on building cells, 0 elsewhere, NaN without data (:func:`building_evidence`).
    max_shift : float
        Largest shift (CRS units).
    per_footprint : bool
    min_gain : float

    Returns
    -------
    shifted : list of shapely.Polygon
        The footprints moved (an empty polygon stays empty).
    shift : (n, 2) float
        Shift applied to each footprint (x, y), CRS units.
    support : (n,) float
        Share of each shifted footprint's samples with data that fall on building cells;
        NaN when the footprint has no data under it (outside the cloud, or a hole), a low
        value when no building stands there (demolished, or a wrong footprint).
    """
    n = len(polygons)
    shifts = np.zeros((n, 2))
    support = np.full(n, np.nan)
    if n == 0:
        return [], shifts, support
    step = evidence.resolution / 2
    polys = [outline_mod._valid_polygon(p) for p in polygons]
    fid, px, py = _footprint_samples(polys, evidence, step)
    r = int(math.floor(max_shift / step + 1e-9))
    grid = np.arange(-r, r + 1) * step
    sx, sy = np.meshgrid(grid, grid)
    disc = np.hypot(sx, sy) <= max_shift + 1e-9
    cand = np.column_stack([sx[disc], sy[disc]])
    scores = np.zeros((len(cand), n))  # sum of (2 e - 1) per footprint and shift
    hits = np.zeros((len(cand), n))  # building samples
    valid = np.zeros((len(cand), n))  # samples with data
    for k, (dx, dy) in enumerate(cand):
        e = evidence.sample(px + dx, py + dy, bilinear=False) if len(px) else np.zeros(0)
        ok = np.isfinite(e)
        scores[k] = np.bincount(fid[ok], weights=2 * e[ok] - 1, minlength=n)
        hits[k] = np.bincount(fid[ok], weights=e[ok], minlength=n)
        valid[k] = np.bincount(fid[ok], minlength=n)
    total = scores.sum(axis=1)
    best = int(np.argmax(total))
    zero = int(np.flatnonzero((cand[:, 0] == 0) & (cand[:, 1] == 0))[0])
    if total[best] <= total[zero]:
        best = zero
    shift = cand[best] + _parabolic(cand, total, best, step)
    if np.hypot(*shift) > max_shift:
        shift *= max_shift / np.hypot(*shift)
    shifts[:] = shift
    chosen = np.full(n, best)
    if per_footprint:
        with np.errstate(invalid="ignore", divide="ignore"):
            share = hits / valid
        own = np.argmax(scores, axis=0)
        gain = share[own, np.arange(n)] - share[best, np.arange(n)]
        better = np.nan_to_num(gain) > min_gain
        chosen[better] = own[better]
        shifts[better] = cand[own[better]]
    with np.errstate(invalid="ignore", divide="ignore"):
        support = hits[chosen, np.arange(n)] / valid[chosen, np.arange(n)]
    support[valid[chosen, np.arange(n)] == 0] = np.nan
    shifted = []
    for p, (dx, dy) in zip(polys, shifts, strict=True):
        shifted.append(shapely.affinity.translate(p, dx, dy) if p is not None else shapely.Polygon())
    log.info(
        "footprints shifted by (%.2f, %.2f); %d moved on their own; %d without data, %d without building",
        shift[0], shift[1], int((chosen != best).sum()), int(np.isnan(support).sum()),
        int((np.nan_to_num(support, nan=1.0) < 0.5).sum()),
    )
    return shifted, shifts, support


def _footprint_samples(
    polys: list[shapely.Polygon | None], grid: Raster, step: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample points (footprint index, x, y) on a grid of ``step`` inside each footprint."""
    west, south, east, north = grid.bounds
    pad = 2 * step
    cols = int(math.ceil((east - west + 2 * pad) / step))
    rows = int(math.ceil((north - south + 2 * pad) / step))
    transform = Affine(step, 0.0, west - pad, 0.0, -step, north + pad)
    shapes = [(p, i + 1) for i, p in enumerate(polys) if p is not None and not p.is_empty]
    if not shapes:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    fids, xs, ys = [], [], []
    # rasterise one footprint at a time: overlapping footprints each keep all their samples
    for p, v in shapes:
        minx, miny, maxx, maxy = p.bounds
        c0 = max(int((minx - transform.c) / step) - 1, 0)
        r0 = max(int((transform.f - maxy) / step) - 1, 0)
        c1 = min(int((maxx - transform.c) / step) + 2, cols)
        r1 = min(int((transform.f - miny) / step) + 2, rows)
        if c1 <= c0 or r1 <= r0:
            continue
        sub = transform @ Affine.translation(c0, r0)
        m = rasterio.features.rasterize([(p, 1)], out_shape=(r1 - r0, c1 - c0), transform=sub, fill=0, dtype="uint8")
        rr, cc = np.nonzero(m)
        if len(rr):
            x, y = sub.c + (cc + 0.5) * step, sub.f - (rr + 0.5) * step
        else:  # thinner than a sample step: one sample inside it
            x, y = (np.array([v]) for v in p.representative_point().coords[0])
        fids.append(np.full(len(x), v - 1))
        xs.append(x)
        ys.append(y)
    if not fids:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    return np.concatenate(fids).astype(np.int64), np.concatenate(xs), np.concatenate(ys)


def _parabolic(cand: np.ndarray, total: np.ndarray, best: int, step: float) -> np.ndarray:
    """Sub-step offset of a peak from parabolas through its neighbours along x and y."""
    out = np.zeros(2)
    for axis in (0, 1):
        offsets = []
        for sign in (-1, 1):
            target = cand[best].copy()
            target[axis] += sign * step
            k = np.flatnonzero(np.all(np.isclose(cand, target), axis=1))
            offsets.append(total[k[0]] if len(k) else None)
        lo, hi = offsets
        if lo is None or hi is None:
            continue
        denom = lo - 2 * total[best] + hi
        if denom < 0:
            out[axis] = float(np.clip(0.5 * (lo - hi) / denom * step, -step / 2, step / 2))
    return out


def assign_blocks(
    buildings: list[Building],
    labels: np.ndarray,
    raised: np.ndarray,
    *,
    min_shared: float,
    max_gap: float | None = None,
    prefix: str = "block",
) -> int:
    """Mark the parts of split blocks: set :attr:`Building.parent` to a block id.

    Detection splits one connected region of raised cells at height jumps and cuts the
    parts' outlines apart where they overlap, so the parts of one block touch along the
    cut. Two buildings belong to one block when both lie mostly on the same connected
    region of ``raised`` (4-connected, as the split) and their footprints touch: at
    least ``min_shared`` of one's boundary within ``max_gap`` of the other (two houses
    joined only through a rejected tree crown are not a block); blocks are the
    connected groups of such pairs. Only groups of two or more buildings get a parent:
    a block that was not split stays one stand-alone building. Block ids are
    ``block0001``... in the order of each block's first building (skipping ids already
    used by a building).

    Parameters
    ----------
    buildings : list of Building
        ``buildings[i]`` is footprint ``i + 1`` of ``labels``; ``parent`` is overwritten.
    labels : (rows, cols) int
        1 + building index per cell (:func:`recon3d.buildings.detect.label_footprints`).
    raised : (rows, cols) bool
        Raised building cells on the same grid
        (:func:`recon3d.buildings.detect.building_mask`).
    min_shared : float
        Shortest shared boundary (CRS units) that makes two footprints neighbours.
    max_gap : float, optional
        Widest gap (CRS units) between touching footprints; ``min_shared / 2`` by default.

    Returns
    -------
    int
        Number of blocks with two or more parts.
    """
    n = len(buildings)
    for b in buildings:
        b.parent = None
    if n < 2:
        return 0
    regions, _ = ndimage.label(np.asarray(raised, bool))
    labels = np.asarray(labels)
    inside = (labels > 0) & (labels <= n) & (regions > 0)
    region_of = np.zeros(n, np.int64)  # the region under most of each footprint's cells
    if inside.any():
        m = int(regions.max()) + 1
        key = labels[inside].astype(np.int64) * m + regions[inside]
        pairs, counts = np.unique(key, return_counts=True)
        lab, reg = pairs // m, pairs % m
        order = np.lexsort((-counts, lab))
        lab, reg = lab[order], reg[order]
        first = np.r_[True, lab[1:] != lab[:-1]]
        region_of[lab[first] - 1] = reg[first]
    polys = [b.footprint for b in buildings]
    tree = shapely.STRtree(polys)
    tol = min_shared / 2 if max_gap is None else max_gap
    tol = max(tol, 1e-9)
    rows, cols = [], []
    for i, p in enumerate(polys):
        if region_of[i] == 0 or p is None or p.is_empty:
            continue
        for j in tree.query(p, predicate="dwithin", distance=tol):
            if j <= i or region_of[j] != region_of[i]:
                continue
            shared = p.boundary.intersection(polys[j].buffer(tol)).length
            if shared >= min_shared:
                rows.append(i)
                cols.append(int(j))
    if not rows:
        return 0
    graph = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, comp = csgraph.connected_components(graph, directed=False)
    sizes = np.bincount(comp)
    used = {b.id for b in buildings}
    names: dict[int, str] = {}
    k = 0
    for b, c in zip(buildings, comp, strict=True):
        if sizes[c] < 2:
            continue
        if c not in names:
            k += 1
            while f"{prefix}{k:04d}" in used:
                k += 1
            names[c] = f"{prefix}{k:04d}"
        b.parent = names[c]
    log.info("%d blocks split into %d parts", len(names), int(sum(sizes[sizes >= 2])))
    return len(names)
