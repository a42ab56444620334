"""Frame-stereo scene folders: ``images/``, a COLMAP model in ``sparse/``, ``georef.json``.

The model is read with pycolmap (text or binary). ``georef.json`` holds
``{"crs": "EPSG:N", "offset": [x0, y0, z0]}`` meaning world = model + offset; without
it the model frame is the world frame and ``--crs`` must name the CRS.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyproj

from recon3d.core.camera import Camera
from recon3d.core.geo import parse_crs
from recon3d.errors import CRSError, InputError

log = logging.getLogger(__name__)

__all__ = ["StereoScene", "is_scene_folder", "read_scene"]

#: COLMAP camera models recon3d reads, with the OpenCV distortion their parameters give.
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class StereoScene:
    """An oriented image block in model coordinates.

    Attributes
    ----------
    cameras : list of Camera
        One per registered image, poses in model coordinates.
    sparse : (n, 3) float
        Sparse 3-D points of the model (model coordinates).
    seen : (len(cameras), n) bool
        Which images observe each sparse point (its COLMAP track).
    offset : (3,) float
        World = model + offset.
    crs : pyproj.CRS
    folder : Path
    """

    cameras: list[Camera]
    sparse: np.ndarray
    seen: np.ndarray
    offset: np.ndarray
    crs: pyproj.CRS
    folder: Path


def is_scene_folder(path: str | Path) -> bool:
    """True for a folder with ``images/`` and ``sparse/``."""
    path = Path(path)
    return path.is_dir() and (path / "sparse").is_dir()


def read_scene(folder: str | Path, *, crs: pyproj.CRS | None = None) -> StereoScene:
    """Read and check a scene folder.

    Raises
    ------
    InputError
        Missing or unreadable model or images, unsupported camera model, images whose
        size differs from the model's, fewer than two images.
    CRSError
        No CRS in georef.json and none given.
    """
    import pycolmap

    folder = Path(folder)
    sparse = _model_dir(folder / "sparse")
    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as exc:
        raise InputError(f"{sparse}: cannot read the COLMAP model ({exc})") from None
    images = _registered(rec)
    cameras = [_camera(rec, image, folder / "images") for image in images]
    if len(cameras) < 2:
        raise InputError(f"{sparse}: the model has {len(cameras)} registered image(s); stereo needs two")
    points, seen = _sparse_points(rec, [im.image_id for im in images])
    offset, scene_crs = _georef(folder, crs)
    return StereoScene(cameras, points, seen, offset, scene_crs, folder)


def _sparse_points(rec, image_ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) sparse points and (len(image_ids), n) bool of the images in their tracks."""
    index = {image_id: k for k, image_id in enumerate(image_ids)}
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    seen = np.zeros((len(image_ids), len(ids)), bool)
    for n, i in enumerate(ids):
        for element in rec.points3D[i].track.elements:
            k = index.get(element.image_id)
            if k is not None:
                seen[k, n] = True
    return xyz, seen


def _model_dir(sparse: Path) -> Path:
    """The folder holding cameras/images/points3D (``sparse/`` or ``sparse/0``)."""
    for candidate in (sparse, sparse / "0"):
        if any((candidate / f"cameras.{ext}").exists() for ext in ("txt", "bin")):
            return candidate
    raise InputError(f"{sparse}: no COLMAP model (cameras.txt or cameras.bin) found")


def _registered(rec) -> list:
    images = [rec.images[i] for i in sorted(rec.images) if rec.images[i].has_pose]
    return sorted(images, key=lambda im: im.name)


def _camera(rec, image, image_dir: Path) -> Camera:
    cam = rec.cameras[image.camera_id]
    model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    if model not in SUPPORTED_MODELS:
        raise InputError(
            f"image {image.name}: camera model {model} is not supported (use one of {', '.join(SUPPORTED_MODELS)})"
        )
    K, dist = _intrinsics(model, np.asarray(cam.params, dtype=np.float64))
    path = image_dir / image.name
    if not path.is_file():
        raise InputError(f"{path}: image not found")
    size = _image_size(path)
    if size != (cam.width, cam.height):
        raise InputError(
            f"{path}: image is {size[0]} x {size[1]} px but the model says {cam.width} x {cam.height}"
        )
    pose = image.cam_from_world()
    R = np.asarray(pose.rotation.matrix(), dtype=np.float64)
    t = np.asarray(pose.translation, dtype=np.float64)
    return Camera(image.name, K, dist, R, t, int(cam.width), int(cam.height), path)


def _intrinsics(model: str, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV K and distortion from COLMAP parameters (principal point shifted by -0.5 px)."""
    dist = np.zeros(5)
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p[:4]
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, dist[0] = p[1], p[2], p[3]
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy, dist[0], dist[1] = p[1], p[2], p[3], p[4]
    else:  # OPENCV: fx, fy, cx, cy, k1, k2, p1, p2
        fx, fy, cx, cy = p[:4]
        dist[:4] = p[4:8]
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    return K, dist


def _image_size(path: Path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: unreadable image")
    return image.shape[1], image.shape[0]


def _georef(folder: Path, crs: pyproj.CRS | None) -> tuple[np.ndarray, pyproj.CRS]:
    path = folder / "georef.json"
    offset = np.zeros(3)
    file_crs = None
    if path.exists():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            offset = np.asarray(data.get("offset", [0, 0, 0]), dtype=np.float64).reshape(3)
            file_crs = parse_crs(data["crs"], source=str(path)) if data.get("crs") else None
        except (ValueError, TypeError) as exc:
            raise InputError(f"{path}: expected {{\"crs\": \"EPSG:N\", \"offset\": [x0, y0, z0]}} ({exc})") from None
    if file_crs is None and crs is None:
        raise CRSError(f"{folder}: no CRS (write georef.json or give --crs)")
    chosen = crs or file_crs
    horizontal = chosen.sub_crs_list[0] if chosen.is_compound else chosen
    if horizontal.is_geographic:
        source = "--crs" if crs is not None else str(path)
        raise CRSError(
            f"{source}: CRS {horizontal.name} is in degrees; the model's coordinates (world = model + offset) "
            "need a projected CRS in metres or feet, such as the scene's UTM zone"
        )
    return offset, chosen
