"""Rectification and triangulation, exact for every camera configuration of the survey family.

Each named survey (headings of 0, 90, 180 and more degrees, bases along the image rows,
the columns and diagonal, off-centre principal points, non-square images, base-to-height
0.1 to 1.0, strips and a 2 x 3 block) is rendered at a small size and read back through
its COLMAP model, as a user's scene would be. These tests cannot pass by luck: they
compare with geometry that is known exactly.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from recon3d.errors import InputError
from recon3d.io.colmap import read_scene
from recon3d.stereo.rectify import rectify_pair, select_pairs
from recon3d.synthetic.family import CONFIGURATIONS
from recon3d.synthetic.scene import write_block_scene

WIDTH = 240


@pytest.fixture(scope="module", params=sorted(CONFIGURATIONS))
def survey(request, tmp_path_factory):
    spec = CONFIGURATIONS[request.param].with_width(WIDTH)
    info = write_block_scene(tmp_path_factory.mktemp(request.param) / "scene", spec)
    return info, read_scene(info.folder)


def _pairs(scene):
    pairs, _ = select_pairs(scene.cameras, scene.sparse, scene.seen)
    for i, j in pairs:
        a, b = scene.cameras[i], scene.cameras[j]
        common = scene.seen[i] & scene.seen[j]
        images = [cv2.imread(str(c.image_path)) for c in (a, b)]
        yield i, j, rectify_pair(a, b, *images, scene.sparse[common]), scene.sparse[common]


def test_every_common_sparse_point_lies_in_both_rectified_images(survey):
    _, scene = survey
    n = 0
    for _, _, pair, points in _pairs(scene):
        h, w = pair.left.shape
        uvl, uvr = pair.project(points)
        for uv, valid in ((uvl, pair.valid_left), (uvr, pair.valid_right)):
            assert (uv[:, 0] >= 0).all() and (uv[:, 0] <= w - 1).all(), pair.name
            assert (uv[:, 1] >= 0).all() and (uv[:, 1] <= h - 1).all(), pair.name
            c, r = np.rint(uv).astype(int).T
            assert valid[r, c].mean() >= 0.99, pair.name
        lo, hi = pair.disparity_range
        d = uvl[:, 0] - uvr[:, 0]
        assert (d >= lo).all() and (d < hi).all()
        # the search spans the scene's depths, not a constant offset in front of them
        assert max(abs(lo), abs(hi)) <= 2 * (hi - lo)
        n += 1
    assert n >= 1


def test_the_range_reaches_roofs_the_pair_sparse_points_miss(survey):
    """A pair whose sparse points sample only the lower half of the scene (the ground, low
    roofs) still searches the disparities of the higher half, given the block's top."""
    _, scene = survey
    top = float(scene.sparse[:, 2].max())
    for i, j, _, points in _pairs(scene):
        low = points[points[:, 2] <= np.median(points[:, 2])]
        if len(low) < 3:
            continue
        a, b = scene.cameras[i], scene.cameras[j]
        images = [cv2.imread(str(c.image_path)) for c in (a, b)]
        pair = rectify_pair(a, b, *images, low, top=top)
        uvl, uvr = pair.project(points)
        d = uvl[:, 0] - uvr[:, 0]
        lo, hi = pair.disparity_range
        assert (d >= lo).all() and (d < hi).all(), (pair.name, d.max(), hi)


def test_exact_correspondences_triangulate_to_the_world_points(survey):
    """Pixels of the first image of each pair with their rendered surface point, matched
    exactly into the second through its camera: rectified, they share a row; triangulated,
    they give the surface point back within 0.01 ground sample distance."""
    info, scene = survey
    rng = np.random.default_rng(0)
    for i, j, pair, _ in _pairs(scene):
        render = info.renders[i]
        rows, cols = rng.integers(0, render.xyz.shape[0], 3000), rng.integers(0, render.xyz.shape[1], 3000)
        xyz = render.xyz[rows, cols].astype(np.float64)
        b = scene.cameras[j]
        uv_b, depth = b.project(xyz, distort=True)
        inside = np.isfinite(xyz).all(axis=1) & (depth > 0)
        inside &= (uv_b[:, 0] >= 0) & (uv_b[:, 0] <= b.width - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] <= b.height - 1)
        assert inside.sum() > 100
        # COLMAP puts the top-left pixel centre at (0.5, 0.5), OpenCV (and Camera) at (0, 0)
        uv_a = np.column_stack([cols, rows]).astype(np.float64)[inside]
        left = pair.to_rectified(uv_a)
        right = pair.to_rectified(uv_b[inside], right=True)
        assert np.abs(left[:, 1] - right[:, 1]).max() < 0.01
        back = pair.triangulate(left[:, 0], left[:, 1], left[:, 0] - right[:, 0])
        gsd = np.linalg.norm(xyz[inside] - pair.camera_left.center, axis=1) / pair.focal
        assert (np.linalg.norm(back - xyz[inside], axis=1) / gsd).max() < 0.01


def test_rectified_pixels_map_back_to_the_resampled_ones(survey):
    """to_original is the mapping the images were resampled with: the rectified grey
    values equal the original ones bilinearly sampled there."""
    _, scene = survey
    for i, _, pair, _ in _pairs(scene):
        rows, cols = np.nonzero(pair.valid_left)
        pick = np.linspace(0, len(rows) - 1, 500).astype(int)
        xy = np.column_stack([cols[pick], rows[pick]]).astype(np.float64)
        uv = pair.to_original(xy).astype(np.float32)
        grey = cv2.cvtColor(cv2.imread(str(scene.cameras[i].image_path)), cv2.COLOR_BGR2GRAY)
        sampled = cv2.remap(grey, uv[:, :1], uv[:, 1:], cv2.INTER_LINEAR)[:, 0]
        diff = np.abs(sampled.astype(int) - pair.left[rows[pick], cols[pick]].astype(int))
        assert diff.max() <= 3 and diff.mean() <= 0.5  # OpenCV's remap rounds positions to 1/32 px
        break


def test_cameras_that_see_different_ground(survey):
    """Two images of a block that share no sparse point are refused, with the pair named."""
    _, scene = survey
    seen = scene.seen.copy()
    seen[1] &= ~seen[0]  # no point in common between the first two images
    with pytest.raises(InputError, match="common sparse points"):
        select_pairs(scene.cameras[:2], scene.sparse, seen[:2])
