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
from dataclasses import astuple, dataclass

import numpy as np
from scipy.spatial import cKDTree

from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.terrain.dsm import grid_points

log = logging.getLogger(__name__)

__all__ = [
    "Candidates",
    "ReturnCounts",
    "Survey",
    "classify_vegetation",
    "colour_kind",
    "decide_vegetation",
    "multi_return_share",
    "nearest_neighbours",
    "neighbour_radius",
    "planar_cells",
    "plane_tolerance",
    "point_features",
    "return_counts",
    "symmetric_eigenvalues",
    "vegetation_candidates",
    "vegetation_cells",
    "vegetation_index",
]


#: Neighbours asked of the k-d tree beyond the k used, so that a tie at the k-th
#: distance is broken by the points' survey order, not by the tree's traversal.
TIE_SLACK = 4


def point_features(
    xyz: np.ndarray, *, k: int = 10, radius: float = np.inf, order: np.ndarray | None = None, workers: int = -1
) -> dict[str, np.ndarray]:
    """Covariance features of each point's k nearest neighbours (the point included).

    The neighbours are those within ``radius``, nearest first, ties broken by ``order``;
    each neighbourhood is centred on its own point, so a point's features depend on its
    neighbours alone, not on the other points given (a tile gives the values the whole
    survey gives).

    Parameters
    ----------
    xyz : (n, 3) float
    k : int
        Neighbourhood size (clipped to n).
    radius : float
        Farthest neighbour (CRS units). A point with fewer than 3 neighbours within it
        is isolated: roughness inf, scattering 1.
    order : (n,) int, optional
        The points' order in the survey (default: as given), which breaks distance ties.
    workers : int
        Threads for the k-d tree query (-1: all cores).

    Returns
    -------
    dict of str to (n,) float
        ``roughness`` (square root of the smallest eigenvalue: RMS distance to the best
        plane, CRS units), ``planarity`` (l2 - l3) / l1, ``linearity`` (l1 - l2) / l1
        and ``scattering`` l3 / l1; ``neighbours`` (n, k) int, indices of each point's
        neighbours (-1 beyond the radius) and ``count`` (n,) int, how many there are.
    """
    xyz = np.asarray(xyz, np.float64)
    n = len(xyz)
    names = ("roughness", "planarity", "linearity", "scattering")
    out = {key: np.zeros(n) for key in names}
    if n == 0:
        out["neighbours"] = np.zeros((0, 0), np.int64)
        out["count"] = np.zeros(0, np.int64)
        return out
    k = max(1, min(k, n))
    nb = nearest_neighbours(xyz, k, radius=radius, order=order, workers=workers)
    valid = nb >= 0
    count = valid.sum(axis=1)
    for s in range(0, n, CHUNK):  # bounded memory: (chunk, k, 3) at a time
        sl = slice(s, min(s + CHUNK, n))
        missing = ~valid[sl]
        p = xyz[np.where(valid[sl], nb[sl], 0)]  # (chunk, k, 3), in place from here on
        p -= xyz[sl, None, :]
        p[missing] = 0.0
        m = count[sl, None, None]
        p -= p.sum(axis=1, keepdims=True) / m
        p[missing] = 0.0
        l3, l2, l1 = (np.clip(w, 0.0, None) for w in symmetric_eigenvalues(np.matmul(p.transpose(0, 2, 1), p) / m))
        safe = np.where(l1 > 0, l1, 1.0)
        out["roughness"][sl] = np.sqrt(l3)
        out["planarity"][sl] = np.where(l1 > 0, (l2 - l3) / safe, 0.0)
        out["linearity"][sl] = np.where(l1 > 0, (l1 - l2) / safe, 0.0)
        out["scattering"][sl] = np.where(l1 > 0, l3 / safe, 0.0)
    isolated = count < min(3, k)
    out["roughness"][isolated] = np.inf
    out["scattering"][isolated] = 1.0
    out["planarity"][isolated] = out["linearity"][isolated] = 0.0
    out["neighbours"] = nb
    out["count"] = count
    return out


def symmetric_eigenvalues(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues of symmetric 3 x 3 matrices in closed form (Smith, 1961), ascending.

    Three to four times faster than ``np.linalg.eigvalsh``, whose LAPACK call per
    matrix dominates for 3 x 3. They agree to 1e-10 of the largest eigenvalue, and to
    1e-8 where two eigenvalues coincide (the arc cosine is flat there): the two zeros of
    a 10 m wire come out within 1e-7 m2, a roughness under 0.3 mm. On the shared LiDAR
    tiles every product is the same, byte for byte.

    Parameters
    ----------
    c : (m, 3, 3) float

    Returns
    -------
    smallest, middle, largest : (m,) float
    """
    a00, a11, a22 = c[:, 0, 0], c[:, 1, 1], c[:, 2, 2]
    a01, a02, a12 = c[:, 0, 1], c[:, 0, 2], c[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0  # the eigenvalues are q + 2 p cos(phi + 2 pi j / 3)
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):  # p = 0: three equal eigenvalues, q
        phi = np.arccos(np.clip(np.where(p > 0, det / (2.0 * p**3), 1.0), -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return smallest, 3.0 * q - largest - smallest, largest


def nearest_neighbours(
    xyz: np.ndarray, k: int, *, radius: float = np.inf, order: np.ndarray | None = None, workers: int = -1
) -> np.ndarray:
    """(n, k) int64 indices of each point's k nearest points within ``radius`` (itself
    included), nearest first, ties broken by ``order``; -1 where there are fewer.

    The k-d tree is asked for k + 1 neighbours; the rare points whose k-th and next
    neighbours are as far are asked again for :data:`TIE_SLACK` more, so that which of
    them is in does not depend on the tree's traversal.
    """
    n = len(xyz)
    # an unbalanced tree (split at the midpoint, not the median) builds and answers
    # about a fifth faster on survey points; the answers do not depend on the tree
    tree = cKDTree(xyz, balanced_tree=False)
    q = min(k + 1, n)
    dist, nb = tree.query(xyz, k=q, distance_upper_bound=radius, workers=workers)
    dist, nb = dist.reshape(n, q), nb.reshape(n, q)
    if q > k:
        edge = np.flatnonzero(np.isfinite(dist[:, k]) & (dist[:, k] == dist[:, k - 1]))
        dist, nb = dist[:, :k].copy(), nb[:, :k].copy()
        if len(edge):
            more = min(k + TIE_SLACK, n)
            d2, n2 = tree.query(xyz[edge], k=more, distance_upper_bound=radius, workers=workers)
            d2, n2 = _canonical(d2.reshape(len(edge), more), n2.reshape(len(edge), more), n, order)
            dist[edge], nb[edge] = d2[:, :k], n2[:, :k]
    tied = np.flatnonzero((np.isfinite(dist[:, 1:]) & (dist[:, 1:] == dist[:, :-1])).any(axis=1))
    if len(tied):
        dist[tied], nb[tied] = _canonical(dist[tied], nb[tied], n, order)
    nb[~np.isfinite(dist)] = -1
    return nb


def _canonical(dist: np.ndarray, nb: np.ndarray, n: int, order: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Neighbours sorted by distance, then by survey order (missing ones, index n, last)."""
    missing = nb >= n
    rank = (np.arange(n) if order is None else np.asarray(order))[np.where(missing, 0, nb)]
    rank[missing] = np.iinfo(np.int64).max
    pick = np.lexsort((rank, dist), axis=-1)
    return np.take_along_axis(dist, pick, axis=1), np.take_along_axis(nb, pick, axis=1)


#: Points per block of the covariance features (memory: block x k x 3 doubles).
CHUNK = 200_000


def neighbour_radius(spacing: float, units: Units) -> float:
    """Farthest neighbour (CRS units) of a point's vegetation features: 8 m, or 20 point
    spacings in a sparse survey. Ten neighbours lie within 2 spacings on a surface and
    within about 1 m in a crown; a point without them within 8 m is isolated (a bird, a
    wire), no roof. The bound is what lets a tile, read with twice that buffer, decide
    its points exactly as the whole survey would; on the Delft strip it changes none of
    the decisions an unbounded search makes (3 m changed 64 of 208,000)."""
    return max(units.length(8.0), 20.0 * spacing)


def colour_kind(cloud: PointCloud) -> str | None:
    """Which colour index a cloud supports: "ndvi" (a near-infrared channel holding
    data), "exg" (RGB only) or None (no colours, or all black)."""
    a = cloud.attributes
    if not {"red", "green", "blue"} <= set(a):
        return None
    if "nir" in a and np.any(np.asarray(a["nir"]) > 0):
        return "ndvi"
    r, g, b = (np.asarray(a[key], np.float64) for key in ("red", "green", "blue"))
    return "exg" if np.any(r + g + b > 0) else None


def vegetation_index(cloud: PointCloud, kind: str | None = "auto") -> tuple[np.ndarray, str] | None:
    """(n,) colour vegetation index and its name, None for a cloud without colours.

    NDVI (nir - red) / (nir + red) when a near-infrared channel holds data, else the
    normalised excess green (2 g - r - b) / (r + g + b) of the RGB channels (IGN LiDAR
    HD files carry a ``nir`` dimension that may be all zeros). ``kind`` ("ndvi",
    "exg" or None) is the survey's (:func:`colour_kind`), when the cloud is a tile of
    it; "auto" asks the cloud itself.
    """
    if kind == "auto":
        kind = colour_kind(cloud)
    if kind is None:
        return None
    a = cloud.attributes
    r, g, b = (np.asarray(a[key], np.float64) for key in ("red", "green", "blue"))
    with np.errstate(invalid="ignore", divide="ignore"):
        if kind == "ndvi":
            nir = np.asarray(a["nir"], np.float64)
            return np.nan_to_num((nir - r) / (nir + r)), "ndvi"
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
    return ReturnCounts.of(multi, rough).share()


@dataclass(frozen=True)
class ReturnCounts:
    """How many of a survey's vegetation candidates are rough, and multi-return echoes
    among the rough and the smooth ones: summed over tiles, they give the survey's
    rules (:meth:`share`, :meth:`few`) exactly."""

    rough: int = 0
    rough_multi: int = 0
    smooth: int = 0
    smooth_multi: int = 0

    @classmethod
    def of(cls, multi: np.ndarray, rough: np.ndarray) -> ReturnCounts:
        multi, rough = np.asarray(multi, bool), np.asarray(rough, bool)
        return cls(int(rough.sum()), int((multi & rough).sum()), int((~rough).sum()), int((multi & ~rough).sum()))

    def __add__(self, other: ReturnCounts) -> ReturnCounts:
        return ReturnCounts(*(a + b for a, b in zip(astuple(self), astuple(other), strict=True)))

    def share(self) -> float:
        """:func:`multi_return_share` of the counted points."""
        crowns = self.rough_multi / self.rough if self.rough else 1.0
        if crowns >= 0.5:
            return np.inf
        planes = self.smooth_multi / self.smooth if self.smooth else 0.0
        return max(0.1, (crowns + planes) / 2)

    def few(self) -> bool:
        """Fewer than :data:`FEW_RETURNS` of the rough points are multi-return echoes (or none is rough)."""
        return not (self.rough and self.rough_multi / self.rough >= FEW_RETURNS)


#: Share of multi-return echoes among the rough points below which a survey's returns
#: say little (a dense canopy, a low penetration): the crown's shape is evidence too.
FEW_RETURNS = 0.05


@dataclass
class Candidates:
    """The points tested for vegetation and their neighbourhoods (:func:`vegetation_candidates`).

    Attributes
    ----------
    index : (m,) int
        Which points of the cloud (those high enough above the terrain, not noise).
    roughness, scattering : (m,) float
    neighbours : (m, k) int
        Neighbours among the candidates (-1 beyond the radius).
    multi : (m,) bool or None
        Echo of a multi-return pulse; None when the survey records no multiple returns.
    colour : (m,) float or None
        Colour vegetation index; None without colours.
    """

    index: np.ndarray
    roughness: np.ndarray
    scattering: np.ndarray
    neighbours: np.ndarray
    multi: np.ndarray | None
    colour: np.ndarray | None

    def rough(self, config: BuildingsConfig, units: Units, noise: float) -> np.ndarray:
        """(m,) bool: rougher than ``vegetation_roughness`` and 3 x the noise."""
        return self.roughness > max(units.height(config.vegetation_roughness), 3.0 * noise)


@dataclass(frozen=True)
class Survey:
    """What the vegetation rules take from the whole survey rather than from a tile.

    Attributes
    ----------
    returns : bool
        Some points are echoes of multi-return pulses.
    colour : str or None
        The colour index the survey supports (:func:`colour_kind`).
    counts : ReturnCounts
        Over every candidate of the survey (:func:`return_counts`).
    """

    returns: bool
    colour: str | None
    counts: ReturnCounts = ReturnCounts()


def vegetation_candidates(
    cloud: PointCloud, dtm: Raster, config: BuildingsConfig, units: Units, survey: Survey, *,
    radius: float = np.inf, order: np.ndarray | None = None,
) -> Candidates:
    """The points at least ``vegetation_min_height`` above the terrain (not noise), with
    their covariance features among each other (:func:`point_features`)."""
    xyz = cloud.xyz
    height = xyz[:, 2] - dtm.sample(xyz[:, 0], xyz[:, 1], bilinear=False)
    cand = np.nan_to_num(height, nan=-np.inf) >= units.height(config.vegetation_min_height)
    c = cloud.classification
    if c is not None:
        cand &= c != ASPRS.NOISE
    idx = np.flatnonzero(cand)
    if len(idx) < 3:
        idx = idx[:0]
    feats = point_features(xyz[idx], k=config.vegetation_neighbours, radius=radius,
                           order=None if order is None else np.asarray(order)[idx])
    a = cloud.attributes
    multi = np.asarray(a["number_of_returns"])[idx] > 1 if survey.returns and "number_of_returns" in a else None
    colour = vegetation_index(cloud, survey.colour)
    return Candidates(idx, feats["roughness"], feats["scattering"], feats["neighbours"], multi,
                      None if colour is None else colour[0][idx])


def return_counts(cand: Candidates, config: BuildingsConfig, units: Units, noise: float,
                  which: np.ndarray | None = None) -> ReturnCounts:
    """:class:`ReturnCounts` of the candidates (``which`` of them: a tile's own points)."""
    if cand.multi is None:
        return ReturnCounts()
    multi, rough = cand.multi, cand.rough(config, units, noise)
    if which is not None:
        multi, rough = multi[which], rough[which]
    return ReturnCounts.of(multi, rough)


def decide_vegetation(
    cand: Candidates, config: BuildingsConfig, units: Units, survey: Survey, *, noise: float = 0.0
) -> np.ndarray:
    """(m,) bool: which candidates are vegetation, after the majority vote among their
    neighbours (the rules of :func:`classify_vegetation`)."""
    if not len(cand.index):
        return np.zeros(0, bool)
    rough = units.height(config.vegetation_roughness)
    is_rough = cand.rough(config, units, noise)
    nb, valid = cand.neighbours, cand.neighbours >= 0
    count = np.maximum(valid.sum(axis=1), 1)

    def neighbour_mean(values: np.ndarray) -> np.ndarray:
        return np.where(valid, values[np.where(valid, nb, 0)], False).sum(axis=1) / count

    evidence = np.zeros(len(cand.index), bool)
    few_returns = True
    if cand.multi is not None:
        evidence |= cand.multi | (neighbour_mean(cand.multi) >= survey.counts.share())
        few_returns = survey.counts.few()
    if cand.colour is not None:
        evidence |= cand.colour > GREEN_THRESHOLDS[survey.colour]
    if cand.colour is None and few_returns:  # shape alone: a noisy roof is as rough as its noise
        evidence |= (cand.scattering > 0.05) & is_rough
    if cand.colour is not None and cand.multi is None:
        # photogrammetric surfaces: the matcher smooths tree crowns (roughness 0.04 m,
        # like roofs' 0.035 m on the rendered city) while their colour stays green
        veg = cand.colour > COLOUR_ONLY_THRESHOLDS[survey.colour]
    else:
        if few_returns and cand.colour is None:
            rough = max(rough, 3.0 * noise)
        veg = (cand.roughness > rough) & evidence
    return neighbour_mean(veg) > 0.5


def classify_vegetation(
    cloud: PointCloud,
    dtm: Raster,
    config: BuildingsConfig,
    units: Units,
    *,
    noise: float = 0.0,
    with_roughness: bool = False,
    radius: float | None = None,
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
    neighbours (within :func:`neighbour_radius`).

    The whole cloud at once; the pipeline runs the same steps tile by tile
    (:func:`vegetation_candidates`, :func:`return_counts`, :func:`decide_vegetation`).

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
    radius : float, optional
        Farthest neighbour; :func:`neighbour_radius` of the cloud's point spacing by default.

    Returns
    -------
    vegetation : (n,) bool
    roughness : (n,) float, only with ``with_roughness``
        RMS of the point's neighbours about their best plane (CRS units), NaN for
        points not tested (too low, noise), inf for isolated points.
    """
    from recon3d.terrain.dsm import point_spacing

    n = len(cloud)
    out = np.zeros(n, bool)
    roughness = np.full(n, np.nan)
    result = (out, roughness) if with_roughness else out
    if n == 0:
        return result
    a = cloud.attributes
    returns = "number_of_returns" in a and bool(np.any(np.asarray(a["number_of_returns"]) > 1))
    survey = Survey(returns, colour_kind(cloud))
    if radius is None:
        radius = neighbour_radius(point_spacing(cloud.xyz[:, :2]), units)
    cand = vegetation_candidates(cloud, dtm, config, units, survey, radius=radius)
    if not len(cand.index):
        return result
    roughness[cand.index] = cand.roughness
    survey = Survey(returns, survey.colour, return_counts(cand, config, units, noise))
    veg = decide_vegetation(cand, config, units, survey, noise=noise)
    out[cand.index] = veg
    log.info("vegetation: %d of %d points above %.1f m", int(veg.sum()), len(cand.index), config.vegetation_min_height)
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
        values = np.nan_to_num(grid_points(np.column_stack([xyz[:, :2], multi]), grid.transform, grid.shape,
                                           reducer="mean", origin=grid.origin))
        return values.astype(np.float32) if share else values > 0.5
    depth = 1.5 * grid.resolution if depth is None else depth
    top = grid_points(xyz, grid.transform, grid.shape, reducer="max", origin=grid.origin)
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
