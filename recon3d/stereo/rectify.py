"""Choosing stereo pairs and rectifying them to epipolar geometry (OpenCV).

After rectification corresponding points share an image row: the left-image disparity
d = x_left - x_right is all that remains to find. The residual vertical parallax of
SIFT matches measures how well that holds; a pair above 1 px is refused.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from recon3d.core.camera import Camera
from recon3d.errors import InputError

log = logging.getLogger(__name__)

__all__ = ["RectifiedPair", "disparity_range", "rectify_pair", "select_pairs"]

#: Largest residual vertical parallax (median, pixels) accepted after rectification.
MAX_PARALLAX_PX = 1.0


@dataclass
class RectifiedPair:
    """Two images resampled so that epipolar lines are image rows.

    Attributes
    ----------
    left, right : (H, W) uint8
        Rectified grey images; ``left`` sees its match at x - d in ``right``.
    color : (H, W, 3) uint8
        The rectified left image in colour (RGB), for point colours.
    valid_left, valid_right : (H, W) bool
        Pixels that fall inside the original images.
    camera_left, camera_right : Camera
    R1 : (3, 3) float
        Rotation from the left camera frame to the rectified frame.
    P1, P2 : (3, 4) float
        Projection matrices of the rectified views (rectified frame of the left camera).
    Q : (4, 4) float
        Disparity-to-depth matrix (``cv2.reprojectImageTo3D``).
    parallax : dict
        Residual vertical parallax of feature matches: median, p90, count (pixels).
    """

    left: np.ndarray
    right: np.ndarray
    color: np.ndarray
    valid_left: np.ndarray
    valid_right: np.ndarray
    camera_left: Camera
    camera_right: Camera
    R1: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    parallax: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.camera_left.name}-{self.camera_right.name}"

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified left and right pixel coordinates, (n, 2) each, of (n, 3) model points."""
        cam = np.asarray(xyz) @ self.camera_left.R.T + self.camera_left.t
        rect = np.column_stack([cam @ self.R1.T, np.ones(len(cam))])
        uvl = rect @ self.P1.T
        uvr = rect @ self.P2.T
        with np.errstate(divide="ignore", invalid="ignore"):
            return uvl[:, :2] / uvl[:, 2:], uvr[:, :2] / uvr[:, 2:]


def select_pairs(
    cameras: list[Camera], sparse: np.ndarray, *, min_ratio: float = 0.08, max_ratio: float = 2.0, min_overlap: float = 0.2
) -> tuple[list[tuple[int, int]], list[dict]]:
    """Image pairs with enough common ground and a usable base-to-height ratio.

    The overlap is the share of sparse points seen by one image that the other sees
    too; the height is the median depth of those points.

    Returns
    -------
    pairs : list of (i, j)
        Indices into ``cameras``, left-to-right order fixed later by rectification.
    report : list of dict
        Every candidate pair with its ratio, overlap and verdict (for run.json).

    Raises
    ------
    InputError
        When no pair qualifies; the message lists the candidates.
    """
    visible = [_inside(c, sparse) for c in cameras]
    pairs, report = [], []
    for i, j in itertools.combinations(range(len(cameras)), 2):
        a, b = cameras[i], cameras[j]
        both = visible[i] & visible[j]
        overlap = both.sum() / max(1, min(visible[i].sum(), visible[j].sum()))
        depth = np.median(a.project(sparse[both])[1]) if both.any() else np.nan
        ratio = float(np.linalg.norm(a.center - b.center) / depth) if both.any() else 0.0
        ok = overlap >= min_overlap and min_ratio <= ratio <= max_ratio
        report.append({"pair": f"{a.name}-{b.name}", "base_to_height": round(ratio, 3),
                       "overlap": round(float(overlap), 3), "used": bool(ok)})
        if ok:
            pairs.append((i, j))
    if not pairs:
        lines = "; ".join(f"{r['pair']}: overlap {r['overlap']:.0%}, B/H {r['base_to_height']:.2f}" for r in report)
        raise InputError(
            f"no image pair overlaps with a usable base-to-height ratio ({min_ratio}-{max_ratio}, "
            f"overlap >= {min_overlap:.0%}): {lines}"
        )
    return pairs, report


def _inside(camera: Camera, xyz: np.ndarray) -> np.ndarray:
    uv, depth = camera.project(xyz)
    return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)


def rectify_pair(
    a: Camera, b: Camera, image_a: np.ndarray, image_b: np.ndarray, *, max_parallax: float = MAX_PARALLAX_PX
) -> RectifiedPair:
    """Undistort and rectify two images from their known relative pose.

    The camera that ends up on the left (its matches shifted towards smaller x in the
    other image) comes first in the result whatever the input order.

    A baseline along the image columns (forward overlap) is handled by turning both
    images and cameras 90 degrees first; the result's cameras are the turned ones.

    Raises
    ------
    InputError
        A residual vertical parallax above ``max_parallax``.
    """
    R, T = _relative_pose(a, b)
    if abs(T[1]) > abs(T[0]):  # baseline along the columns (forward overlap): turn both views
        rot = cv2.ROTATE_90_CLOCKWISE
        return rectify_pair(
            a.rotated_clockwise(), b.rotated_clockwise(), cv2.rotate(image_a, rot), cv2.rotate(image_b, rot),
            max_parallax=max_parallax,
        )
    if T[0] > 0:  # b lies to the left of a: swap so that disparities are positive
        return rectify_pair(b, a, image_b, image_a, max_parallax=max_parallax)
    size = (a.width, a.height)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
        a.K, a.dist.reshape(1, 5), b.K, b.dist.reshape(1, 5), size, R, T.reshape(3, 1),
        flags=0, alpha=0,  # principal points may differ: convergent views keep their overlap
    )
    left, color, valid_left = _remap(image_a, a, R1, P1, size)
    right, _, valid_right = _remap(image_b, b, R2, P2, size)
    pair = RectifiedPair(left, right, color, valid_left, valid_right, a, b, R1, P1, P2, Q)
    pair.parallax = measure_parallax(left, right)
    if pair.parallax["n"] >= 20 and pair.parallax["median"] > max_parallax:
        raise InputError(
            f"images {a.name} and {b.name}: residual vertical parallax {pair.parallax['median']:.2f} px "
            f"after rectification exceeds {max_parallax} px; the orientations do not fit the images"
        )
    return pair


def _relative_pose(a: Camera, b: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of camera b relative to camera a (x_b = R x_a + T)."""
    R = b.R @ a.R.T
    return R, b.t - R @ a.t


def _remap(image: np.ndarray, cam: Camera, Rr: np.ndarray, P: np.ndarray, size):
    map1, map2 = cv2.initUndistortRectifyMap(cam.K, cam.dist, Rr, P, size, cv2.CV_32FC1)
    color = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    color = cv2.remap(color, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    gray = cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)
    ones = np.full(image.shape[:2], 255, np.uint8)
    valid = cv2.remap(ones, map1, map2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0
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


def disparity_range(pair: RectifiedPair, sparse: np.ndarray, *, max_count: int = 256) -> tuple[int, int, str]:
    """Disparity search range from the sparse points seen in both rectified images.

    The 1st to 99th percentile of their disparities, widened by 10 % and 8 px; at most
    ``max_count`` disparities, so the cost volume stays bounded.

    Returns
    -------
    min_disparity, max_disparity : int
    reason : str
    """
    uvl, uvr = pair.project(sparse)
    h, w = pair.left.shape
    seen = (
        np.isfinite(uvl).all(axis=1) & np.isfinite(uvr).all(axis=1)
        & (uvl[:, 0] >= 0) & (uvl[:, 0] < w) & (uvl[:, 1] >= 0) & (uvl[:, 1] < h)
        & (uvr[:, 0] >= 0) & (uvr[:, 0] < w)
    )
    if seen.sum() < 3:
        raise InputError(f"images {pair.name}: fewer than 3 sparse points seen by both; cannot bound the disparities")
    d = uvl[seen, 0] - uvr[seen, 0]
    lo, hi = np.percentile(d, [1, 99])
    margin = 0.1 * (hi - lo) + 8.0
    dmin, dmax = int(np.floor(lo - margin)), int(np.ceil(hi + margin))
    reason = f"{seen.sum()} sparse points: disparities {lo:.1f}..{hi:.1f} px, widened by {margin:.1f} px"
    if dmax - dmin > max_count:
        centre = (dmin + dmax) // 2
        dmin, dmax = centre - max_count // 2, centre + max_count // 2
        reason += f"; capped at {max_count} disparities"
        log.warning("images %s: disparity range capped at %d", pair.name, max_count)
    return dmin, dmax, reason
