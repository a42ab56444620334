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

    def rotated_clockwise(self) -> Camera:
        """The same camera for its image turned 90 degrees clockwise (``cv2.ROTATE_90_CLOCKWISE``).

        Pixel (u, v) moves to (height - 1 - v, u); the camera frame turns about its
        optical axis, so the projection of every world point follows the pixels.
        """
        rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        K = np.array([[fy, 0.0, self.height - 1 - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]])
        k1, k2, p1, p2, k3 = self.dist
        dist = np.array([k1, k2, p2, -p1, k3])
        return Camera(self.name, K, dist, rz @ self.R, rz @ self.t, self.height, self.width, self.image_path)

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distortion-free projection of (n, 3) world points.

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
            uv = (cam @ self.K.T)[:, :2] / depth[:, None]
        return uv, depth
