"""Frame stereo: an oriented scene folder to a dense point cloud in world coordinates."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import cv2
import numpy as np

from recon3d.config import StereoConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import PointCloud
from recon3d.errors import InputError
from recon3d.io.colmap import StereoScene
from recon3d.stereo.check import check_pair, tie_ground, tie_point_radius, under_tie_points, verdict
from recon3d.stereo.fuse import fuse
from recon3d.stereo.rectify import RectifiedPair, rectify_pair, sample_extremes, select_pairs
from recon3d.stereo.triangulate import triangulate

log = logging.getLogger(__name__)

__all__ = ["dense_cloud", "matching_constraints"]


def dense_cloud(
    scene: StereoScene,
    config: StereoConfig,
    *,
    bounds: Callable[[RectifiedPair], tuple[np.ndarray, np.ndarray, np.ndarray | None]] | None = None,
    warn: Callable[[str], None] | None = None,
    progress: Callable[[str], None] | None = None,
    units: Units | None = None,
) -> tuple[PointCloud, dict]:
    """Match every usable pair of the scene, check each against the sparse points, fuse,
    and remove the fused points far below every tie point around them.

    Parameters
    ----------
    scene : StereoScene
    config : StereoConfig
    bounds : callable, optional
        ``bounds(pair)`` -> per-pixel disparity bounds (low, high) and an optional
        weight map for the matcher (vector-constrained matching), or None.
    warn : callable, optional
        Receives the warnings of the self-check (default: logged).
    progress : callable, optional
        Receives "pair k/n" as each pair starts.
    units : Units, optional
        Of the scene's CRS (default: metres).

    Returns
    -------
    cloud : PointCloud
        World coordinates (model + offset), the scene's CRS; colours and ``quality``.
    report : dict
        Pairs considered, rectification residuals, disparity ranges, the self-check per
        pair, point counts and each pair's share of the fused cloud.

    Raises
    ------
    InputError
        No usable pair, or a pair whose dense result contradicts the sparse points.
    """
    warn = warn or log.warning
    pairs, candidates = select_pairs(scene.cameras, scene.sparse, scene.seen, max_partners=config.max_partners or None)
    report = {"candidates": candidates, "pairs": []}
    if bounds is not None:
        report["constraints"] = getattr(bounds, "sources", {})
    clouds = []
    # every pair searches up to the block's highest sparse points, though its own may sample no tall roof
    top = sample_extremes(scene.sparse[:, 2])[1]
    for k, (i, j) in enumerate(pairs):
        if progress:
            progress(f"pair {k + 1}/{len(pairs)}")
        common = scene.seen[i] & scene.seen[j]
        cloud, record = _match_pair(scene, i, j, scene.sparse[common], top, config, bounds, warn)
        source = len(report["pairs"]) + 1  # the pair's id in cloud.laz
        cloud.attributes["point_source_id"] = np.full(len(cloud), source, np.uint16)
        report["pairs"].append({"point_source_id": source, **record})
        clouds.append(cloud)
    if not any(len(c) for c in clouds):
        raise InputError(f"{scene.folder}: dense matching produced no point")
    gsd = _ground_sample_distance(scene)
    cloud = fuse([c for c in clouds if len(c)], cell=gsd, rough=_foliage)
    cloud = PointCloud(cloud.xyz + scene.offset, cloud.attributes, scene.crs)
    cloud = _without_points_under_tie_points(cloud, scene, config, units or Units(), report)
    kept = np.bincount(cloud.attributes["point_source_id"], minlength=len(clouds) + 1)
    for record in report["pairs"]:  # what each pair gives the cloud the run goes on with
        n = int(kept[record["point_source_id"]])
        record["points_fused"] = n
        record["fused_share_percent"] = round(100.0 * n / max(1, len(cloud)), 2)
    report["pair_count"] = len(pairs)
    report["ground_sample_distance"] = round(gsd, 4)
    report["points"] = len(cloud)
    return cloud, report


def _without_points_under_tie_points(cloud: PointCloud, scene: StereoScene, config: StereoConfig, units: Units,
                                     report: dict) -> PointCloud:
    """The fused cloud less the points more than ``config.tie_point_margin`` below every
    tie point around them (:func:`recon3d.stereo.check.under_tie_points`), counted in
    ``report["under_tie_points"]``."""
    margin = config.tie_point_margin
    if not math.isfinite(margin) or not len(scene.sparse):
        return cloud
    ties = scene.sparse + scene.offset
    radius, why = tie_point_radius(ties, units)
    under = under_tie_points(cloud.xyz, ties, radius=radius, margin=units.height(margin))
    report["under_tie_points"] = {
        "value": int(under.sum()), "radius": round(radius * units.horizontal, 1), "margin": margin,
        "reason": f"points more than {margin:g} m below every tie point within the radius ({why}), or, with "
                  f"none within it, {margin:g} m plus 3 spreads below the plane under the tie points: "
                  "mismatches, removed",
    }
    ground = tie_ground(ties)
    if ground is not None:
        report["under_tie_points"]["plane_spread"] = round(ground[1] * units.vertical, 3)
    if under.any():
        log.info("%d dense points more than %g m below the tie points around them removed", int(under.sum()), margin)
        cloud = cloud[~under]
    return cloud


def matching_constraints(scene: StereoScene, config: StereoConfig, units, *, dem=None, footprints=None,
                         constraints=None):
    """The per-pixel disparity bounds for :func:`dense_cloud` from the user's vectors and
    DEM (:mod:`recon3d.stereo.constraints`), or None when none was given (or
    ``config.vectors`` is off).

    Returns
    -------
    callable or None
        ``bounds(pair)`` -> (low, high, weight) per rectified left pixel; its ``sources``
        attribute says what went in, for run.json.
    """
    from recon3d.terrain.dtm import densify_lines
    from recon3d.stereo.constraints import elevation_bounds, pair_bounds, roof_range

    if not config.vectors:
        return None
    ground = np.zeros((0, 3))
    if constraints is not None:
        lines, points = constraints
        ground = np.concatenate([densify_lines(lines, units.length(1.0)), points]) if lines else points
    roofs = [(f.polygon, *roof_range(f.attributes)) for f in footprints or []]
    roofs = [r for r in roofs if r[1] is not None or r[2] is not None]
    if dem is None and len(ground) < 3 and not roofs:
        return None
    world = scene.sparse + scene.offset
    lo, hi = world.min(axis=0), world.max(axis=0)
    pad = 0.5 * (hi[:2] - lo[:2]) + units.length(20.0)
    extent = (lo[0] - pad[0], lo[1] - pad[1], hi[0] + pad[0], hi[1] + pad[1])
    tallest, why = _tallest_object(world, dem, config, units)
    bounds = elevation_bounds(
        extent, units.length(1.0), dem=dem, dem_tolerance=units.height(config.dem_tolerance),
        max_object_height=tallest, ground_points=ground if len(ground) >= 3 else None,
        ground_tolerance=units.height(0.5), footprints=roofs, roof_tolerance=units.length(config.roof_tolerance),
        footprint_weight=config.footprint_weight,
    )
    tops = [r[2] for r in roofs if r[2] is not None]
    z_range = (float(lo[2]) - units.height(30.0), max([float(hi[2]), *tops]) + units.height(30.0))

    def pixel_bounds(pair: RectifiedPair):
        return pair_bounds(pair, bounds, scene.offset, z_range)

    pixel_bounds.sources = {**bounds.sources, "max_object_height": {"value": round(tallest, 2), "reason": why}}
    return pixel_bounds


def _tallest_object(world: np.ndarray, dem, config: StereoConfig, units) -> tuple[float, str]:
    """Height of the tallest object above the DEM (CRS height units) and why."""
    if config.max_object_height is not None:
        return units.height(config.max_object_height), "config"
    if dem is None:
        return units.height(40.0), "no DEM"
    above = world[:, 2] - dem.sample(world[:, 0], world[:, 1])
    above = above[np.isfinite(above)]
    if not above.size:
        return units.height(40.0), "no sparse point over the DEM: 40 m"
    return float(above.max()) + units.height(10.0), f"highest sparse point {above.max():.1f} above the DEM, plus 10 m"


def _match_pair(scene, i, j, points, top, config, bounds, warn) -> tuple[PointCloud, dict]:
    """Rectify, match, triangulate and self-check one pair (``top``: see :func:`rectify_pair`)."""
    from recon3d.stereo.match import MatchParams, match, photo_consistency

    a, b = scene.cameras[i], scene.cameras[j]
    pair = rectify_pair(
        a, b, _read(a.image_path), _read(b.image_path), points,
        max_parallax=config.max_parallax, max_disparities=config.max_disparities, top=top,
    )
    dmin, dmax = pair.disparity_range
    # black borders outside the photos are nodata, not texture to match
    left = np.where(pair.valid_left, pair.left, np.nan).astype(np.float32)
    right = np.where(pair.valid_right, pair.right, np.nan).astype(np.float32)
    low = high = weight = None
    if bounds is not None:
        low, high, weight = bounds(pair)
    slant, slant_reason = _slant(pair, points, config)
    # frame pairs: a roof face foreshortened in one view is missed beside the ground its
    # building hides; see MatchParams.fill_foreground
    params = MatchParams(min_disparity=dmin, max_disparity=dmax, engine=config.engine, slant=slant,
                         fill_foreground=True, sharpen_steps=config.sharpen_steps)
    result = match(left, right, params, guide=pair.color, guide_right=pair.color_right, low=low, high=high,
                   weight=weight)
    # A filled-in disparity is a guess, even where the images agree with it: beside walls
    # such agreement is often chance, and carried the roof onto the street in 62 % of the
    # spilled cells of a rendered survey. Agreement still tells a steep or shadowed roof
    # face the matcher missed from a courtyard it could not see (see make_dtm). 1: the
    # images agree with the guess; 2: it lies beyond an occlusion's width.
    consistent = (result.filled & (photo_consistency(left, right, result.disparity) >= 0.4)).astype(np.uint8)
    if result.foreground is not None:  # no hidden ground
        consistent[result.foreground] = 2
    cloud = triangulate(
        pair, result.disparity, result.confidence, min_angle_deg=config.min_angle,
        guessed=result.filled, consistent=consistent,
    )
    check = check_pair(pair, result.disparity, ~result.filled & np.isfinite(result.disparity), points)
    message = verdict(pair.name, check, offset=scene.offset)
    if message:
        warn(message)
    overlap = _overlap(pair)
    matched = np.isfinite(result.unfilled) & overlap
    record = {
        "pair": pair.name,
        "images": [pair.camera_left.name, pair.camera_right.name],
        "rectified_size": list(pair.left.shape[::-1]),
        "disparity_offset_px": round(pair.offset, 1),
        "vertical_parallax_px": pair.parallax,
        "disparity_range": {"value": [dmin, dmax], "reason": pair.range_reason},
        "matched_percent": round(100.0 * float(matched.sum()) / max(1, int(overlap.sum())), 2),
        "density_percent": round(100.0 * float(np.mean(np.isfinite(result.disparity[overlap]))), 1) if overlap.any() else 0.0,
        "matching": {k: result.params[k] for k in ("disparity_range_searched", "seconds", "engine", "sharpened_percent",
                                                   "foreground_percent")
                     if k in result.params},
        "slant": {"value": slant, "reason": slant_reason},
        "self_check": {k: v for k, v in check.items() if k != "uncovered"},
        "points": len(cloud),
    }
    if bounds is not None:
        record["constrained_percent"] = round(100.0 * float(np.mean(np.isfinite(low[overlap]))), 2) if low is not None else 0.0
    return cloud, record


#: Base-to-height ratio from which frame pairs also match sheared census windows (see
#: ``StereoConfig.slant``). On the four wide-base surveys of the family at 1000 px (B/H
#: 0.6-1.0) the sheared windows lowered the tolerant DSM RMS by 0.04-0.18 m and raised
#: footprint completeness by 0.7-3.8 points; below it roof faces are not foreshortened
#: enough to need them.
SLANT_BASE_TO_HEIGHT = 0.45
#: Disparity gradient of the sheared windows when chosen automatically.
SLANT = 0.5


def _slant(pair: RectifiedPair, points: np.ndarray, config: StereoConfig) -> tuple[float, str]:
    """The census windows' shear for a pair and why (run.json)."""
    if config.slant is not None:
        return float(config.slant), "config"
    if config.engine != "census":
        return 0.0, "sgbm engine: upright windows only"
    depth = ((np.asarray(points, np.float64) - pair.camera_left.center) @ pair.rotation.T)[:, 2]
    depth = depth[depth > 0]
    if not depth.size:
        return 0.0, "upright windows: no sparse point to judge the base-to-height ratio by"
    ratio = pair.baseline / float(np.median(depth))
    if ratio >= SLANT_BASE_TO_HEIGHT:
        return SLANT, (f"base-to-height {ratio:.2f} >= {SLANT_BASE_TO_HEIGHT}: roof faces are foreshortened "
                       "in one view, sheared windows match them")
    return 0.0, f"base-to-height {ratio:.2f} < {SLANT_BASE_TO_HEIGHT}: upright windows suffice"


def _overlap(pair: RectifiedPair) -> np.ndarray:
    """(H, W) bool: left pixels whose match at the middle of the searched range lies in the right image."""
    mid = int(round(sum(pair.disparity_range) / 2))
    shifted = np.zeros_like(pair.valid_right)
    w = shifted.shape[1]
    if mid >= 0:
        shifted[:, mid:] = pair.valid_right[:, : w - mid]
    else:
        shifted[:, : w + mid] = pair.valid_right[:, -mid:]
    return pair.valid_left & shifted


def _foliage(cloud: PointCloud) -> np.ndarray | None:
    """(n,) bool: points coloured like foliage (the colour-only vegetation threshold)."""
    from recon3d.buildings.vegetation import COLOUR_ONLY_THRESHOLDS, vegetation_index

    index = vegetation_index(cloud)
    return None if index is None else index[0] > COLOUR_ONLY_THRESHOLDS[index[1]]


def _read(path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"{path}: unreadable image")
    return image


def _ground_sample_distance(scene: StereoScene) -> float:
    """Median pixel footprint on the ground: depth of the sparse points over the focal length."""
    gsd = []
    for k, cam in enumerate(scene.cameras):
        _, depth = cam.project(scene.sparse[scene.seen[k]])
        depth = depth[depth > 0]
        if depth.size:
            gsd.append(np.median(depth) / cam.K[0, 0])
    return float(np.median(gsd)) if gsd else 1.0
