"""Roof planes of one building from its points, and the roof type they make.

The planes come from Open3D's RANSAC (``PointCloud.segment_plane``), run again and
again on the points not explained yet, as Open3D returns one plane per call
(Open3D PR #1287); each hypothesis is drawn from at most 1000 of those points (a
regular stride), its inliers are then taken among all of them. Each RANSAC plane is
checked against the local surface normals (a plane cutting across a ridge collects
inliers whose normals disagree with it), split into spatially connected parts
(parts with too few points are dropped) and refitted by least squares without the
points beyond 2.5 robust sigmas. The parts are then merged (same plane in 3-D),
regularised and grown over their neighbours:

- near-horizontal planes (slope below ``flat_slope``) are snapped flat;
- aspects (downhill directions) within ``azimuth_snap`` of a footprint edge normal
  take that direction, so eaves run parallel to the walls;
- two planes facing opposite ways with nearly equal slopes (the two sides of a
  gable, the pairs of a hip roof) get exactly opposite aspects and one common slope,
  which makes their ridge horizontal.

Determinism: points are sorted before anything else (the result does not depend on
their order, hence not on tiling) and Open3D's global generator is re-seeded
(``o3d.utility.random.seed``) before every RANSAC call. Seeding alone is not enough:
0.16-0.18 ignored the seed (Open3D issues #5647, #7270; fixed by PR #6580), and with
0.20 a seeded ``segment_plane`` running on several TBB threads still returns a
different plane now and then (measured here: 1 call in 4 on 2 threads). Open3D is
therefore limited to one thread (``o3d.utility.set_max_threads(1)``) during the
search and the previous limit restored afterwards; one building at a time is
small, and buildings run in parallel at a higher level. Planes are refitted by
least squares in numpy, never taken from Open3D's returned model.

Clouds denser than ``max_density`` (12 points/m2) are thinned on a fixed grid for the
search, every point being labelled at the end; a roof needing more than
``max_planes`` planes is reported (``too_many_planes``) rather than segmented further.

Coordinates are the caller's (the city model's local frame in the pipeline); all
lengths of :class:`RoofParams` are in the same units.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

__all__ = [
    "ROOF_TYPES",
    "RoofParams",
    "RoofPlane",
    "RoofSegmentation",
    "plane_height",
    "roof_type",
    "segment_roof",
]

#: Roof types :func:`roof_type` returns ("unknown" when there is no plane at all).
ROOF_TYPES = ("flat", "shed", "gable", "hip", "pyramid", "mansard", "complex")


@dataclass(frozen=True)
class RoofParams:
    """Roof segmentation settings, lengths in the units of the points.

    Attributes
    ----------
    distance : float
        RANSAC inlier distance to a plane.
    min_plane_area : float
        Smallest plane kept (plan-view area); with the measured point density it
        gives the minimal point count of a plane.
    min_points : int
        Fewest points of a plane, whatever the density.
    max_planes : int
        The search stops after ``max_planes + 1`` planes; a segmentation with more
        planes than ``max_planes`` reports ``too_many_planes``.
    max_slope : float
        Steeper planes (degrees) are walls, not roofs.
    normal_angle : float
        Largest angle (degrees) between a plane and the local normal of an inlier
        lying on a locally planar surface.
    flat_slope : float
        Planes flatter than this (degrees) are made horizontal.
    merge_angle : float
        Planes whose normals differ by less (degrees) and whose points fit each
        other's plane are merged.
    symmetry_slope : float
        Opposite planes whose slopes differ by less (degrees) get one common slope.
    azimuth_snap : float
        Aspects within this angle (degrees) of a footprint edge normal are snapped to it;
        also the tolerance for two aspects to count as opposite.
    ransac_iterations : int
        RANSAC iterations per plane.
    neighbours : int
        Neighbours used for local normals.
    max_density : float
        Denser clouds are thinned to about this many points per unit area for the
        plane search (every point is labelled afterwards); 0 keeps all points.
    seed : int
        Seed of Open3D's random generator.
    """

    distance: float = 0.15
    min_plane_area: float = 2.0
    min_points: int = 12
    max_planes: int = 24
    max_slope: float = 75.0
    normal_angle: float = 30.0
    flat_slope: float = 5.0
    merge_angle: float = 6.0
    symmetry_slope: float = 5.0
    azimuth_snap: float = 8.0
    ransac_iterations: int = 300
    neighbours: int = 10
    max_density: float = 12.0
    seed: int = 0

    @classmethod
    def from_config(cls, cfg, units=None) -> RoofParams:
        """Settings from a :class:`~recon3d.config.LodConfig` (metres) in CRS units.

        Parameters
        ----------
        cfg : LodConfig
        units : Units, optional
            Units of the CRS; metres when omitted.
        """
        from recon3d.core.geo import Units

        u = units or Units()
        d = cls()
        return cls(
            distance=u.height(getattr(cfg, "plane_distance", d.distance)),
            min_plane_area=u.area(getattr(cfg, "min_plane_area", d.min_plane_area)),
            min_points=int(getattr(cfg, "min_plane_points", d.min_points)),
            max_planes=int(getattr(cfg, "max_planes", d.max_planes)),
            max_density=1.0 / u.area(1.0 / d.max_density),
            seed=int(getattr(cfg, "seed", d.seed)),
        )


@dataclass
class RoofPlane:
    """One roof plane.

    Attributes
    ----------
    plane : (4,) float
        ``(a, b, c, d)`` with ``a x + b y + c z + d = 0``, unit normal, ``c > 0``.
    inliers : (k,) int
        Indices of the plane's points in the array given to :func:`segment_roof`.
    rms : float
        RMS of the inliers' distances to the plane.
    area : float
        Plan-view area the inliers cover (count over point density).
    centroid : (3,) float
        Mean of the inliers.
    """

    plane: np.ndarray
    inliers: np.ndarray
    rms: float
    area: float
    centroid: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        return self.plane[:3]

    @property
    def slope(self) -> float:
        """Slope in degrees (0 for a flat roof)."""
        return math.degrees(math.acos(min(1.0, abs(float(self.plane[2])))))

    @property
    def azimuth(self) -> float:
        """Aspect (downhill direction) in degrees counter-clockwise from +x; 0 when flat."""
        a, b = float(self.plane[0]), float(self.plane[1])
        return math.degrees(math.atan2(b, a)) % 360.0 if a or b else 0.0

    def height(self, x, y) -> np.ndarray:
        """Height of the plane above (x, y)."""
        return plane_height(self.plane, x, y)


@dataclass
class RoofSegmentation:
    """The planes of one roof.

    Attributes
    ----------
    planes : list of RoofPlane
        Largest first.
    labels : (n,) int
        Plane of every input point, -1 for points on no plane.
    spacing : float
        Mean point spacing (inverse square root of the plan-view density).
    min_points : int
        Fewest points a plane needed at this density.
    too_many_planes : bool
        The search found more than ``max_planes`` planes.
    """

    planes: list[RoofPlane]
    labels: np.ndarray
    spacing: float
    min_points: int
    too_many_planes: bool = False

    @property
    def rms(self) -> float:
        """RMS distance of all plane points to their plane (NaN without planes)."""
        if not self.planes:
            return float("nan")
        n = sum(len(p.inliers) for p in self.planes)
        return math.sqrt(sum(p.rms**2 * len(p.inliers) for p in self.planes) / n)

    @property
    def coverage(self) -> float:
        """Share of the points lying on a plane."""
        return float((self.labels >= 0).mean()) if len(self.labels) else 0.0


def plane_height(plane: np.ndarray, x, y) -> np.ndarray:
    """z of the plane ``(a, b, c, d)`` above (x, y)."""
    a, b, c, d = plane
    return -(a * np.asarray(x) + b * np.asarray(y) + d) / c


def segment_roof(
    points: np.ndarray, params: RoofParams | None = None, *, footprint=None
) -> RoofSegmentation:
    """Roof planes of one building.

    Parameters
    ----------
    points : (n, 3) float
        The building's roof points (local frame): points inside the footprint, above
        the terrain.
    params : RoofParams, optional
    footprint : shapely.Polygon, optional
        Outline in the same coordinates; its edge directions are used to regularise
        the aspects of sloped planes.

    Returns
    -------
    RoofSegmentation
        Deterministic: the same points in any order give the same planes.
    """
    p = params or RoofParams()
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    order = np.lexsort((pts[:, 2], pts[:, 1], pts[:, 0]))
    xyz = pts[order]
    spacing = _spacing(xyz)
    min_pts = max(int(p.min_points), int(round(p.min_plane_area / spacing**2)))
    empty = RoofSegmentation([], np.full(n, -1, np.int64), spacing, min_pts)
    if n < min_pts or n < 4:
        return empty
    thin = _thin(xyz, spacing, p.max_density)
    sub = xyz[thin]
    sub_spacing = _spacing(sub) if len(thin) < n else spacing
    sub_min = max(int(p.min_points), int(round(p.min_plane_area / sub_spacing**2)))
    if len(sub) < sub_min:
        return empty
    tree = cKDTree(sub)
    normals, curvature = _normals(sub, min(p.neighbours, len(sub)), tree)
    edges = tree.query_pairs(max(2.0 * sub_spacing, 1.5 * p.distance), output_type="ndarray")
    groups = _ransac_planes(sub, normals, curvature, edges, sub_min, p)
    too_many = len(groups) > 2 * p.max_planes  # the search stopped early
    if not groups:
        return empty
    fits = [_fit_robust(sub[g])[0] for g in groups]
    groups, fits = _merge(sub, groups, fits, p)
    fits = _regularise(sub, groups, fits, _edge_azimuths(footprint, 4.0 * spacing), p)
    sub_labels = _grow(sub, groups, fits, edges, p)
    labels = np.full(n, -1, np.int64)
    labels[thin] = sub_labels
    if len(thin) < n:
        # the points left out by the thinning take their nearest kept point's plane
        rest = np.setdiff1d(np.arange(n), thin)
        near = thin[tree.query(xyz[rest])[1]]
        k = labels[near]
        ok = k >= 0
        planes_arr = np.array(fits)
        dist = np.full(len(rest), np.inf)
        own = planes_arr[k[ok]]
        dist[ok] = np.abs(np.einsum("ij,ij->i", xyz[rest[ok]], own[:, :3]) + own[:, 3])
        labels[rest[dist < p.distance]] = k[dist < p.distance]
    planes = []
    counts = np.bincount(sub_labels[sub_labels >= 0], minlength=len(fits))
    for k in np.argsort(-counts, kind="stable"):
        if counts[k] < sub_min:
            continue
        members = np.flatnonzero(labels == k)
        plane = fits[k]
        residual = xyz[members] @ plane[:3] + plane[3]
        planes.append(
            RoofPlane(
                plane=plane,
                inliers=np.sort(order[members]),
                rms=float(np.sqrt(np.mean(residual**2))),
                area=float(counts[k] * sub_spacing**2),
                centroid=xyz[members].mean(axis=0),
            )
        )
    out = np.full(n, -1, np.int64)
    for k, plane in enumerate(planes):
        out[plane.inliers] = k
    too_many = too_many or len(planes) > p.max_planes
    return RoofSegmentation(planes, out, spacing, min_pts, too_many)


def roof_type(planes: Sequence[RoofPlane] | RoofSegmentation, *, flat_slope: float = 5.0) -> str:
    """Roof type from the planes: flat, shed, gable, hip, pyramid, mansard or complex.

    Only planes with at least 8 % of the roof area count ("major" planes); small
    dormers and chimneys do not change the type.

    - flat: no sloped major plane, or flat planes cover 85 % of the roof;
    - shed: one sloped major plane;
    - gable: two sloped planes facing opposite ways (within 20 degrees);
    - hip / pyramid: four sloped planes in two opposite pairs, the pairs at right
      angles; a pyramid when both pairs' intersection lines pass through one apex
      (their heights over the roof centre differ by less than 10 % of the roof's
      height range), a hip roof otherwise;
    - mansard: steep (>= 45 degrees) planes facing at least two opposite ways
      below a flat or shallow (< 30 degrees) top;
    - complex: anything else.

    Returns "unknown" without planes.
    """
    planes = list(planes.planes if isinstance(planes, RoofSegmentation) else planes)
    if not planes:
        return "unknown"
    total = sum(pl.area for pl in planes)
    major = [pl for pl in planes if pl.area >= 0.08 * total]
    flat = [pl for pl in major if pl.slope < flat_slope]
    sloped = [pl for pl in major if pl.slope >= flat_slope]
    if not sloped or sum(pl.area for pl in flat) >= 0.85 * total:
        return "flat"
    small_flat = sum(pl.area for pl in flat) < 0.15 * total
    if len(sloped) == 1 and small_flat:
        return "shed"
    convex = _convex(sloped)
    if len(sloped) == 2 and small_flat and convex and _opposite(sloped[0], sloped[1], 20.0):
        return "gable"
    if len(sloped) == 4 and small_flat and convex:
        kind = _hip_or_pyramid(sloped)
        if kind:
            return kind
    if _is_mansard(major, flat_slope):
        return "mansard"
    return "complex"


# --------------------------------------------------------------------------- helpers


def _spacing(xyz: np.ndarray) -> float:
    """Mean point spacing in plan: the median distance to the 4th nearest neighbour.

    Both for a regular grid and for random (Poisson) points this is close to
    ``1 / sqrt(density)``.
    """
    if len(xyz) < 6:
        return 1.0
    d = cKDTree(xyz[:, :2]).query(xyz[:, :2], k=5)[0][:, 4]
    s = float(np.median(d))
    return s if s > 0 else float(np.mean(d)) or 1.0


def _thin(xyz: np.ndarray, spacing: float, max_density: float) -> np.ndarray:
    """Indices of the points kept when the plan density exceeds ``max_density``: the first
    point (in sorted order) of every cell of a grid of ``1 / sqrt(max_density)``.

    The cell divides 100 units exactly, so the grid is the same whatever the local
    frame's origin (a multiple of 100 m): the thinning does not depend on tiling.
    """
    n = len(xyz)
    if not max_density or 1.0 / spacing**2 <= max_density:
        return np.arange(n)
    cell = 100.0 / math.ceil(100.0 * math.sqrt(max_density))
    keys = np.floor(xyz[:, :2] / cell).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def _normals(xyz: np.ndarray, k: int, tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (z >= 0) and surface variation (lambda0 / sum lambda) from k neighbours
    (``tree``: a k-d tree of ``xyz``, when one is already built)."""
    idx = (cKDTree(xyz) if tree is None else tree).query(xyz, k=k)[1].reshape(len(xyz), -1)
    nb = xyz[idx]
    nb -= nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    w, v = np.linalg.eigh(cov)
    normal = v[:, :, 0]
    normal[normal[:, 2] < 0] *= -1
    curvature = w[:, 0] / np.maximum(w.sum(axis=1), 1e-12)
    return normal, curvature


def _fit(points: np.ndarray) -> np.ndarray:
    """Least-squares plane (a, b, c, d), unit normal, c >= 0."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][-1]
    if normal[2] < 0:
        normal = -normal
    return np.append(normal, -normal @ centre)


def _fit_robust(points: np.ndarray, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane refitted without the points beyond 2.5 robust sigmas
    (edge and wall points that RANSAC's threshold let in); returns (plane, kept mask)."""
    keep = np.ones(len(points), bool)
    plane = _fit(points)
    for _ in range(iterations):
        r = np.abs(points @ plane[:3] + plane[3])
        sigma = 1.4826 * float(np.median(r))
        new = r <= max(2.5 * sigma, 1e-6)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        plane = _fit(points[keep])
    return plane, keep


def _components(members: np.ndarray, edges: np.ndarray, n: int) -> list[np.ndarray]:
    """Connected parts of the point subset ``members`` (edges: neighbour pairs of all points)."""
    inside = np.zeros(n, bool)
    inside[members] = True
    e = edges[inside[edges[:, 0]] & inside[edges[:, 1]]]
    local = np.full(n, -1, np.int64)
    local[members] = np.arange(len(members))
    m = len(members)
    graph = scipy.sparse.coo_matrix((np.ones(len(e)), (local[e[:, 0]], local[e[:, 1]])), shape=(m, m))
    count, label = connected_components(graph, directed=False)
    sizes = np.bincount(label, minlength=count)
    parts = np.argsort(-sizes, kind="stable")
    split = np.argsort(label, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(np.bincount(label, minlength=count))])
    return [members[split[bounds[c] : bounds[c + 1]]] for c in parts]


#: Largest number of points RANSAC draws its hypotheses from.
_RANSAC_SAMPLE = 1000


def _ransac_planes(xyz, normals, curvature, edges, min_pts, p: RoofParams) -> list[np.ndarray]:
    """Point groups of the planes found by repeated, seeded RANSAC."""
    from recon3d.core.o3d import open3d

    o3d = open3d()
    previous = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        return _ransac_loop(o3d, xyz, normals, curvature, edges, min_pts, p)
    finally:
        o3d.utility.set_max_threads(previous)


def _ransac_loop(o3d, xyz, normals, curvature, edges, min_pts, p: RoofParams) -> list[np.ndarray]:
    n = len(xyz)
    remaining = np.ones(n, bool)
    cos_normal = math.cos(math.radians(p.normal_angle))
    cos_wall = math.cos(math.radians(p.max_slope))
    groups: list[np.ndarray] = []
    failures = 0
    for attempt in range(6 * (p.max_planes + 1)):
        idx = np.flatnonzero(remaining)
        if len(idx) < min_pts or failures >= 3 or len(groups) > 2 * p.max_planes:
            break
        # the hypothesis from at most _RANSAC_SAMPLE points (a regular stride through
        # the sorted points), its inliers among all of them
        sample = idx
        if len(idx) > _RANSAC_SAMPLE:
            sample = idx[np.linspace(0, len(idx) - 1, _RANSAC_SAMPLE).astype(np.int64)]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz[sample]))
        o3d.utility.random.seed(int(p.seed) + attempt)
        model, _ = cloud.segment_plane(float(p.distance), 3, int(p.ransac_iterations))
        model = np.asarray(model, dtype=np.float64)
        scale = np.linalg.norm(model[:3]) or 1.0
        normal, offset = model[:3] / scale, model[3] / scale
        inliers = idx[np.abs(xyz[idx] @ normal + offset) <= p.distance]
        if not len(inliers):
            failures += 1
            continue
        agree = (np.abs(normals[inliers] @ normal) >= cos_normal) | (curvature[inliers] > 0.05)
        found = 0
        for part in _components(inliers[agree], edges, n) if agree.any() else []:
            if len(part) < min_pts:
                break
            plane, keep = _fit_robust(xyz[part])
            if plane[2] < cos_wall:  # a wall or a tree trunk: not a roof plane
                remaining[part] = False
                continue
            if keep.sum() < min_pts:
                continue
            remaining[part[keep]] = False
            groups.append(part[keep])
            found += 1
        if found:
            failures = 0
        else:
            failures += 1
            remaining[inliers] = False
    return groups


def _merge(xyz, groups, fits, p: RoofParams):
    """Merge groups lying on one plane.

    Two groups merge when each lies on the other's plane with similar normals (two
    parallel roofs at different heights would otherwise merge into one tilted
    plane), or when the smaller one lies on the larger one's plane (a narrow strip
    of points has a poorly defined plane of its own); and when their joint fit is
    as good as a plane fit of one group. Best pair first, until none is left.
    """
    cos_merge = math.cos(math.radians(p.merge_angle))
    groups, fits = list(groups), list(fits)
    rejected: set[tuple[int, int, int, int]] = set()
    while len(groups) > 1:
        # near[j, i]: share of (a sample of) group j's points within distance / 2 of
        # plane i; "the median distance is below distance / 2" is "near >= 0.5"
        picks = [
            g if len(g) <= 400 else g[np.linspace(0, len(g) - 1, 400).astype(np.int64)] for g in groups
        ]
        sizes = np.array([len(x) for x in picks])
        planes = np.array(fits)
        close = np.abs(xyz[np.concatenate(picks)] @ planes[:, :3].T + planes[:, 3]) <= 0.5 * p.distance
        near = np.add.reduceat(close, np.r_[0, np.cumsum(sizes)[:-1]], axis=0) / sizes[:, None]
        on_other = near.T  # on_other[i, j]: group j on plane i
        size = np.array([len(g) for g in groups])
        similar = np.abs(planes[:, :3] @ planes[:, :3].T) >= cos_merge
        mutual = np.minimum(on_other, on_other.T) >= 0.5
        small_on_large = np.where(size[:, None] >= size[None, :], on_other, on_other.T) >= 0.5
        cand = ((similar & mutual) | small_on_large) & ~np.eye(len(groups), dtype=bool)
        pairs = zip(*np.nonzero(np.triu(cand)), strict=True)
        order = sorted((-min(on_other[i, j], on_other[j, i]), int(i), int(j)) for i, j in pairs)
        pair = None
        for _, i, j in order:
            key = (len(groups[i]), len(groups[j]), int(groups[i][0]), int(groups[j][0]))
            if key in rejected:
                continue
            both = np.concatenate([groups[i], groups[j]])
            plane = _fit_robust(xyz[both])[0]
            resid = np.abs(xyz[both] @ plane[:3] + plane[3])
            if np.median(resid) < 0.5 * p.distance and np.percentile(resid, 90) < p.distance:
                pair = (i, j, both, plane)
                break
            rejected.add(key)
        if pair is None:
            break
        i, j, both, plane = pair
        groups[i], fits[i] = np.sort(both), plane
        del groups[j], fits[j]
    return groups, fits


def _edge_azimuths(footprint, min_length: float) -> np.ndarray:
    """Directions (degrees) of the footprint's edges at least ``min_length`` long."""
    if footprint is None:
        return np.zeros(0)
    rings = [footprint.exterior, *footprint.interiors]
    out = []
    for ring in rings:
        c = np.asarray(ring.coords)[:, :2]
        d = np.diff(c, axis=0)
        length = np.hypot(d[:, 0], d[:, 1])
        out.append(np.degrees(np.arctan2(d[length >= min_length, 1], d[length >= min_length, 0])))
    return np.concatenate(out) % 360.0 if out else np.zeros(0)


def _angle_diff(a, b):
    """Signed smallest difference a - b of angles in degrees, in (-180, 180]."""
    return (np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0


def _regularise(xyz, groups, fits, edge_az, p: RoofParams) -> list[np.ndarray]:
    """Flat snapping, aspect snapping to the footprint, symmetric slopes; offsets refitted."""
    slope = np.array([math.degrees(math.acos(min(1.0, f[2]))) for f in fits])
    az = np.array([math.degrees(math.atan2(f[1], f[0])) % 360.0 for f in fits])
    weight = np.array([len(g) for g in groups], dtype=np.float64)
    sloped = slope >= p.flat_slope
    if len(edge_az):
        targets = (edge_az[:, None] + np.array([0.0, 90.0, 180.0, 270.0])[None, :]).ravel()
        for k in np.flatnonzero(sloped):
            diff = _angle_diff(targets, az[k])
            j = int(np.argmin(np.abs(diff)))
            if abs(diff[j]) <= p.azimuth_snap:
                az[k] = targets[j] % 360.0
    # symmetric pairs: greedy, closest first
    cand = []
    for i in np.flatnonzero(sloped):
        for j in np.flatnonzero(sloped):
            if j <= i:
                continue
            opp = abs(float(_angle_diff(az[i], az[j] + 180.0)))
            ds = abs(slope[i] - slope[j])
            if opp <= p.azimuth_snap and ds <= p.symmetry_slope:
                cand.append((opp + ds, int(i), int(j)))
    used = set()
    for _, i, j in sorted(cand):
        if i in used or j in used:
            continue
        used |= {i, j}
        s = (slope[i] * weight[i] + slope[j] * weight[j]) / (weight[i] + weight[j])
        mid = (az[i] + 0.5 * float(_angle_diff(az[j] + 180.0, az[i]))) % 360.0
        slope[i] = slope[j] = s
        az[i], az[j] = mid, (mid + 180.0) % 360.0
    out = []
    for k, g in enumerate(groups):
        if sloped[k]:
            s, a = math.radians(slope[k]), math.radians(az[k])
            normal = np.array([math.sin(s) * math.cos(a), math.sin(s) * math.sin(a), math.cos(s)])
        else:
            normal = np.array([0.0, 0.0, 1.0])
        pts = xyz[g]
        d = -float(np.median(pts @ normal)) if not sloped[k] else -float(np.mean(pts @ normal))
        out.append(np.append(normal, d))
    return out


def _grow(xyz, groups, fits, edges, p: RoofParams) -> np.ndarray:
    """Point labels: the groups' points still near their (regularised) plane, grown over
    neighbouring points within ``distance`` of the plane (closest plane wins)."""
    n = len(xyz)
    planes = np.array(fits)
    labels = np.full(n, -1, np.int64)
    for k, g in enumerate(groups):
        labels[g] = k
    has = labels >= 0
    dist_own = np.full(n, np.inf)
    own = planes[labels[has]]
    dist_own[has] = np.abs(np.einsum("ij,ij->i", xyz[has], own[:, :3]) + own[:, 3])
    labels[dist_own > 2.0 * p.distance] = -1
    if not len(edges):
        return labels
    src = np.concatenate([edges[:, 0], edges[:, 1]])
    dst = np.concatenate([edges[:, 1], edges[:, 0]])
    for _ in range(50):
        sel = (labels[src] >= 0) & (labels[dst] < 0)
        if not sel.any():
            break
        s, d = src[sel], dst[sel]
        k = labels[s]
        dist = np.abs(np.einsum("ij,ij->i", xyz[d], planes[k, :3]) + planes[k, 3])
        ok = dist < p.distance
        if not ok.any():
            break
        d, k, dist = d[ok], k[ok], dist[ok]
        order = np.lexsort((k, dist, d))
        d, k = d[order], k[order]
        first = np.r_[True, d[1:] != d[:-1]]
        labels[d[first]] = k[first]
    return labels


def _convex(planes: list[RoofPlane]) -> bool:
    """Whether the planes make a convex roof: each one is the lowest of all at its own
    centroid (within 5 % of the roof's height range), as for a gable, hip or pyramid
    roof; false for cross gables, butterfly roofs and separate wings."""
    if len(planes) < 2:
        return True
    zs = [q.centroid[2] for q in planes]
    tol = 0.05 * max(1.0, 4.0 * float(np.ptp(zs)))
    for q in planes:
        x, y = q.centroid[:2]
        own = float(q.height(x, y))
        if any(float(o.height(x, y)) < own - tol for o in planes if o is not q):
            return False
    return True


def _opposite(a: RoofPlane, b: RoofPlane, tol: float) -> bool:
    return abs(float(_angle_diff(a.azimuth, b.azimuth + 180.0))) <= tol


def _perpendicular(a: RoofPlane, b: RoofPlane, tol: float) -> bool:
    return abs(abs(float(_angle_diff(a.azimuth, b.azimuth))) - 90.0) <= tol


def _hip_or_pyramid(sloped: list[RoofPlane]) -> str | None:
    """'hip' or 'pyramid' for four planes in two opposite, perpendicular pairs; else None."""
    a = sloped[0]
    partners = [q for q in sloped[1:] if _opposite(a, q, 20.0)]
    if len(partners) != 1:
        return None
    b = partners[0]
    c, d = (q for q in sloped[1:] if q is not b)
    if not (_opposite(c, d, 20.0) and _perpendicular(a, c, 20.0)):
        return None
    # height of each pair's intersection line above the planes' common centre
    weights = np.array([q.area for q in sloped])
    centre = np.average([q.centroid[:2] for q in sloped], axis=0, weights=weights)
    h1 = _pair_height(a, b, centre)
    h2 = _pair_height(c, d, centre)
    # the planes' centroids lie about half-way down the roof: twice the drop from the
    # higher line to them is the roof's height range
    low = float(np.min([q.centroid[2] for q in sloped]))
    span = max(2.0 * (max(h1, h2) - low), 1e-6)
    return "pyramid" if abs(h1 - h2) < 0.1 * span else "hip"


def _pair_height(a: RoofPlane, b: RoofPlane, centre: np.ndarray) -> float:
    """Height of the intersection line of two opposite planes, at the point of the line
    nearest to ``centre`` in plan."""
    # difference of the two height functions: g(x, y) = ha - hb = u . (x, y) + w
    ga = -a.plane[:2] / a.plane[2]
    gb = -b.plane[:2] / b.plane[2]
    u = ga - gb
    w = -a.plane[3] / a.plane[2] + b.plane[3] / b.plane[2]
    nu = float(u @ u)
    if nu < 1e-12:
        return float(a.height(*centre))
    foot = centre - (float(u @ centre) + w) / nu * u
    return float(a.height(*foot))


def _is_mansard(major: list[RoofPlane], flat_slope: float) -> bool:
    steep = [q for q in major if q.slope >= 45.0]
    top = [q for q in major if q.slope < 30.0]
    if len(steep) < 2 or not top:
        return False
    pairs = any(_opposite(a, b, 20.0) for i, a in enumerate(steep) for b in steep[i + 1 :])
    above = max(q.centroid[2] for q in top) > max(q.centroid[2] for q in steep)
    return pairs and above
