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
        if distort and np.any(self.dist):
            import cv2

            uv, _ = cv2.projectPoints(cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), self.K, self.dist)
            return uv.reshape(-1, 2), depth
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ self.K.T)[:, :2] / depth[:, None]
        return uv, depth
