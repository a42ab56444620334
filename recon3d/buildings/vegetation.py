"""Trees told apart from buildings, point by point.

Each point above the terrain gets covariance features of its neighbourhood
(roughness, planarity, scattering...); a rough point that is also a multi-return echo
(or among enough of them) or green (NDVI with a near-infrared channel, excess green with RGB only) is vegetation,
after a majority vote among its neighbours. Without returns or colour, roughness alone
decides, above a threshold no lower than three times the terrain's noise.
:func:`vegetation_cells` turns the points into the share of vegetation per DSM cell,
which :mod:`recon3d.buildings.detect` uses to keep crowns out of the building mask.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.terrain.dsm import grid_points

log = logging.getLogger(__name__)

__all__ = ["classify_vegetation", "multi_return_share", "planar_cells", "plane_tolerance", "point_features", "vegetation_cells", "vegetation_index"]


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


def multi_return_share(multi: np.ndarray, rough: np.ndarray) -> float:
    """Share of multi-return echoes among a point's neighbours that makes it vegetation evidence.

    A pulse splits on only part of the leaves it meets: under a dense canopy a
    quarter of a crown's echoes or fewer are multi-return, too few for a majority
    vote on each point's own echo. Where the survey's rough points (crowns, mostly)
    are less than half multi-return echoes, the neighbourhood's share is evidence
    when it is closer to theirs than to the planar points' (roofs, whose edges split
    pulses too): half way between the two, 0.1 at least. Where they are more, each
    point's own echo is evidence enough, and a neighbourhood rule would only take
    roof edges (inf is returned).

    Parameters
    ----------
    multi, rough : (n,) bool
        Per candidate point: an echo of a multi-return pulse; a rough neighbourhood.
    """
    crowns = float(np.mean(multi[rough])) if rough.any() else 1.0
    if crowns >= 0.5:
        return np.inf
    planes = float(np.mean(multi[~rough])) if (~rough).any() else 0.0
    return max(0.1, (crowns + planes) / 2)


#: Share of multi-return echoes among the rough points below which a survey's returns
#: say little (a dense canopy, a low penetration): the crown's shape is evidence too.
FEW_RETURNS = 0.05


def classify_vegetation(
    cloud: PointCloud,
    dtm: Raster,
    config: BuildingsConfig,
    units: Units,
    *,
    noise: float = 0.0,
    with_roughness: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """(n,) bool: points of trees and bushes (ASPRS class 5 in cloud.laz).

    A point at least ``vegetation_min_height`` above the terrain is vegetation when its
    neighbourhood is rough (RMS about the best plane above ``vegetation_roughness``;
    roofs and walls are planar) and it carries vegetation evidence: an echo of a
    multi-return pulse (leaves let part of the pulse through, roofs do not), or a
    neighbourhood with a share of such echoes nearer the survey's crowns' than its
    roofs' (:func:`multi_return_share`; under a dense canopy most leaves return one
    echo though their pulses split on the next), or a green
    colour (NDVI > 0.3, or excess green > 0.05 with RGB only). A cloud without colours
    whose rough points are almost never multi-return echoes (fewer than
    :data:`FEW_RETURNS`: no returns recorded, a dense canopy, a low penetration) also
    takes the shape of a crown as evidence: scattering l3 / l1 > 0.05 with a roughness
    above 3 x the cloud's measured height ``noise`` (a noisy roof is as rough as its
    noise). A coloured cloud without returns (stereo) is judged on colour
    alone: dense matching smooths tree crowns until they are as planar as roofs. The
    decision is then smoothed by a majority vote among the ``vegetation_neighbours``
    neighbours.

    Parameters
    ----------
    cloud : PointCloud
    dtm : Raster
    config : BuildingsConfig
    units : Units
    noise : float
        Height noise of the cloud (CRS height units), e.g. the ground filter's estimate.
    with_roughness : bool
        Also return each point's roughness.

    Returns
    -------
    vegetation : (n,) bool
    roughness : (n,) float, only with ``with_roughness``
        RMS of the point's neighbours about their best plane (CRS units), NaN for
        points not tested (too low, noise).
    """
    n = len(cloud)
    out = np.zeros(n, bool)
    roughness = np.full(n, np.nan)
    result = (out, roughness) if with_roughness else out
    if n == 0:
        return result
    xyz = cloud.xyz
    height = xyz[:, 2] - dtm.sample(xyz[:, 0], xyz[:, 1], bilinear=False)
    cand = np.nan_to_num(height, nan=-np.inf) >= units.height(config.vegetation_min_height)
    c = cloud.classification
    if c is not None:
        cand &= c != ASPRS.NOISE
    idx = np.flatnonzero(cand)
    if len(idx) < 3:
        return result
    feats = point_features(xyz[idx], k=config.vegetation_neighbours)
    roughness[idx] = feats["roughness"]
    evidence = np.zeros(len(idx), bool)
    a = cloud.attributes
    have_returns = "number_of_returns" in a and np.any(np.asarray(a["number_of_returns"]) > 1)
    rough = units.height(config.vegetation_roughness)
    is_rough = feats["roughness"] > max(rough, 3.0 * noise)
    few_returns = True
    if have_returns:
        multi = np.asarray(a["number_of_returns"])[idx] > 1
        evidence |= multi | (multi[feats["neighbours"]].mean(axis=1) >= multi_return_share(multi, is_rough))
        few_returns = not np.mean(multi[is_rough]) >= FEW_RETURNS if is_rough.any() else True
    colour = vegetation_index(cloud)
    if colour is not None:
        evidence |= colour[0][idx] > GREEN_THRESHOLDS[colour[1]]
    if colour is None and few_returns:  # shape alone: a noisy roof is as rough as its noise
        evidence |= (feats["scattering"] > 0.05) & is_rough
    if colour is not None and not have_returns:
        # photogrammetric surfaces: the matcher smooths tree crowns (roughness 0.04 m,
        # like roofs' 0.035 m on the rendered city) while their colour stays green
        veg = colour[0][idx] > COLOUR_ONLY_THRESHOLDS[colour[1]]
    else:
        if few_returns and colour is None:
            rough = max(rough, 3.0 * noise)
        veg = (feats["roughness"] > rough) & evidence
    veg = veg[feats["neighbours"]].mean(axis=1) > 0.5
    out[idx] = veg
    log.info("vegetation: %d of %d points above %.1f m", int(veg.sum()), len(idx), config.vegetation_min_height)
    return result


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


def plane_tolerance(config: BuildingsConfig, units: Units, noise: float = 0.0) -> float:
    """RMS about the local plane (CRS units) up to which a point lies on a plane.

    Twice ``vegetation_roughness`` or 1.5 x the cloud's height ``noise``, whichever is
    larger: a roof scanned with noise s has an RMS of about 0.85 s about its best local
    plane, a crown's leaves scatter 0.1 to 0.3 m (more would let crowns of a noisy
    survey pass as planes).
    """
    return max(2.0 * units.height(config.vegetation_roughness), 1.5 * noise)


def planar_cells(cloud: PointCloud, grid: Raster, roughness: np.ndarray, tolerance: float) -> np.ndarray:
    """(rows, cols) float: share of each cell's upper points that lie on a local plane.

    Parameters
    ----------
    cloud : PointCloud
    grid : Raster
    roughness : (n,) float
        Per-point roughness (:func:`classify_vegetation` with ``with_roughness``); NaN
        (points near the ground, not tested) counts as planar.
    tolerance : float
        :func:`plane_tolerance`.

    Returns
    -------
    (rows, cols) float32
        In [0, 1] (1 in empty cells), voted like :func:`vegetation_cells`.
    """
    rough = np.nan_to_num(np.asarray(roughness, np.float64), nan=0.0) > tolerance
    share = vegetation_cells(cloud, grid, rough, share=True)
    return 1.0 - share
