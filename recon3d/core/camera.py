"""Frame cameras: intrinsics, lens distortion and pose, in OpenCV conventions."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Camera"]


@dataclass
class Camera:
    """A pinhole frame camera with its image.

    Parameters
    ----------
    name : str
        Image name in the model.
    K : (3, 3) float
        Intrinsics in the OpenCV pixel convention: the centre of the top-left pixel is
        (0, 0). COLMAP's convention puts it at (0.5, 0.5); :mod:`recon3d.io.colmap`
        converts.
    dist : (5,) float
        OpenCV distortion coefficients (k1, k2, p1, p2, k3).
    R : (3, 3) float
        Rotation of ``cam_from_world``: x_cam = R x_world + t (camera looks along +z,
        image x to the right, y down).
    t : (3,) float
    width, height : int
        Image size in pixels.
    image_path : Path or None
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    image_path: Path | None = None

    @property
    def center(self) -> np.ndarray:
        """(3,) projection centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def viewing_direction(self) -> np.ndarray:
        """(3,) unit optical axis in world coordinates."""
        return self.R[2]

    def project(self, xyz: np.ndarray, *, distort: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Projection of (n, 3) world points, without lens distortion unless ``distort``.

        Returns
        -------
        uv : (n, 2) float
            OpenCV pixel coordinates.
        depth : (n,) float
            Distance along the optical axis (negative behind the camera).
        """
        cam = np.asarray(xyz, dtype=np.float64) @ self.R.T + self.t
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = cam[:, 0] / depth, cam[:, 1] / depth
        if distort and np.any(self.dist):
            x, y = _distort(x, y, np.asarray(self.dist, dtype=np.float64))
        K = self.K
        uv = np.column_stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]])
        return uv, depth


def _distort(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's lens model (k1, k2, p1, p2[, k3]) on normalised image coordinates (n,).

    The same formula as ``cv2.projectPoints``, without the Jacobians it always computes
    (which made it the slowest step of orthorectifying a million cells).
    """
    k1, k2, p1, p2, k3 = (list(dist) + [0.0] * 5)[:5]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    return (x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy)
