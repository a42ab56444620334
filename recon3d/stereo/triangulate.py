"""From a disparity map to 3-D points in model coordinates, with a quality per point."""

from __future__ import annotations

import numpy as np

from recon3d.core.pointcloud import PointCloud
from recon3d.stereo.rectify import RectifiedPair

__all__ = ["triangulate"]


def triangulate(
    pair: RectifiedPair, disparity: np.ndarray, confidence: np.ndarray, *, min_angle_deg: float = 1.0,
    guessed: np.ndarray | None = None,
    consistent: np.ndarray | None = None,
) -> PointCloud:
    """Intersect the rays of every valid disparity.

    Parameters
    ----------
    pair : RectifiedPair
    disparity : (H, W) float
        Left-image disparity, NaN where invalid.
    confidence : (H, W) float
        Matching confidence in [0, 1].
    min_angle_deg : float
        Rays meeting at a smaller angle are dropped (depth too uncertain).
    guessed : (H, W) bool, optional
        Pixels whose disparity is a guess: filled in rather than matched.
    consistent : (H, W) uint8 or bool, optional
        Guessed pixels with evidence for them: 1 (or True) where the images agree with
        the guess (photo-consistent), 2 where the pixel lies beyond an occlusion's width
        beside the surface it was filled from
        (:func:`recon3d.stereo.match.foreground_beyond_occlusion`); 0 elsewhere.

    Returns
    -------
    PointCloud
        xyz in model coordinates (no CRS yet); attributes ``red``, ``green``,
        ``blue`` (uint16), ``quality`` (confidence scaled by the intersection angle's
        depth precision, in [0, 1]), ``intersection_angle`` (degrees), ``observed``
        (uint8, 0 for points of guessed pixels; all 1 without ``guessed``) and, with
        ``consistent``, ``consistent`` (uint8, its value at the point's pixel).
    """
    valid = np.isfinite(disparity) & pair.valid_left
    rows, cols = np.nonzero(valid)
    xr = np.round(cols - disparity[rows, cols]).astype(np.int64)
    inside = (xr >= 0) & (xr < pair.valid_right.shape[1])
    inside[inside] = pair.valid_right[rows[inside], xr[inside]]
    valid[rows[~inside], cols[~inside]] = False  # the match must land inside the right image
    rows, cols = np.nonzero(valid)
    xyz = pair.triangulate(cols, rows, disparity[rows, cols])
    ca, cb = pair.camera_left.center, pair.camera_right.center
    ra, rb = xyz - ca, xyz - cb
    cos = np.einsum("ij,ij->i", ra, rb) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1))
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    keep = np.isfinite(xyz).all(axis=1) & (angle >= min_angle_deg)
    rgb = pair.color[valid][keep].astype(np.uint16) * 257
    quality = confidence[valid][keep] * np.sin(np.radians(np.minimum(angle[keep], 90.0)))
    attributes = {
        "red": rgb[:, 0],
        "green": rgb[:, 1],
        "blue": rgb[:, 2],
        "quality": quality.astype(np.float32),
        "intersection_angle": angle[keep].astype(np.float32),
        "observed": np.ones(int(keep.sum()), np.uint8) if guessed is None else (~guessed[valid][keep]).astype(np.uint8),
    }
    if consistent is not None:
        attributes["consistent"] = consistent[valid][keep].astype(np.uint8)
    return PointCloud(xyz[keep], attributes)
