"""Satellite (RPC) stereo: affine epipolar rectification, matching and ray intersection.

Pushbroom images have no single projection centre, but over a crop of a few thousand
pixels each RPC is very close to an affine camera (the s2p observation). The epipolar
direction is then constant over the crop: a pixel of one image, lifted through the
RPC heights, traces a straight line in the other. Both images are turned so that
these lines are rows, the second one fitted (affine, least squares) so that
corresponding points share a row, then matched with the frame-stereo matcher. Each
match is intersected by finding the height at which the first image's pixel projects
onto its match in the second image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import pyproj

from recon3d.core.pointcloud import PointCloud
from recon3d.errors import InputError
from recon3d.io.rpc import RPCCamera

log = logging.getLogger(__name__)

__all__ = ["SatellitePair", "absolute_shift", "dense_cloud_rpc", "rectify_rpc_pair", "utm_crs"]


@dataclass
class SatellitePair:
    """Two RPC images resampled to a common epipolar geometry.

    Attributes
    ----------
    left, right : (H, W) float32
        Rectified images, NaN outside the originals.
    A1, A2 : (2, 3) float
        Affine maps from crop pixels (col, row) to rectified (x, y).
    heights : (2,) float
        Height interval (ellipsoidal metres) the disparity range covers.
    disparity_range : (2,) int
    parallax : dict
        Residual vertical parallax of SIFT matches (px) after rectification.
    shift : (2,) float
        Relative bias of the second RPC (crop pixels, col and row) removed using tie points.
    """

    left: np.ndarray
    right: np.ndarray
    A1: np.ndarray
    A2: np.ndarray
    heights: tuple[float, float]
    disparity_range: tuple[int, int]
    parallax: dict
    shift: np.ndarray


def utm_crs(lon: float, lat: float) -> pyproj.CRS:
    """The WGS 84 / UTM zone CRS of a point (EPSG 326xx north, 327xx south)."""
    zone = int((lon + 180.0) // 6.0) + 1
    return pyproj.CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


def _correspondences(a: RPCCamera, b: RPCCamera, heights: np.ndarray, n: int = 15):
    """Crop pixels (col, row) of a grid over ``a`` and of the same ground points in ``b``, per height.

    Returns p1 (k, 2), p2 (k, 2) and the height of each pair (k,).
    """
    rows, cols = np.meshgrid(np.linspace(0, a.height - 1, n), np.linspace(0, a.width - 1, n), indexing="ij")
    r, c = rows.ravel(), cols.ravel()
    p1, p2, hh = [], [], []
    for h in heights:
        lon, lat = a.localize(r, c, np.full(r.shape, h))
        r2, c2 = b.project(lon, lat, np.full(r.shape, h))
        ok = np.isfinite(r2) & np.isfinite(c2)
        p1.append(np.column_stack([c[ok], r[ok]]))
        p2.append(np.column_stack([c2[ok], r2[ok]]))
        hh.append(np.full(ok.sum(), h))
    return np.concatenate(p1), np.concatenate(p2), np.concatenate(hh)


def _direction(p_fixed_moving: np.ndarray, n_heights: int) -> np.ndarray:
    """Mean unit direction of the tracks (k, 2) traced as height grows (k = points x heights)."""
    tracks = p_fixed_moving.reshape(n_heights, -1, 2)
    d = (tracks[-1] - tracks[0]).mean(axis=0)
    return d / np.linalg.norm(d)


def rectify_rpc_pair(a: RPCCamera, b: RPCCamera, image_a: np.ndarray, image_b: np.ndarray) -> SatellitePair:
    """Affine epipolar rectification of two RPC crops, with the relative RPC bias removed.

    Raises
    ------
    InputError
        When the crops do not overlap, or the images are the same view (no parallax).
    """
    h0, h1 = a.model.height_range
    heights = np.linspace(h0, h1, 5)
    for cam in (a, b):
        rows = np.array([0, 0, cam.height - 1, cam.height - 1.0])
        cols = np.array([0, cam.width - 1, 0, cam.width - 1.0])
        hm = np.full(4, 0.5 * (h0 + h1))
        lon, lat = cam.localize(rows, cols, hm)
        if not np.all(cam.in_domain(lon, lat, hm)):
            raise InputError(f"image {cam.name}: the crop lies outside its RPC validity domain")
    p1, p2, hh = _correspondences(a, b, heights)
    if len(p1) < 20 or not _overlap(p2, b):
        raise InputError(f"images {a.name} and {b.name}: their footprints do not overlap")
    q2, q1, _ = _correspondences(b, a, heights)
    d2 = _direction(p2, len(heights))  # epipolar direction in b: a's pixel lifted through the heights
    d1 = _direction(q1, len(heights))
    parallax_px = np.linalg.norm(p2.reshape(len(heights), -1, 2)[-1] - p2.reshape(len(heights), -1, 2)[0], axis=1).mean()
    if parallax_px < 2.0:
        raise InputError(
            f"images {a.name} and {b.name}: only {parallax_px:.1f} px of parallax over {h0:.0f}-{h1:.0f} m; "
            "the two images see the ground from the same direction (identical images?)"
        )
    shift = _relative_bias(a, b, image_a, image_b, d2)
    p2 = p2 + shift
    R1 = np.array([d1, [-d1[1], d1[0]]])
    A1 = np.column_stack([R1, np.zeros(2)])
    x1 = p1 @ R1.T
    design = np.column_stack([p2, np.ones(len(p2))])
    y_row = np.linalg.lstsq(design, x1[:, 1], rcond=None)[0]  # same row as in a, for every height
    mid = hh == heights[len(heights) // 2]
    x_row = np.linalg.lstsq(design[mid], x1[mid, 0], rcond=None)[0]  # zero disparity at the middle height
    A2 = np.array([x_row, y_row]) - np.array([[0, 0, shift @ x_row[:2]], [0, 0, shift @ y_row[:2]]])
    A1, A2, size = _frame(A1, A2, a, b)
    left = _warp(image_a, A1, size)
    right = _warp(image_b, A2, size)
    d = _apply(A1, p1)[:, 0] - _apply(A2, p2 - shift)[:, 0]
    lo, hi = np.floor(d.min()) - 4, np.ceil(d.max()) + 4
    parallax = _measure_parallax(left, right)
    log.info("RPC pair %s-%s: disparity %d..%d, vertical parallax %s", a.name, b.name, lo, hi, parallax)
    return SatellitePair(left, right, A1, A2, (h0, h1), (int(lo), int(hi)), parallax, shift)


def _overlap(p2: np.ndarray, b: RPCCamera) -> bool:
    inside = (p2[:, 0] >= 0) & (p2[:, 0] < b.width) & (p2[:, 1] >= 0) & (p2[:, 1] < b.height)
    return inside.mean() > 0.1


def _relative_bias(a: RPCCamera, b: RPCCamera, image_a: np.ndarray, image_b: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Shift (col, row) of b's RPC across the epipolar direction, from SIFT tie points.

    RPCs of one pair disagree by a near-constant offset; only its component across the
    epipolar lines matters for rectification (along them it is a height offset).
    """
    g1, g2 = _to8(image_a), _to8(image_b)
    sift = cv2.SIFT_create(nfeatures=3000)
    k1, s1 = sift.detectAndCompute(g1, None)
    k2, s2 = sift.detectAndCompute(g2, None)
    if s1 is None or s2 is None:
        return np.zeros(2)
    good = [m[0] for m in cv2.BFMatcher(cv2.NORM_L2).knnMatch(s1, s2, k=2) if len(m) == 2 and m[0].distance < 0.7 * m[1].distance]
    if len(good) < 10:
        log.warning("RPC pair %s-%s: %d tie points, no bias correction", a.name, b.name, len(good))
        return np.zeros(2)
    t1 = np.array([k1[m.queryIdx].pt for m in good])
    t2 = np.array([k2[m.trainIdx].pt for m in good])
    mid = float(np.mean(a.model.height_range))
    lon, lat = a.localize(t1[:, 1], t1[:, 0], np.full(len(t1), mid))
    r2, c2 = b.project(lon, lat, np.full(len(t1), mid))
    residual = t2 - np.column_stack([c2, r2])
    across = np.array([-d2[1], d2[0]])
    offsets = residual @ across
    med = np.median(offsets)
    keep = np.abs(offsets - med) < 3.0
    shift = across * float(np.median(offsets[keep]))
    log.info("RPC pair %s-%s: relative bias %.2f px across the epipolar lines (%d tie points)", a.name, b.name, med, keep.sum())
    return shift


def _to8(image: np.ndarray) -> np.ndarray:
    v = image[np.isfinite(image)]
    lo, hi = np.percentile(v, [0.5, 99.5]) if v.size else (0.0, 1.0)
    return np.clip((np.nan_to_num(image, nan=lo) - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)


def _apply(A: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ A[:, :2].T + A[:, 2]


def _frame(A1: np.ndarray, A2: np.ndarray, a: RPCCamera, b: RPCCamera):
    """Translate both maps so the rectified images start at (0, 0) and share rows; output size."""
    corners = lambda cam: np.array([[0, 0], [cam.width - 1, 0], [0, cam.height - 1], [cam.width - 1, cam.height - 1]], float)  # noqa: E731
    c1, c2 = _apply(A1, corners(a)), _apply(A2, corners(b))
    y0 = min(c1[:, 1].min(), c2[:, 1].min())
    y1 = max(c1[:, 1].max(), c2[:, 1].max())
    A1, A2 = A1.copy(), A2.copy()
    A1[:, 2] -= [c1[:, 0].min(), y0]
    A2[:, 2] -= [c2[:, 0].min(), y0]
    width = int(np.ceil(max(np.ptp(c1[:, 0]), np.ptp(c2[:, 0])))) + 1
    return A1, A2, (width, int(np.ceil(y1 - y0)) + 1)


def _warp(image: np.ndarray, A: np.ndarray, size) -> np.ndarray:
    valid = cv2.warpAffine(np.ones(image.shape, np.uint8), A, size, flags=cv2.INTER_NEAREST, borderValue=0)
    out = cv2.warpAffine(image.astype(np.float32), A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out[valid == 0] = np.nan
    return out


def _measure_parallax(left: np.ndarray, right: np.ndarray) -> dict:
    from recon3d.stereo.rectify import measure_parallax

    return measure_parallax(_to8(left), _to8(right))


def dense_cloud_rpc(a: RPCCamera, b: RPCCamera, image_a: np.ndarray, image_b: np.ndarray) -> tuple[PointCloud, dict]:
    """Rectify, match and intersect an RPC pair into a cloud in the UTM zone of the scene.

    Returns
    -------
    cloud : PointCloud
        x, y in WGS 84 / UTM (metres), z ellipsoidal height (metres); ``quality``.
    report : dict
        Bias, residual vertical parallax, disparity range, density.
    """
    from recon3d.stereo.match import MatchParams, match

    pair = rectify_rpc_pair(a, b, image_a, image_b)
    lo, hi = pair.disparity_range
    result = match(pair.left, pair.right, MatchParams(min_disparity=lo, max_disparity=hi + 1))
    y, x = np.nonzero(np.isfinite(result.disparity))
    d = result.disparity[y, x]
    p1 = _apply(_invert(pair.A1), np.column_stack([x, y]).astype(float))
    p2 = _apply(_invert(pair.A2), np.column_stack([x - d, y]).astype(float)) - pair.shift
    inside = (p1[:, 0] >= 0) & (p1[:, 0] <= a.width - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= a.height - 1)
    p1, p2, conf = p1[inside], p2[inside], result.confidence[y[inside], x[inside]]
    h = _intersect(a, b, p1, p2, *pair.heights)
    lon, lat = a.localize(p1[:, 1], p1[:, 0], h)
    ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h)
    crs = utm_crs(float(np.nanmedian(lon)), float(np.nanmedian(lat)))
    east, north = pyproj.Transformer.from_crs(4326, crs, always_xy=True).transform(lon[ok], lat[ok])
    cloud = PointCloud(np.column_stack([east, north, h[ok]]), {"quality": conf[ok].astype(np.float32)}, crs)
    report = {
        "relative_bias_px": np.round(pair.shift, 3).tolist(),
        "vertical_parallax_px": pair.parallax,
        "disparity_range": list(pair.disparity_range),
        "height_interval_m": list(pair.heights),
        "matched_percent": result.params.get("matched_percent"),
        "points": len(cloud),
        "heights": "ellipsoidal (WGS 84), as the RPCs give them",
    }
    return cloud, report


def _invert(A: np.ndarray) -> np.ndarray:
    M = np.linalg.inv(A[:, :2])
    return np.column_stack([M, -M @ A[:, 2]])


def _intersect(a: RPCCamera, b: RPCCamera, p1: np.ndarray, p2: np.ndarray, h0: float, h1: float, steps: int = 2) -> np.ndarray:
    """Height at which a's pixel p1 projects onto b's pixel p2 (secant steps along the epipolar line)."""
    ha = np.full(len(p1), h0)
    hb = np.full(len(p1), h1)
    for _ in range(steps + 1):
        qa = _lift(a, b, p1, ha)
        qb = _lift(a, b, p1, hb)
        dq = qb - qa
        t = np.einsum("ij,ij->i", p2 - qa, dq) / np.maximum(np.einsum("ij,ij->i", dq, dq), 1e-12)
        h = ha + t * (hb - ha)
        ha, hb = h - 2.0, h + 2.0
    return h


def _lift(a: RPCCamera, b: RPCCamera, p1: np.ndarray, h: np.ndarray) -> np.ndarray:
    lon, lat = a.localize(p1[:, 1], p1[:, 0], h)
    r, c = b.project(lon, lat, h)
    return np.column_stack([c, r])


def absolute_shift(cloud: PointCloud, gcps: np.ndarray, *, search: float = 5.0, step: float = 0.5) -> tuple[np.ndarray, dict]:
    """Translation that brings the cloud onto ground control points (the RPCs' absolute bias).

    An RPC pair's absolute error is close to a constant shift on the ground. With 3-D
    control points only (no image measurements), the horizontal part is found by
    sliding the points over the cloud's surface (median height per 1 m column, a grid
    search within ``search`` metres) to the position where the height residuals agree
    best; the vertical part is then their median. Points on sloped or built ground
    carry the horizontal information; on flat ground only the height is recovered.

    Parameters
    ----------
    cloud : PointCloud
        Metric CRS.
    gcps : (m, 3) float
        Control points in the cloud's CRS.

    Returns
    -------
    shift : (3,) float
        To add to the cloud's coordinates.
    report : dict
    """
    from recon3d.core.raster import Raster, grid_for_bounds
    from recon3d.terrain.dsm import grid_points

    if len(gcps) < 3:
        raise InputError(f"{len(gcps)} ground control points; at least 3 are needed to estimate the bias")
    lo, hi = cloud.bounds
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], 1.0)
    surface = Raster(grid_points(cloud.xyz, transform, shape, reducer="mean"), transform)
    offsets = np.arange(-search, search + step / 2, step)
    best = (np.inf, 0.0, 0.0, 0.0)
    for dx in offsets:  # a small grid of shifts, each vectorised over the points
        for dy in offsets:
            dz = gcps[:, 2] - surface.sample(gcps[:, 0] - dx, gcps[:, 1] - dy)
            ok = np.isfinite(dz)
            if ok.sum() < 3:
                continue
            med = float(np.median(dz[ok]))
            spread = float(np.median(np.abs(dz[ok] - med)))
            if spread < best[0] - 1e-9:
                best = (spread, dx, dy, med)
    if not np.isfinite(best[0]):
        raise InputError("the ground control points do not fall on the reconstructed surface")
    shift = np.array(best[1:])
    report = {"shift_m": np.round(shift, 3).tolist(), "residual_mad_m": round(best[0], 3), "gcps": int(len(gcps))}
    log.info("absolute bias from %d GCPs: %s m", len(gcps), report["shift_m"])
    return shift, report
