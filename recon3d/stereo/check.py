"""The self-check of a matched pair against what its own input already knows.

A COLMAP model holds triangulated sparse points: bundle adjusted, each observed by
the images of its track. Dense matching must agree with them. For every pair,
:func:`check_pair` measures

- **coverage**: the share of the sparse points both images observe whose pixel, or a
  neighbour of it, holds a matched disparity (not a filled-in one). A rectification that
  drops part of the common area, or a disparity search that misses the scene, shows
  here first;
- **discrepancy**: the distance from each covered sparse point to the dense surface
  along its ray, from the matched disparity of its 3 x 3 pixel neighbourhood closest to
  its own (the sparse point's pixel is itself uncertain by about a pixel);
- **reprojection**: dense points triangulated from a sample of matched pixels, projected
  into both original images through the cameras (lens distortion included), against
  the pixels the rectified images were resampled from. Rectification and triangulation
  must agree to a small fraction of a pixel.

The tie points also bound the dense cloud from below (:func:`under_tie_points`): they
lie on the surface, ground or objects, and in any neighbourhood wider than a roof some
lie on the ground, so a dense point far below every tie point around it is a mismatch.
On a rendered hilly survey seven cells of such points under a hilltop sank the DTM by
metres (ground check points 1.54 m RMS, 0.10 m without them).

They also check the DTM (:func:`sunk_under_ground_ties`): a coherent patch of
mismatches a few metres under the ground, too shallow for the bound above, can be taken
for the ground over hundreds of square metres. The tie points on the ground inside such
a patch contradict it.

:func:`verdict` turns the figures into an error (the geometry contradicts the input:
nothing is written) or a warning (part of the area is lost), with the pair and the
figures named.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np
import shapely

from recon3d.core.geo import Units
from recon3d.core.raster import Raster, grid_for_bounds
from recon3d.errors import InputError
from recon3d.stereo.rectify import RectifiedPair
from recon3d.terrain.dsm import grid_points

__all__ = ["LIMITS", "MIN_TIE_POINTS_FOR_PLANE", "TIE_POINT_RADIUS", "check_pair", "sunk_under_ground_ties", "tie_ground",
           "tie_point_radius", "under_tie_points", "verdict"]

#: Thresholds of :func:`verdict`: least coverage (percent, a warning below), largest
#: median discrepancy (ground sample distances) and largest 95th percentile of the
#: reprojection error (pixels), errors beyond.
LIMITS = {"coverage_percent": 90.0, "discrepancy_gsd": 2.0, "reprojection_px": 1.0}


def check_pair(
    pair: RectifiedPair,
    disparity: np.ndarray,
    matched: np.ndarray,
    points: np.ndarray,
    *,
    samples: int = 20000,
) -> dict:
    """Compare a pair's dense disparities with the sparse points both images observe.

    Parameters
    ----------
    pair : RectifiedPair
    disparity : (H, W) float
        Left-image disparity (NaN where none).
    matched : (H, W) bool
        Pixels whose disparity was matched rather than filled in.
    points : (n, 3) float
        Sparse points in both images' tracks, model coordinates.
    samples : int
        Matched pixels reprojected into the original images (an even spread).

    Returns
    -------
    dict
        ``sparse_points``, ``covered``, ``coverage_percent``, ``discrepancy_m`` (median),
        ``discrepancy_p90_m``, ``gsd_m``, ``discrepancy_gsd``, ``disparity_error_px``
        (median), ``reprojection_px`` (95th percentile, worse image), ``uncovered``
        (model xyz of the sparse points not covered, (k, 3)).
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    h, w = disparity.shape
    uvl, uvr = pair.project(points)
    expected = uvl[:, 0] - uvr[:, 0]
    col, row = np.rint(uvl[:, 0]).astype(np.int64), np.rint(uvl[:, 1]).astype(np.int64)
    ok = matched & np.isfinite(disparity)
    best = np.full(len(points), np.inf)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = row + dr, col + dc
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            err = np.full(len(points), np.inf)
            hit = inside.copy()
            hit[inside] = ok[r[inside], c[inside]]
            err[hit] = np.abs(disparity[r[hit], c[hit]] - expected[hit])
            best = np.minimum(best, err)
    covered = np.isfinite(best)
    distance = np.linalg.norm(points - pair.camera_left.center, axis=1)
    # moving the disparity by e moves the point along its ray by e / (d - offset) of its distance
    along = best / np.maximum(expected - pair.offset, 1e-9) * distance
    gsd = float(np.median(distance / pair.focal)) if len(points) else float("nan")
    result = {
        "sparse_points": int(len(points)),
        "covered": int(covered.sum()),
        "coverage_percent": round(100.0 * float(covered.mean()), 2) if len(points) else 0.0,
        "gsd_m": round(gsd, 4),
        "reprojection_px": _reprojection(pair, disparity, ok, samples),
        "uncovered": points[~covered],
    }
    if covered.any():
        median = float(np.median(along[covered]))
        result.update(
            discrepancy_m=round(median, 4),
            discrepancy_p90_m=round(float(np.percentile(along[covered], 90)), 4),
            discrepancy_gsd=round(median / gsd, 3),
            disparity_error_px=round(float(np.median(best[covered])), 3),
        )
    return result


def _reprojection(pair: RectifiedPair, disparity: np.ndarray, ok: np.ndarray, samples: int) -> float | None:
    """95th percentile (pixels) of the worse image's reprojection error of matched pixels."""
    rows, cols = np.nonzero(ok)
    if not len(rows):
        return None
    pick = np.linspace(0, len(rows) - 1, min(samples, len(rows))).astype(np.int64)
    y, x = rows[pick].astype(np.float64), cols[pick].astype(np.float64)
    d = disparity[rows[pick], cols[pick]].astype(np.float64)
    xyz = pair.triangulate(x, y, d)
    good = np.isfinite(xyz).all(axis=1)
    errors = []
    for cam, xy, right in ((pair.camera_left, np.column_stack([x, y]), False),
                           (pair.camera_right, np.column_stack([x - d, y]), True)):
        seen = pair.to_original(xy[good], right=right)
        projected = cam.project(xyz[good], distort=True)[0]
        errors.append(np.linalg.norm(projected - seen, axis=1))
    worst = np.maximum(*errors)
    return round(float(np.percentile(worst, 95)), 4) if worst.size else None


def verdict(name: str, check: dict, limits: dict = LIMITS, *, offset=(0.0, 0.0, 0.0)) -> str | None:
    """Raise when a pair's dense result contradicts its input; return a warning or None.

    The warning names where the uncovered sparse points lie, in world coordinates
    (model + ``offset``).

    Raises
    ------
    InputError
        Median discrepancy above ``limits["discrepancy_gsd"]`` ground sample distances
        (and above one pixel of disparity, the sparse points' own precision), or a
        reprojection error above ``limits["reprojection_px"]``.
    """
    reproj = check.get("reprojection_px")
    if reproj is not None and reproj > limits["reprojection_px"]:
        raise InputError(
            f"images {name}: dense points reproject {reproj:.2f} px from where they were matched "
            f"(95th percentile, limit {limits['reprojection_px']} px); the rectification does not fit the cameras"
        )
    if check.get("covered", 0) and check["discrepancy_gsd"] > limits["discrepancy_gsd"] and check["disparity_error_px"] > 1.0:
        raise InputError(
            f"images {name}: the dense surface lies {check['discrepancy_m']:.2f} m "
            f"({check['discrepancy_gsd']:.1f} ground sample distances, {check['disparity_error_px']:.1f} px of "
            f"disparity) from the model's own sparse points (median of {check['covered']}); "
            f"limit {limits['discrepancy_gsd']} GSD: the orientation or the matching is wrong"
        )
    if check["sparse_points"] and check["coverage_percent"] < limits["coverage_percent"]:
        lost = check["uncovered"] + np.asarray(offset, np.float64)
        where = ""
        if len(lost):
            lo, hi = lost.min(axis=0), lost.max(axis=0)
            where = f" (x {lo[0]:.0f}..{hi[0]:.0f}, y {lo[1]:.0f}..{hi[1]:.0f})"
        return (
            f"images {name}: the dense result covers {check['covered']} of the {check['sparse_points']} sparse "
            f"points both images observe ({check['coverage_percent']:.0f} %, expected >= "
            f"{limits['coverage_percent']:.0f} %); {len(lost)} lie where nothing was matched{where}"
        )
    return None


#: Least radius (m) around a point searched for tie points by :func:`under_tie_points`;
#: :func:`tie_point_radius` widens it where the tie points are sparse. On the survey
#: family at 1000 px, 30 m rather than 60 m brought a hilly survey's ground check points
#: from 3.86 to 1.73 m RMS (random_26: mismatches 5-17 m low) and changed no other by
#: more than 1 cm.
TIE_POINT_RADIUS = 30.0


def tie_point_radius(tie_points: np.ndarray, units: Units) -> tuple[float, str]:
    """Radius (CRS units) within which the ground holds tie points, and why.

    Three tie point spacings (the square root of the area of their convex hull per
    point), at least :data:`TIE_POINT_RADIUS`: wide enough that streets and yards, not
    only roofs, hold tie points within it.
    """
    xy = np.asarray(tie_points, np.float64)[:, :2]
    area = shapely.MultiPoint(xy).convex_hull.area if len(xy) >= 3 else 0.0
    spacing = math.sqrt(area / len(xy)) if area > 0 else 0.0
    radius = max(units.length(TIE_POINT_RADIUS), 3.0 * spacing)
    why = (f"3 x the tie points' spacing ({spacing * units.horizontal:.1f} m), at least {TIE_POINT_RADIUS:.0f} m: "
           "streets, not only roofs, hold tie points within it")
    return radius, why


def under_tie_points(xyz: np.ndarray, tie_points: np.ndarray, *, radius: float, margin: float) -> np.ndarray:
    """(n,) bool: points more than ``margin`` below every tie point within ``radius``.

    The radius is rounded to cells of about ``radius / 8``. A point with no tie point
    within it is judged against the ground of all of them instead (:func:`tie_ground`):
    flagged when more than ``margin`` plus three times that plane's spread below it.

    Parameters
    ----------
    xyz : (n, 3) float
        Dense points.
    tie_points : (m, 3) float
        Sparse points, same coordinates.
    radius, margin : float
        CRS units.
    """
    xyz = np.asarray(xyz, np.float64)
    under = np.zeros(len(xyz), bool)
    if not len(xyz) or not len(tie_points):
        return under
    lo, hi = xyz[:, :2].min(axis=0) - radius, xyz[:, :2].max(axis=0) + radius  # tie points around the edge
    step = radius / 8
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], step)
    lowest = grid_points(np.asarray(tie_points, np.float64), transform, shape, reducer="min")
    k = math.ceil(radius / step)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    floor = cv2.erode(np.where(np.isfinite(lowest), lowest, np.inf).astype(np.float32), disc,
                      borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    cols, rows = ~transform * (xyz[:, 0], xyz[:, 1])
    rows = np.clip(np.floor(rows).astype(np.int64), 0, shape[0] - 1)
    cols = np.clip(np.floor(cols).astype(np.int64), 0, shape[1] - 1)
    floor = floor[rows, cols].astype(np.float64)
    under = np.isfinite(floor) & (xyz[:, 2] < floor - margin)  # inf: no tie point within the radius
    far = ~np.isfinite(floor)
    ground = tie_ground(tie_points) if far.any() else None
    if ground is not None:
        plane, spread = ground
        under[far] = xyz[far, 2] < plane(xyz[far, :2]) - margin - 3.0 * spread
    return under


#: Tie points needed to fit :func:`tie_ground`'s plane.
MIN_TIE_POINTS_FOR_PLANE = 10


def tie_ground(tie_points: np.ndarray) -> tuple[Callable[[np.ndarray], np.ndarray], float] | None:
    """The plane under the tie points, and the spread of the ground tie points about it.

    Least squares on the lower half of the tie points, three times over (each round keeps
    those at or below the median residual of the last): roofs and trees drop out, the
    ground and its slope stay. The spread is the NMAD of the residuals of the lower half
    of all the tie points: a plane fits flat or evenly sloping ground closely, hills
    loosely.

    Parameters
    ----------
    tie_points : (m, 3) float
        Sparse points.

    Returns
    -------
    plane : callable
        ``plane(xy)`` -> (n,) heights, for (n, 2) coordinates.
    spread : float
        None instead of both with fewer than :data:`MIN_TIE_POINTS_FOR_PLANE` tie points.
    """
    t = np.asarray(tie_points, np.float64)
    if len(t) < MIN_TIE_POINTS_FOR_PLANE:
        return None
    centre = t[:, :2].mean(axis=0)
    design = np.column_stack([t[:, :2] - centre, np.ones(len(t))])
    keep = np.ones(len(t), bool)
    for _ in range(3):
        coef = np.linalg.lstsq(design[keep], t[keep, 2], rcond=None)[0]
        residual = t[:, 2] - design @ coef
        keep = residual <= np.median(residual[keep])
    lower = residual[residual <= np.median(residual)]
    spread = 1.4826 * float(np.median(np.abs(lower - np.median(lower))))

    def plane(xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, np.float64) - centre
        return xy[:, 0] * coef[0] + xy[:, 1] * coef[1] + coef[2]

    return plane, spread


#: Largest spread (m) of the ground tie points about their plane (:func:`tie_ground`)
#: for which :func:`sunk_under_ground_ties` tells ground tie points from the others:
#: flat or evenly sloping land. On hills no plane tells them apart, and the check is off.
GROUND_TIE_MAX_SPREAD = 0.5

#: How far (m) beyond three spreads a ground tie point may lie from the plane.
GROUND_TIE_BAND = 0.5

#: How far (m) the DTM may lie under the ground tie points before its region is sunk.
SUNK_MARGIN = 1.0


def sunk_under_ground_ties(dtm: Raster, tie_points: np.ndarray, *, margin: float, band: float,
                           max_spread: float) -> tuple[np.ndarray, np.ndarray]:
    """The DTM's regions sunk under the ground tie points inside them.

    Ground tie points are those within ``band`` plus three spreads of the plane under
    the tie points (:func:`tie_ground`); only where that plane fits the ground closely
    (spread at most ``max_spread``) does it tell them from roofs and crowns. A region is
    a 4-connected set of cells where the DTM lies more than ``margin`` under the plane;
    it is sunk when a ground tie point in it stands more than ``margin`` above the DTM.
    A pit that holds no ground tie point is left as it is: it may be real.

    Parameters
    ----------
    dtm : Raster
        (rows, cols) terrain heights, NaN where unknown.
    tie_points : (m, 3) float
        Sparse points, in the DTM's coordinates.
    margin, band, max_spread : float
        CRS height units.

    Returns
    -------
    sunk : (rows, cols) bool
    ties : (k, 3) float
        The ground tie points inside the sunk regions.
    """
    ground = tie_ground(tie_points)
    none = np.zeros(dtm.shape, bool), np.empty((0, 3))
    if ground is None or ground[1] > max_spread:
        return none
    plane, spread = ground
    t = np.asarray(tie_points, np.float64)
    t = t[np.abs(t[:, 2] - plane(t[:, :2])) <= band + 3.0 * spread]
    row, col = dtm.rowcol(t[:, 0], t[:, 1])
    inside = (row >= 0) & (row < dtm.shape[0]) & (col >= 0) & (col < dtm.shape[1])
    t, row, col = t[inside], row[inside], col[inside]
    if not len(t):
        return none
    xs, ys = dtm.cell_centers()  # a plane is the sum of its first row and its first column, less their corner
    along_x = plane(np.column_stack([xs, np.full_like(xs, ys[0])]))
    along_y = plane(np.column_stack([np.full_like(ys, xs[0]), ys]))
    under = along_y[:, None] + (along_x - along_x[0] - margin)
    low = np.isfinite(dtm.data) & (dtm.data < under)
    contradicted = low[row, col] & (t[:, 2] - dtm.data[row, col] > margin)
    if not contradicted.any():
        return none
    _, labels = cv2.connectedComponents(low.astype(np.uint8), connectivity=4)
    sunk = np.isin(labels, np.unique(labels[row[contradicted], col[contradicted]]))
    return sunk, t[sunk[row, col]]
