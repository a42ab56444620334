"""The frame-stereo path on real photographs: the Middlebury "cones" pair as an oriented scene.

Cones is already rectified and its true disparities are known. Given as a COLMAP model
(two pinhole cameras a baseline apart along x, sparse points from the true disparities,
as a structure-from-motion model would hold them), recon3d must rectify it back to
itself, match it, triangulate, pass its own self-check, and give points whose
disparities agree with the truth.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import shared

from recon3d.config import StereoConfig
from recon3d.io.colmap import read_scene
from recon3d.pipeline.stereo import dense_cloud

FOCAL, BASE = 250.0, 0.16  # any pair gives the same disparities (depth = FOCAL * BASE / d); a
# short focal length keeps the base-to-height ratio (about 0.12) in the usable range


def _write_scene(folder, left, right, disparity, n_points=300):
    import pycolmap

    h, w = disparity.shape
    (folder / "images").mkdir(parents=True)
    shutil.copy(left, folder / "images" / "left.png")
    shutil.copy(right, folder / "images" / "right.png")
    rng = np.random.default_rng(0)
    rows, cols = np.nonzero(disparity > 0)
    pick = rng.choice(len(rows), n_points, replace=False)
    v, u = rows[pick].astype(float), cols[pick].astype(float)
    d = disparity[rows[pick], cols[pick]].astype(float)
    z = FOCAL * BASE / d
    xyz = np.column_stack([(u - w / 2 + 0.5) * z / FOCAL, (v - h / 2 + 0.5) * z / FOCAL, z])
    rec = pycolmap.Reconstruction()
    for k, (name, cx) in enumerate((("left.png", 0.0), ("right.png", BASE)), start=1):
        camera = pycolmap.Camera(model="PINHOLE", width=w, height=h, params=[FOCAL, FOCAL, w / 2, h / 2], camera_id=k)
        rec.add_camera_with_trivial_rig(camera)
        uv = np.column_stack([u - (d if k == 2 else 0.0), v]) + 0.5  # COLMAP pixel centres
        image = pycolmap.Image(name=name, keypoints=uv, camera_id=k, image_id=k)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([[-cx], [0.0], [0.0]])))
    for i, p in enumerate(xyz):
        rec.add_point3D(p, pycolmap.Track([pycolmap.TrackElement(1, i), pycolmap.TrackElement(2, i)]), np.full(3, 128, np.uint8))
    (folder / "sparse").mkdir()
    rec.write_text(str(folder / "sparse"))
    (folder / "georef.json").write_text(json.dumps({"crs": "EPSG:32631", "offset": [500000.0, 5400000.0, 0.0]}))


@pytest.fixture(scope="module")
def cones(tmp_path_factory):
    import rasterio

    base = shared("stereo/middlebury_cones/left.png").parent
    with rasterio.open(base / "disp_left.tif") as src:
        truth = src.read(1).astype(np.float32)
    folder = tmp_path_factory.mktemp("cones") / "scene"
    _write_scene(folder, base / "left.png", base / "right.png", truth)
    scene = read_scene(folder)
    cloud, report = dense_cloud(scene, StereoConfig())
    return scene, cloud, report, truth


@pytest.mark.slow
def test_cones_pass_the_self_check(cones):
    _, _, report, _ = cones
    pair = report["pairs"][0]
    assert pair["vertical_parallax_px"]["median"] <= 0.3
    check = pair["self_check"]
    assert check["coverage_percent"] >= 90.0
    assert check["disparity_error_px"] <= 0.5
    assert check["reprojection_px"] <= 0.01
    lo, hi = pair["disparity_range"]["value"]
    assert hi - lo <= 80  # the scene's 10..55 px, widened: no offset to search through


@pytest.mark.slow
def test_cones_points_agree_with_the_true_disparities(cones):
    """Each fused point, seen from the left camera, has the disparity the truth gives at
    its pixel: measured 96 % within 1 px (matched points on pixels with a truth)."""
    scene, cloud, _, truth = cones
    h, w = truth.shape
    model = cloud.xyz - scene.offset
    uv, depth = scene.cameras[0].project(model)
    col, row = np.rint(uv).astype(int).T
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h) & (cloud.attributes["observed"] > 0)
    d_true = truth[row[inside], col[inside]]
    known = d_true > 0
    d_point = FOCAL * BASE / depth[inside][known]
    assert known.sum() > 50000
    assert np.mean(np.abs(d_point - d_true[known]) <= 1.0) >= 0.9
