"""Choosing stereo pairs and rectifying them to epipolar geometry.

After rectification corresponding points share an image row: the left-image disparity
d = x_left - x_right is all that remains to find.

The rectification is computed here rather than by ``cv2.stereoRectify``, whose
``alpha`` crops either the common area (``alpha=0`` keeps only pixels valid in both
views, losing a side of a 55 % overlap) or nothing, and which puts the principal points
where the disparity search must first cross hundreds of pixels of constant offset.
Here (Fusiello, Trucco and Verri 2000):

1. both views turn to one orientation: x along the baseline (from the left camera to
   the right one), z the mean of the two optical axes made orthogonal to it, so any
   heading, base direction (along the image rows, the columns or diagonal) and attitude
   works without special cases;
2. the common focal length is the mean of the cameras' (no resolution lost);
3. the rectified images are cut to the part of the left view whose match can lie in
   the right view for the scene's depths (the sparse points' disparities, widened), and
   the right view is shifted by the median disparity of those points, so the searched
   disparities are centred on 0 and span the scene's depth range only.

Every sparse point seen by both images therefore lands in both rectified images. The
residual vertical parallax of SIFT matches measures how well the orientation fits the
images; a pair above 1 px is refused.
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import shapely
import shapely.affinity

from recon3d.core.camera import Camera
from recon3d.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["MAX_PARALLAX_PX", "RectifiedPair", "measure_parallax", "rectify_pair", "sample_extremes", "select_pairs"]

#: Largest residual vertical parallax (median, pixels) accepted after rectification.
MAX_PARALLAX_PX = 1.0

#: Share of the sparse disparity spread, and pixels, added on both sides of the range.
RANGE_MARGIN = (0.15, 8.0)
#: Share of the pair's sparse height span added above the highest sparse point when
#: the range is raised to cover a tower taller than every sampled roof (see
#: :func:`rectify_pair`'s ``top``).
TOP_MARGIN = 0.25


@dataclass
class RectifiedPair:
    """Two images resampled so that epipolar lines are image rows.

    Both rectified views share one orientation ``rotation`` and focal length; their
    principal points differ along x by ``offset``, the disparity of a point at
    infinity. A left pixel (x, y) of disparity d sees the point at depth
    ``focal * baseline / (d - offset)`` along the rectified z axis.

    Attributes
    ----------
    left, right : (H, W) uint8
        Rectified grey images; ``left`` sees its match at x - d in ``right``.
    color : (H, W, 3) uint8
        The rectified left image in colour (RGB), for point colours.
    valid_left, valid_right : (H, W) bool
        Pixels that fall inside the original images.
    camera_left, camera_right : Camera
    rotation : (3, 3) float
        World (model) to rectified frame, shared by both views.
    focal : float
        Focal length of both rectified views (pixels).
    cx_left, cx_right, cy : float
        Principal points of the rectified views (OpenCV pixel convention).
    baseline : float
        Distance between the projection centres (model units).
    disparity_range : (int, int)
        Disparities ``lo <= d < hi`` the scene's depths can give (sparse points, widened).
    range_reason : str
    parallax : dict
        Residual vertical parallax of feature matches: median, p90, count (pixels).
    resampled : dict
        Where the rectified pixels were sampled from in the originals, every ``"step"``
        pixels (``"left"``, ``"right"``: (rows, cols, 2) float64), fixed when the images
        were resampled: :meth:`to_original` reads it, so a later change of the pair's
        parameters shows as a reprojection error instead of passing unseen.
    color_right : (H, W, 3) uint8 or None
        The rectified right image in colour (RGB), for the matcher's colour tests
        (``MatchParams.sharpen_steps``).
    """

    left: np.ndarray
    right: np.ndarray
    color: np.ndarray
    valid_left: np.ndarray
    valid_right: np.ndarray
    camera_left: Camera
    camera_right: Camera
    rotation: np.ndarray
    focal: float
    cx_left: float
    cx_right: float
    cy: float
    baseline: float
    disparity_range: tuple[int, int] = (0, 1)
    range_reason: str = ""
    parallax: dict = field(default_factory=dict)
    resampled: dict = field(default_factory=dict)
    color_right: np.ndarray | None = None

    @property
    def name(self) -> str:
        return f"{self.camera_left.name}-{self.camera_right.name}"

    @property
    def offset(self) -> float:
        """Disparity of a point at infinity, ``cx_left - cx_right`` (pixels)."""
        return self.cx_left - self.cx_right

    @property
    def R1(self) -> np.ndarray:
        """(3, 3) left camera frame to rectified frame (OpenCV's ``R1``)."""
        return self.rotation @ self.camera_left.R.T

    @property
    def R2(self) -> np.ndarray:
        """(3, 3) right camera frame to rectified frame (OpenCV's ``R2``)."""
        return self.rotation @ self.camera_right.R.T

    @property
    def P1(self) -> np.ndarray:
        """(3, 4) projection of the rectified left view, rectified frame of the left camera."""
        return np.array([[self.focal, 0, self.cx_left, 0], [0, self.focal, self.cy, 0], [0, 0, 1, 0]], float)

    @property
    def P2(self) -> np.ndarray:
        """(3, 4) projection of the rectified right view, rectified frame of the left camera."""
        fb = self.focal * self.baseline
        return np.array([[self.focal, 0, self.cx_right, -fb], [0, self.focal, self.cy, 0], [0, 0, 1, 0]], float)

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified left and right pixel coordinates, (n, 2) each, of (n, 3) model points."""
        p = (np.asarray(xyz, np.float64) - self.camera_left.center) @ self.rotation.T
        with np.errstate(divide="ignore", invalid="ignore"):
            y = self.focal * p[:, 1] / p[:, 2] + self.cy
            xl = self.focal * p[:, 0] / p[:, 2] + self.cx_left
            xr = self.focal * (p[:, 0] - self.baseline) / p[:, 2] + self.cx_right
        return np.column_stack([xl, y]), np.column_stack([xr, y])

    def triangulate(self, x: np.ndarray, y: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(n, 3) model points of left pixels (x, y) with disparities d, (n,) each.

        Rows are shared, so the two rays meet exactly; disparities at or below
        ``offset`` (at or beyond infinity) give NaN.
        """
        x, y, d = (np.asarray(v, np.float64) for v in (x, y, d))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(d > self.offset, self.focal * self.baseline / (d - self.offset), np.nan)
        rect = np.column_stack([(x - self.cx_left) * z / self.focal, (y - self.cy) * z / self.focal, z])
        return rect @ self.rotation + self.camera_left.center

    def depth_to_disparity(self, depth: np.ndarray) -> np.ndarray:
        """Disparity of points at rectified depths ``depth`` (any shape)."""
        return self.focal * self.baseline / np.asarray(depth, np.float64) + self.offset

    def to_rectified(self, uv: np.ndarray, *, right: bool = False) -> np.ndarray:
        """(n, 2) rectified pixel coordinates of (n, 2) pixels of the original (distorted) image.

        The inverse of :meth:`to_original` (``cv2.undistortPoints``).
        """
        cam = self.camera_right if right else self.camera_left
        cx = self.cx_right if right else self.cx_left
        P = np.array([[self.focal, 0, cx], [0, self.focal, self.cy], [0, 0, 1]], float)
        uv = np.asarray(uv, np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(uv, cam.K, cam.dist, R=self.R2 if right else self.R1, P=P).reshape(-1, 2)

    def to_original(self, xy: np.ndarray, *, right: bool = False) -> np.ndarray:
        """(n, 2) pixel coordinates in the original (distorted) image of rectified pixels (n, 2).

        The mapping the images were resampled with (``cv2.initUndistortRectifyMap``),
        interpolated from :attr:`resampled` (within 0.001 px), or computed from the
        pair's parameters when the pair was built by hand.
        """
        grid = self.resampled.get("right" if right else "left")
        if grid is None:
            return self._project_to_original(xy, right=right)
        from scipy.ndimage import map_coordinates

        q = np.asarray(xy, np.float64) / self.resampled["step"]
        coords = [q[:, 1], q[:, 0]]
        return np.column_stack([map_coordinates(grid[..., k], coords, order=1, mode="nearest") for k in (0, 1)])

    def _project_to_original(self, xy: np.ndarray, *, right: bool = False) -> np.ndarray:
        cam = self.camera_right if right else self.camera_left
        cx = self.cx_right if right else self.cx_left
        xy = np.asarray(xy, np.float64)
        rays = np.column_stack([(xy[:, 0] - cx) / self.focal, (xy[:, 1] - self.cy) / self.focal, np.ones(len(xy))])
        in_camera = rays @ (self.R2 if right else self.R1)  # rectified to camera frame
        uv, _ = cv2.projectPoints(in_camera.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
        return uv.reshape(-1, 2)

    def freeze_resampling(self, step: int = 8) -> None:
        """Record :attr:`resampled` from the current parameters (when the images are resampled)."""
        h, w = self.left.shape
        gy, gx = np.meshgrid(np.arange(0, h + step, step, dtype=np.float64), np.arange(0, w + step, step, dtype=np.float64), indexing="ij")
        xy = np.column_stack([gx.ravel(), gy.ravel()])
        self.resampled = {"step": step} | {
            side: self._project_to_original(xy, right=side == "right").reshape(*gx.shape, 2)
            for side in ("left", "right")
        }


# --------------------------------------------------------------------------- pairs


def select_pairs(
    cameras: list[Camera],
    sparse: np.ndarray,
    seen: np.ndarray | None = None,
    *,
    min_ratio: float = 0.08,
    max_ratio: float = 2.0,
    min_overlap: float = 0.2,
    min_points: int = 10,
    max_partners: int | None = None,
) -> tuple[list[tuple[int, int]], list[dict]]:
    """Image pairs with enough common ground and a usable base-to-height ratio.

    The overlap is the share of the sparse points one image observes that the other
    observes too (their COLMAP tracks; without tracks, the points inside both frames);
    the height is the median depth of those points. With ``max_partners``, a usable pair
    is kept when it is among the best ``max_partners`` of either of its images, by common
    sparse points times min(1, base-to-height / 0.3) (a narrow base measures depth less
    well): a block's pairs then grow with its images, not with their square.

    Parameters
    ----------
    cameras : list of Camera
    sparse : (n, 3) float
        Sparse points, model coordinates.
    seen : (len(cameras), n) bool, optional
        Which cameras observe each point.

    Returns
    -------
    pairs : list of (i, j)
        Indices into ``cameras``.
    report : list of dict
        Every candidate pair with its ratio, overlap and verdict (for run.json).

    Raises
    ------
    InputError
        When no pair qualifies; the message lists the candidates.
    """
    visible = seen if seen is not None else np.stack([_inside(c, sparse) for c in cameras])
    pairs, report, score = [], [], {}
    for i, j in itertools.combinations(range(len(cameras)), 2):
        a, b = cameras[i], cameras[j]
        both = visible[i] & visible[j]
        overlap = both.sum() / max(1, min(visible[i].sum(), visible[j].sum()))
        depth = float(np.median(a.project(sparse[both])[1])) if both.any() else np.nan
        base = b.center - a.center
        ratio = float(np.linalg.norm(base) / depth) if both.any() else 0.0
        axis = a.viewing_direction + b.viewing_direction
        along_view = abs(float(base @ axis)) / max(1e-12, float(np.linalg.norm(base) * np.linalg.norm(axis)))
        why = ""
        if both.sum() < min_points:
            why = f"{int(both.sum())} common sparse points"
        elif overlap < min_overlap:
            why = f"overlap {overlap:.0%}"
        elif not min_ratio <= ratio <= max_ratio:
            why = f"base-to-height {ratio:.2f}"
        elif along_view > 0.7:
            why = "base along the viewing direction"
        report.append({
            "pair": f"{a.name}-{b.name}", "base_to_height": round(ratio, 3), "overlap": round(float(overlap), 3),
            "common_points": int(both.sum()), "used": not why, **({"refused": why} if why else {}),
        })
        if not why:
            pairs.append((i, j))
            score[(i, j)] = float(both.sum()) * min(1.0, ratio / 0.3)
    if max_partners is not None and pairs:
        best = {k: sorted((p for p in pairs if k in p), key=lambda p: -score[p])[:max_partners] for k in range(len(cameras))}
        kept = [p for p in pairs if p in best[p[0]] or p in best[p[1]]]
        for r, p in zip([r for r in report if r["used"]], pairs, strict=True):
            if p not in kept:
                r.update(used=False, refused=f"not among the {max_partners} best partners of either image")
        pairs = kept
    if not pairs:
        lines = "; ".join(f"{r['pair']}: {r.get('refused', '')}" for r in report)
        raise InputError(
            f"no image pair sees the same ground with a usable base-to-height ratio ({min_ratio}-{max_ratio}, "
            f"overlap >= {min_overlap:.0%}, at least {min_points} common sparse points): {lines}"
        )
    return pairs, report


def _inside(camera: Camera, xyz: np.ndarray) -> np.ndarray:
    uv, depth = camera.project(xyz, distort=True)  # the photo as taken, lens and all
    return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)


# --------------------------------------------------------------------------- rectification


def rectify_pair(
    a: Camera,
    b: Camera,
    image_a: np.ndarray,
    image_b: np.ndarray,
    points: np.ndarray,
    *,
    max_parallax: float = MAX_PARALLAX_PX,
    max_disparities: int = 384,
    top: float | None = None,
) -> RectifiedPair:
    """Undistort and rectify two images from their known orientation.

    ``a`` is the left view: its rectified x axis points from ``a``'s projection centre
    to ``b``'s, so disparities are positive whatever the base direction.

    Parameters
    ----------
    a, b : Camera
    image_a, image_b : (h, w, 3) or (h, w) uint8
        The images as read (BGR or grey).
    points : (n, 3) float
        Model points both images see (the sparse points of both tracks): they bound
        the scene's depths and so the searched disparities and the rectified extent.
    max_parallax : float
        Largest median residual vertical parallax of SIFT matches (pixels).
    max_disparities : int
        Widest disparity range; a wider one is cut around the points' median.
    top : float, optional
        Height (model z, up) the scene's surface may reach, such as the highest sparse
        point of the whole block (:func:`sample_extremes`). The range then also covers every point raised to
        ``max(top, highest of points) + TOP_MARGIN * their height span``: a sparse
        model samples roofs by chance, and a tower taller than every sampled roof of
        the pair lies beyond their disparities (on random surveys of the synthetic
        family, 0.6-3 % of a pair's pixels, whole buildings matched as ground). The
        raised part is cut first when the range is too wide.

    Raises
    ------
    InputError
        Fewer than 3 points, no common ground in front of both cameras, or a residual
        vertical parallax above ``max_parallax``.
    """
    name = f"images {a.name} and {b.name}"
    rotation, baseline = _common_orientation(a, b)
    focal = float(np.mean([a.K[0, 0], a.K[1, 1], b.K[0, 0], b.K[1, 1]]))
    points = np.asarray(points, np.float64).reshape(-1, 3)
    depth = (points - a.center) @ rotation[2]
    points = points[depth > 0]
    if len(points) < 3:
        raise InputError(f"{name}: fewer than 3 sparse points seen by both; cannot bound the disparities")
    raw = focal * baseline / ((points - a.center) @ rotation[2])  # disparity with principal points at 0
    lo, hi, reason = _widened_range(raw, max_disparities, name)
    if top is not None:
        hi, reason = _raised_top(points, a.center, rotation, focal * baseline, top, lo, hi, max_disparities, reason)
    left_area = _rectified_outline(a, rotation, focal)
    right_area = _rectified_outline(b, rotation, focal)
    reach = shapely.convex_hull(shapely.union(
        shapely.affinity.translate(right_area, lo), shapely.affinity.translate(right_area, hi)
    ))
    common = left_area.intersection(reach)
    if common.is_empty or common.area < 1.0:
        raise InputError(f"{name}: the two images do not see the same ground (no common area for the sparse points' depths)")
    u0, v0, u1, v1 = common.bounds
    shift = int(round(float(np.median(raw))))
    pad_lo, pad_hi = math.ceil(hi - shift), math.ceil(shift - lo)
    left0 = math.floor(u0) - pad_lo
    width = math.ceil(u1) - math.floor(u0) + pad_lo + pad_hi + 1
    height = math.ceil(v1) - math.floor(v0) + 1
    cx_left, cy = float(-left0), float(-math.floor(v0))
    cx_right = cx_left + shift
    size = (width, height)
    left, color, valid_left = _remap(image_a, a, rotation, focal, cx_left, cy, size)
    right, color_right, valid_right = _remap(image_b, b, rotation, focal, cx_right, cy, size)
    d_lo, d_hi = math.floor(lo - shift), math.ceil(hi - shift) + 1
    pair = RectifiedPair(
        left, right, color, valid_left, valid_right, a, b, rotation, focal, cx_left, cx_right, cy, baseline,
        (d_lo, d_hi), reason, color_right=color_right,
    )
    pair.freeze_resampling()
    pair.parallax = measure_parallax(left, right)
    log.info(
        "%s rectified to %d x %d px (originals %d x %d, %d x %d); disparities [%d, %d), shift %d px",
        name, width, height, a.width, a.height, b.width, b.height, d_lo, d_hi, shift,
    )
    if pair.parallax["n"] >= 20 and pair.parallax["median"] > max_parallax:
        raise InputError(
            f"{name}: residual vertical parallax {pair.parallax['median']:.2f} px "
            f"after rectification exceeds {max_parallax} px; the orientations do not fit the images"
        )
    return pair


def _common_orientation(a: Camera, b: Camera) -> tuple[np.ndarray, float]:
    """World-to-rectified rotation (rows x, y, z) and the baseline length."""
    x = b.center - a.center
    baseline = float(np.linalg.norm(x))
    if baseline <= 0:
        raise InputError(f"images {a.name} and {b.name} share their projection centre: no stereo base")
    x /= baseline
    z = a.viewing_direction + b.viewing_direction
    z = z - (z @ x) * x
    if np.linalg.norm(z) < 1e-6:
        raise InputError(f"images {a.name} and {b.name}: the base lies along the viewing direction")
    z /= np.linalg.norm(z)
    return np.stack([x, np.cross(z, x), z]), baseline


def _rectified_outline(cam: Camera, rotation: np.ndarray, focal: float, n: int = 32) -> shapely.Polygon:
    """The image border in rectified coordinates with the principal point at (0, 0)."""
    w, h = cam.width - 0.5, cam.height - 0.5
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    border = np.concatenate([
        np.column_stack([-0.5 + t * (w + 0.5), np.full(n, -0.5)]),
        np.column_stack([np.full(n, w), -0.5 + t * (h + 0.5)]),
        np.column_stack([w - t * (w + 0.5), np.full(n, h)]),
        np.column_stack([np.full(n, -0.5), h - t * (h + 0.5)]),
    ])
    P = np.array([[focal, 0, 0], [0, focal, 0], [0, 0, 1]], float)
    uv = cv2.undistortPoints(border.reshape(-1, 1, 2), cam.K, cam.dist, R=rotation @ cam.R.T, P=P).reshape(-1, 2)
    return shapely.Polygon(uv).buffer(0)


def sample_extremes(values: np.ndarray) -> tuple[float, float]:
    """Lowest and highest of a sparse sample, (n,) float: its 0.5th and 99.5th
    percentiles from 50 values on (one stray point does not set them), else its min
    and max."""
    lo, hi = np.percentile(values, [0.5, 99.5]) if len(values) >= 50 else (values.min(), values.max())
    return float(lo), float(hi)


def _widened_range(raw: np.ndarray, max_count: int, name: str) -> tuple[float, float, str]:
    """Disparity range (raw, principal points at 0) from the points' disparities."""
    lo, hi = sample_extremes(raw)
    margin = RANGE_MARGIN[0] * (hi - lo) + RANGE_MARGIN[1]
    reason = f"{len(raw)} sparse points: disparities spread {hi - lo:.1f} px, widened by {margin:.1f} px on each side"
    lo, hi = lo - margin, hi + margin
    if hi - lo > max_count:
        mid = float(np.median(raw))
        lo, hi = max(lo, mid - max_count / 2), min(hi, mid + max_count / 2)
        reason += f"; capped at {max_count} disparities"
        log.warning("%s: disparity range capped at %d (stereo.max_disparities)", name, max_count)
    return float(lo), float(hi), reason


def _raised_top(points, center, rotation, fb: float, top: float, lo: float, hi: float, max_count: int,
                reason: str) -> tuple[float, str]:
    """Upper end of the range (raw disparity) raised to cover the points lifted to the
    scene's top plus :data:`TOP_MARGIN` of their height span, within ``max_count``."""
    z = points[:, 2]
    z_lo, z_hi = sample_extremes(z)
    ceiling = max(top, z_hi) + TOP_MARGIN * (z_hi - z_lo)
    raised = points.copy()
    raised[:, 2] = np.maximum(z, ceiling)
    depth = (raised - center) @ rotation[2]
    depth = depth[depth > 0]
    if not depth.size:
        return hi, reason
    reach = min(float((fb / depth).max()), lo + max_count)
    if reach <= hi:
        return hi, reason
    return reach, reason + (f"; raised by {reach - hi:.1f} px to reach surfaces {ceiling - z_hi:.1f} (CRS units) "
                            "above the pair's highest sparse point (the block's highest, plus a margin)")


def _remap(image: np.ndarray, cam: Camera, rotation, focal, cx, cy, size):
    """Grey and RGB rectified image, and the mask of pixels inside the original."""
    P = np.array([[focal, 0, cx], [0, focal, cy], [0, 0, 1]], float)
    map1, map2 = cv2.initUndistortRectifyMap(cam.K, cam.dist, rotation @ cam.R.T, P, size, cv2.CV_32FC1)
    color = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    color = cv2.remap(color, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    gray = cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)
    h, w = image.shape[:2]
    # every bilinear tap inside the photo: no black border blended into the edge pixels
    valid = (map1 >= 0) & (map1 <= w - 1) & (map2 >= 0) & (map2 <= h - 1)
    return gray, cv2.cvtColor(color, cv2.COLOR_BGR2RGB), valid


def measure_parallax(left: np.ndarray, right: np.ndarray, *, max_features: int = 4000) -> dict:
    """Vertical parallax of SIFT matches (Lowe ratio 0.75) between rectified images.

    Returns ``{"median", "p90", "rms", "n"}`` in pixels over matches within 4 px of
    the same row (others are mismatches, counted in ``"rejected"``).
    """
    sift = cv2.SIFT_create(nfeatures=max_features)
    ka, da = sift.detectAndCompute(left, None)
    kb, db = sift.detectAndCompute(right, None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return {"median": float("nan"), "p90": float("nan"), "rms": float("nan"), "n": 0, "rejected": 0}
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in matches if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
    pa = np.array([ka[m.queryIdx].pt for m in good]).reshape(-1, 2)
    pb = np.array([kb[m.trainIdx].pt for m in good]).reshape(-1, 2)
    dy = np.abs(pa[:, 1] - pb[:, 1])
    keep = dy <= 4.0
    v = dy[keep]
    if v.size == 0:
        return {"median": float("inf"), "p90": float("inf"), "rms": float("inf"), "n": 0, "rejected": int(dy.size)}
    return {
        "median": round(float(np.median(v)), 3),
        "p90": round(float(np.percentile(v, 90)), 3),
        "rms": round(float(np.sqrt(np.mean(v**2))), 3),
        "n": int(v.size),
        "rejected": int((~keep).sum()),
    }
