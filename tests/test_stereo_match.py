"""Dense matching: Middlebury accuracy, exact synthetic ground truth, determinism, bad input."""

from __future__ import annotations

import dataclasses
import warnings

import cv2
import numpy as np
import pytest
from conftest import shared

from recon3d.errors import InputError
from recon3d.stereo.match import DisparityResult, MatchParams, match

CONES = "stereo/middlebury_cones"


# ----------------------------------------------------------------------------- helpers


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.0)
    return cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)


def _plane_pair(h: int, w: int, a: float, b: float = 0.0, c: float = 0.0, seed: int = 0):
    """A random-texture pair whose left disparity is exactly d(x, y) = a + b x + c y.

    The right image at column xr shows the left texture at xl with xl - d(xl, y) = xr,
    i.e. xl = (xr + a + c y) / (1 - b); bicubic resampling of a smooth texture.
    """
    margin = 100
    base = _texture(h, w + 2 * margin, seed)
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    left = base[:, margin : margin + w].copy()
    xl = (xx + a + c * yy) / (1.0 - b)
    right = cv2.remap(base, xl + margin, yy, cv2.INTER_CUBIC)
    return left, right, a + b * xx + c * yy


def _interior(shape, left_margin: int) -> np.ndarray:
    """Pixels away from the borders (the left band sees its match outside the right image)."""
    mask = np.zeros(shape, bool)
    mask[4:-4, left_margin:-4] = True
    return mask


def _cones():
    import rasterio

    left = cv2.imread(str(shared(f"{CONES}/left.png")), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(shared(f"{CONES}/right.png")), cv2.IMREAD_GRAYSCALE)
    occlusion = cv2.imread(str(shared(f"{CONES}/occlusion.png")), cv2.IMREAD_GRAYSCALE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TIFF has no georeferencing
        with rasterio.open(shared(f"{CONES}/disp_left.tif")) as src:
            gt = src.read(1).astype(np.float32)
    # evaluated: pixels with a ground truth (> 0) that the mask says are non-occluded (white)
    return left, right, gt, (gt > 0) & (occlusion == 255)


def _scores(disp: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict:
    """Middlebury scores; invalid (NaN) pixels count as errors."""
    err = np.abs(disp - gt)[mask]
    err = np.where(np.isfinite(err), err, np.inf)
    finite = np.isfinite(err)
    return {
        "bad1": 100.0 * float((err > 1).mean()),
        "bad2": 100.0 * float((err > 2).mean()),
        "mae": float(err[finite].mean()),
        "density": 100.0 * float(finite.mean()),
    }


@pytest.fixture(scope="module")
def cones():
    return _cones()


# ----------------------------------------------------------------------------- Middlebury


@pytest.mark.parametrize(("engine", "regression"), [("census", 3.5), ("sgbm", 3.6)])
def test_middlebury_cones_bad1(cones, engine, regression, record_property):
    """Acceptance: bad-1 <= 5 % on non-occluded pixels, invalid pixels counted as errors.

    Measured 3.2 % (census, the default) and 3.3 % (sgbm) at 100 % density; raw
    StereoSGBM scores 12.6 % at 90.6 %. ``regression`` guards the measured figures.
    """
    left, right, gt, mask = cones
    result = match(left, right, MatchParams(min_disparity=0, max_disparity=64, engine=engine))
    scores = _scores(result.disparity, gt, mask)
    for key, value in scores.items():
        record_property(f"cones_{engine}_{key}", round(value, 3))
    assert scores["bad1"] <= 5.0, scores
    assert scores["bad1"] <= regression, scores
    assert scores["density"] >= 99.9, scores
    assert scores["mae"] < 0.5, scores


def test_edge_aware_median_moves_a_smeared_step_onto_the_colour_edge():
    """A roof (disparity 30) whose matched edge came out 2 px short of its colour edge
    gets those pixels back; pixels away from the step keep their sub-pixel values."""
    from recon3d.stereo.match import _edge_aware_median

    h, w, edge = 40, 60, 30
    guide = np.zeros((h, w, 3), np.float32)
    guide[:, :edge] = (200, 90, 70)  # tiles
    guide[:, edge:] = (70, 110, 50)  # grass
    rng = np.random.default_rng(0)
    guide += rng.normal(0, 3, guide.shape).astype(np.float32)
    truth = np.where(np.arange(w) < edge, 30.0, 10.0).astype(np.float32)[None, :].repeat(h, 0)
    truth += rng.uniform(-0.3, 0.3, truth.shape).astype(np.float32)
    smeared = truth.copy()
    smeared[:, edge - 2 : edge] = 10.0  # the cost window pulled the background in
    out = _edge_aware_median(smeared, guide, radius=6, sigma=12.0)
    assert np.abs(out - truth)[:, 8:-8].max() < 1.0
    assert np.array_equal(out[:, :edge - 10], smeared[:, :edge - 10])  # far from the step


def test_middlebury_cones_unfilled_map(cones):
    """The map before gap filling: NaN where matching failed, and accurate where valid."""
    left, right, gt, mask = cones
    filled = match(left, right)
    unfilled = match(left, right, MatchParams(fill_gaps=False))
    assert np.array_equal(filled.unfilled, unfilled.disparity, equal_nan=True)
    holes = ~np.isfinite(unfilled.disparity)
    assert 0.01 < holes.mean() < 0.2  # occlusions and mismatches are left out
    assert np.array_equal(holes, filled.filled)
    assert np.all(unfilled.confidence[holes] == 0)
    assert np.all(filled.confidence[filled.filled] == pytest.approx(MatchParams().fill_confidence))
    valid = mask & ~holes
    err = np.abs(unfilled.disparity - gt)[valid]
    assert (err > 1).mean() < 0.03  # what the matcher keeps is right


# ----------------------------------------------------------------------------- synthetic truth


@pytest.mark.parametrize("engine", ["census", "sgbm"])
@pytest.mark.parametrize(
    ("a", "b", "c"),
    [(12.0, 0.0, 0.0), (9.5, 0.0, 0.0), (10.3, 0.05, 0.02), (8.0, 0.1, 0.0)],
    ids=["integer-shift", "half-pixel-shift", "slanted-plane", "steep-slant"],
)
def test_synthetic_plane_subpixel(engine, a, b, c):
    left, right, gt = _plane_pair(120, 160, a, b, c)
    result = match(left, right, MatchParams(min_disparity=0, max_disparity=40, engine=engine))
    inside = _interior(gt.shape, left_margin=int(np.ceil(gt.max())) + 2)
    err = np.abs(result.disparity - gt)[inside]
    assert np.isfinite(err).all()
    assert err.mean() < 0.2, err.mean()
    assert (err > 1).mean() < 0.005


def test_sheared_windows_match_a_foreshortened_plane():
    """A surface whose disparity grows by 0.5 px per column (a roof face at a wide base,
    squeezed to half its width in the right view): upright census windows get 71 % of
    it within 1 px, windows sheared by slant 0.5 get 91 %; a fronto-parallel plane stays
    exact."""
    left, right, gt = _plane_pair(120, 160, 5.0, 0.5, 0.0)
    inside = _interior(gt.shape, left_margin=int(np.ceil(gt.max())) + 2) & (np.arange(160)[None, :] - gt >= 2)

    def good(slant, pair=(left, right, gt)):
        result = match(pair[0], pair[1], MatchParams(min_disparity=1, max_disparity=90, slant=slant, fill_gaps=False))
        return float(np.mean(np.abs(result.disparity - pair[2])[inside] <= 1.0))

    upright, sheared = good(0.0), good(0.5)
    assert upright < 0.8, upright
    assert sheared > 0.88, sheared
    flat = _plane_pair(120, 160, 10.0)
    inside = _interior(flat[2].shape, left_margin=14)
    assert good(0.5, flat) >= 0.995


def test_slant_out_of_range():
    from recon3d.config import StereoConfig

    for bad in (-0.1, 1.0):
        with pytest.raises(InputError, match="slant"):
            MatchParams(slant=bad)
        with pytest.raises(InputError, match="stereo.slant"):
            StereoConfig(slant=bad)


def test_negative_disparities():
    """Swapping the images turns disparity d into -d: a negative range must work."""
    left, right, gt = _plane_pair(100, 140, 9.0)
    result = match(right, left, MatchParams(min_disparity=-24, max_disparity=0))
    inside = np.zeros(gt.shape, bool)
    inside[4:-4, 4:-14] = True
    assert np.abs(result.disparity + gt)[inside].mean() < 0.2


def test_colour_uint16_and_float_inputs_agree():
    left, right, _ = _plane_pair(80, 120, 7.0)
    l8, r8 = np.rint(left).astype(np.uint8), np.rint(right).astype(np.uint8)
    grey = match(l8, r8, MatchParams(max_disparity=24))
    colour = match(np.dstack([l8] * 3), np.dstack([r8] * 3), MatchParams(max_disparity=24))
    assert np.array_equal(grey.disparity, colour.disparity, equal_nan=True)
    # a 16-bit pair with an offset and a different gain still matches (census is rank-based)
    l16 = (l8.astype(np.uint16) * 200 + 1000).astype(np.uint16)
    r16 = (r8.astype(np.uint16) * 200 + 1000).astype(np.uint16)
    deep = match(l16, r16, MatchParams(max_disparity=24))
    inside = _interior(l8.shape, 12)
    assert np.abs(deep.disparity - 7.0)[inside].mean() < 0.2


def test_float_nodata_gives_nan():
    left, right, gt = _plane_pair(80, 120, 6.0)
    left = left.astype(np.float32)
    left[20:30, 50:70] = np.nan
    result = match(left, right, MatchParams(max_disparity=24))
    assert np.isnan(result.disparity[20:30, 50:70]).all()
    assert np.all(result.confidence[20:30, 50:70] == 0)
    inside = _interior(gt.shape, 10)
    inside[16:34, 46:74] = False
    assert np.abs(result.disparity - gt)[inside].mean() < 0.2


def test_pyramid_narrows_a_wide_range():
    left, right, gt = _plane_pair(128, 192, 11.0, 0.02)
    wide = match(left, right, MatchParams(min_disparity=0, max_disparity=160))
    lo, hi = wide.params["disparity_range_searched"]["value"]
    assert 0 <= lo <= 11 and 15 <= hi < 80
    inside = _interior(gt.shape, 40)
    assert np.abs(wide.disparity - gt)[inside].mean() < 0.2
    plain = match(left, right, MatchParams(min_disparity=0, max_disparity=160, pyramid_levels=0))
    assert plain.params["disparity_range_searched"]["value"] == [0, 160]


def test_strips_match_whole_image():
    """Processing in strips of rows (bounded memory) changes almost nothing."""
    left, right, gt = _plane_pair(200, 120, 6.5, 0.03, 0.01)
    whole = match(left, right, MatchParams(max_disparity=32))
    strips = match(left, right, MatchParams(max_disparity=32, strip_memory_mb=1))
    assert whole.params["strips"] == 1 and strips.params["strips"] > 1
    inside = _interior(gt.shape, 16)
    diff = np.abs(whole.disparity - strips.disparity)[inside]
    assert np.nanmax(diff) < 0.5 and np.isfinite(diff).all()


def test_strips_search_what_the_coarse_pass_saw_in_their_rows():
    """A ground sloping from 5 to 85 px of disparity down the image: no strip of rows
    needs the whole range, and each searches only its own part of it (covering its true
    disparities), with the same accuracy as one strip over everything."""
    left, right, gt = _plane_pair(320, 200, 5.0, 0.0, 0.25)
    params = MatchParams(max_disparity=128, strip_memory_mb=2)
    result = match(left, right, params)
    ranges = result.params["strip_disparity_ranges"]
    assert len(ranges) > 2
    widths = [hi - lo for lo, hi in ranges]
    lo_all, hi_all = result.params["disparity_range_searched"]["value"]
    assert max(widths) < 0.6 * (hi_all - lo_all), (ranges, lo_all, hi_all)
    inside = _interior(gt.shape, 100)
    err = np.abs(result.disparity - gt)[inside]
    assert np.isfinite(err).all() and err.mean() < 0.2, err.mean()
    whole = match(left, right, MatchParams(max_disparity=128))
    assert whole.params["strips"] == 1
    assert np.abs(whole.disparity - gt)[inside].mean() < 0.2


def test_result_contract():
    left, right, _ = _plane_pair(64, 96, 5.0)
    result = match(left, right, MatchParams(max_disparity=16))
    assert isinstance(result, DisparityResult)
    assert result.disparity.shape == left.shape and result.disparity.dtype == np.float32
    assert result.confidence.shape == left.shape and result.confidence.dtype == np.float32
    assert np.all((result.confidence >= 0) & (result.confidence <= 1))
    assert result.filled.dtype == bool
    assert result.params["engine"] == "census" and result.params["max_disparity"] == 16
    assert "seconds" in result.params and "disparity_range_searched" in result.params
    finite = result.disparity[np.isfinite(result.disparity)]
    assert finite.min() >= -0.5 and finite.max() <= 16.5


# ----------------------------------------------------------------------------- determinism


@pytest.mark.parametrize("engine", ["census", "sgbm"])
def test_deterministic(engine):
    left, right, _ = _plane_pair(200, 128, 8.3, 0.04)  # 1 MB strips: 4 of them
    params = MatchParams(max_disparity=32, engine=engine, strip_memory_mb=1)
    first = match(left, right, params)
    second = match(left.copy(), right.copy(), params)
    one_worker = match(
        left, right, MatchParams(max_disparity=32, engine=engine, strip_memory_mb=1, workers=1)
    )
    if engine == "census":
        assert first.params["strips"] > 1
    for other in (second, one_worker):
        assert np.array_equal(first.disparity, other.disparity, equal_nan=True)
        assert np.array_equal(first.confidence, other.confidence)


_THREADS_SCRIPT = """
import hashlib, sys
import numpy as np
sys.path.insert(0, {tests!r})
from test_stereo_match import _plane_pair
from recon3d.stereo.match import MatchParams, match
left, right, _ = _plane_pair(150, 140, 9.3, 0.05, 0.02)
result = match(left, right, MatchParams(max_disparity=40, strip_memory_mb=1))
print(result.params["strips"], hashlib.sha256(result.disparity.tobytes() + result.confidence.tobytes()).hexdigest())
"""


def test_same_bytes_whatever_the_thread_count():
    """The compiled census engine gives the same bytes on 1 and on 2 numba threads."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    tests = Path(__file__).resolve().parent
    script = _THREADS_SCRIPT.format(tests=str(tests))
    outputs = []
    for threads in ("1", "2"):
        env = {**os.environ, "NUMBA_NUM_THREADS": threads,
               "PYTHONPATH": os.pathsep.join([str(tests.parent), os.environ.get("PYTHONPATH", "")])}
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, check=False)
        assert done.returncode == 0, done.stderr[-3000:]
        outputs.append(done.stdout.strip().splitlines()[-1])
    strips, digest = outputs[0].split()
    assert int(strips) > 1  # strip borders are part of what must not depend on threads
    assert outputs[0] == outputs[1]


# ----------------------------------------------------------------------------- bad input


def test_images_of_different_sizes():
    with pytest.raises(InputError, match="differ in size"):
        match(np.zeros((50, 60), np.uint8), np.zeros((50, 61), np.uint8))


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((4, 50, 60), np.uint8),
        np.zeros((50, 60, 4), np.uint8),
        np.zeros(60, np.uint8),
        np.zeros((50, 60, 3, 1)),
    ],
    ids=["4-band-first", "rgba", "1-d", "4-d"],
)
def test_not_a_2d_image(image):
    with pytest.raises(InputError, match="shape"):
        match(image, image)


def test_unsupported_types_and_tiny_images():
    with pytest.raises(InputError, match="pixel type"):
        match(np.zeros((50, 60), bool), np.zeros((50, 60), bool))
    with pytest.raises(InputError, match="too small"):
        match(np.zeros((5, 60), np.uint8), np.zeros((5, 60), np.uint8))
    with pytest.raises(InputError, match="no finite pixel"):
        match(np.full((50, 60), np.nan), np.zeros((50, 60)))


@pytest.mark.parametrize(("lo", "hi"), [(10, 10), (20, 5)])
def test_empty_disparity_range(lo, hi):
    with pytest.raises(InputError, match="empty disparity range"):
        MatchParams(min_disparity=lo, max_disparity=hi)


def test_range_outside_the_image_and_bad_parameters():
    img = np.zeros((40, 50), np.uint8)
    with pytest.raises(InputError, match="outside the image width"):
        match(img, img, MatchParams(min_disparity=60, max_disparity=90))
    with pytest.raises(InputError, match="engine"):
        MatchParams(engine="bm")
    with pytest.raises(InputError, match="census_window"):
        MatchParams(census_window=(9, 9))
    with pytest.raises(InputError, match="p2"):
        MatchParams(p1=10, p2=5)
    with pytest.raises(InputError, match="sharpen_steps"):
        MatchParams(sharpen_steps=-1.0)
    from recon3d.config import StereoConfig

    with pytest.raises(InputError, match="stereo.sharpen_steps"):
        StereoConfig(sharpen_steps=-0.5)
    assert isinstance(InputError("x"), ValueError)


def test_photo_consistency_confirms_the_true_disparity_only():
    from recon3d.stereo.match import photo_consistency

    rng = np.random.default_rng(1)
    right = cv2.GaussianBlur(rng.uniform(0, 255, (60, 120)).astype(np.float32), (3, 3), 0)
    left = np.roll(right, 7, axis=1)  # left sees its match at x - 7 in right
    good = photo_consistency(left, right, np.full(left.shape, 7.0, np.float32))
    bad = photo_consistency(left, right, np.full(left.shape, 12.0, np.float32))
    inner = np.s_[5:-5, 20:-5]
    assert np.median(good[inner]) > 0.95
    assert np.median(np.abs(bad[inner])) < 0.3
    holes = np.full(left.shape, np.nan, np.float32)
    assert np.isnan(photo_consistency(left, right, holes)).all()


def _row_with_hole(left_d: float, right_d: float, hole: tuple[int, int], width: int = 60) -> np.ndarray:
    """(5, width) disparities: ``left_d`` left of the hole, ``right_d`` right of it."""
    row = np.full(width, left_d, np.float32)
    row[hole[1]:] = right_d
    row[hole[0]:hole[1]] = np.nan
    return np.repeat(row[None], 5, axis=0)


def test_foreground_beyond_occlusion_is_the_far_end_of_a_hole_wider_than_the_step():
    from recon3d.stereo.match import OCCLUSION_MARGIN_PX, foreground_beyond_occlusion

    # ground at 10 px, a roof at 18 px: the 8 px next to the ground can be hidden
    # ground, the rest of the 20 px hole both images see
    disp = _row_with_hole(10.0, 18.0, (20, 40))
    best = np.where(np.isfinite(disp), disp, 17.0)  # the rejected matches lean to the roof
    fg = foreground_beyond_occlusion(disp, best, np.where(np.isfinite(disp), disp, 10.0))
    first = 20 + int(8 + OCCLUSION_MARGIN_PX)
    assert fg[:, first:40].all() and not fg[:, :first].any() and not fg[:, 40:].any()
    # rejected matches nearer the ground: the hole stays background
    assert not foreground_beyond_occlusion(disp, np.where(np.isfinite(disp), disp, 11.0), disp).any()
    # a hole no wider than the step is all occlusion
    narrow = _row_with_hole(10.0, 18.0, (20, 28))
    assert not foreground_beyond_occlusion(narrow, np.where(np.isfinite(narrow), narrow, 17.0), narrow).any()
    # a street between two roofs: its left side stands above the background around
    street = _row_with_hole(18.0, 19.0, (20, 40))
    assert not foreground_beyond_occlusion(street, np.full_like(street, 19.0), np.full_like(street, 10.0)).any()


def test_ground_hidden_in_a_courtyard_is_filled_from_the_ground_not_the_roof_around_it():
    """A courtyard open to the left, partly hidden from the right image by the wing
    right of it: its column neighbours are roof, and the second smallest neighbour (the
    rule for a mismatch) would raise it to the roof."""
    from recon3d.stereo.match import _fill_background

    ground, roof = 10.0, 30.0
    disp = np.full((60, 120), ground, np.float32)
    disp[5:56, 60:100] = roof  # the wing
    disp[5:16, 20:100] = roof  # the two arms around the courtyard
    disp[45:56, 20:100] = roof
    disp[16:45, 20:60] = np.nan  # the courtyard, 40 px wide
    disp[25:30, 85:90] = np.nan  # a hole in the roof, which the right image sees
    filled = _fill_background(disp)
    # the 20 px (the step from ground to roof) next to the wing: hidden ground
    assert np.all(filled[16:45, 40:60] == ground)
    # the rest both images see: a mismatch, left to the neighbours
    assert np.all(filled[16:45, 20:38] == roof)
    assert np.all(filled[25:30, 85:90] == roof)


def test_a_stray_low_match_above_a_hidden_hole_is_not_taken_for_the_ground():
    """Only a lowest neighbour on the left (where the ground behind a raised surface
    lies) is taken: a stray low match above the hole is not the ground."""
    from recon3d.stereo.match import _fill_background

    ground, roof = 10.0, 30.0
    disp = np.full((120, 120), ground, np.float32)
    disp[:, 60:100] = roof
    disp[5:, 40:60] = np.nan  # ground hidden behind the roof, open only at the top
    disp[4, 40:60] = 2.0  # a row of stray matches under the ground at its top
    assert np.all(_fill_background(disp)[5:, 40:60] == ground)  # the left neighbour


def test_match_fills_the_far_end_of_a_wide_hole_from_the_surface_beside_it():
    """End to end: a step the matcher cannot match on one side of a raised block."""
    rng = np.random.default_rng(3)
    h, w, d_ground, d_roof = 120, 200, 4, 20
    right = rng.uniform(0, 255, (h, w)).astype(np.float32)
    left = np.roll(right, d_ground, axis=1)
    left[30:90, 100:160] = np.roll(right, d_roof, axis=1)[30:90, 100:160]  # the raised block
    left[30:90, 100:130] = rng.uniform(0, 255, (60, 30))  # its left half unmatchable
    params = MatchParams(min_disparity=0, max_disparity=32, fill_foreground=True)
    with_fg = match(left, right, params)
    without = match(left, right, dataclasses.replace(params, fill_foreground=False))
    core = np.s_[40:80, 118:128]  # beyond the 16 px occlusion width from the ground side
    assert np.median(without.disparity[core]) < 8  # background fill: the ground
    assert with_fg.foreground[core].mean() > 0.5
    assert np.median(with_fg.disparity[core]) > 14  # taken for the block


def _ridge_scene(hole_colour_split: int, beyond: str = "ridge"):
    """One row, repeated: matched ground at 10 px up to column 19, a hole over 20..49,
    the ridge at 40 px from column 50 on (falling away, or flat); the left image green
    up to ``hole_colour_split`` and red from there (RGB on a 0..255 scale, with a little
    texture)."""
    w = 80
    row = np.full(w, 10.0, np.float32)
    row[50:] = 40.0 - (np.arange(w - 50) * 0.5 if beyond == "ridge" else 0.0)
    row[20:50] = np.nan
    disp = np.repeat(row[None], 6, axis=0)
    rng = np.random.default_rng(0)
    image = np.empty((6, w, 3), np.float32)
    image[:, :hole_colour_split] = (70, 110, 50)  # grass
    image[:, hole_colour_split:] = (160, 75, 55)  # tiles
    image += rng.normal(0, 4, image.shape)
    return disp, np.where(np.isfinite(disp), disp, 10.0), np.clip(image, 0, 255).astype(np.float32)


def test_faces_by_colour_split_the_hole_where_the_roof_colour_starts():
    from recon3d.stereo.match import faces_by_colour

    disp, background, image = _ridge_scene(35)
    face, value = faces_by_colour(disp, background, image)
    # the face spans the red part of the hole; the green part is the hidden ground
    assert face[:, 35:50].all() and not face[:, :35].any() and not face[:, 50:].any()
    # its lower edge lands where the last ground pixel (19, at 10 px) lands in the
    # right image: 35 - 26 = 19 - 10; then a ramp up to the ridge's 40 px
    np.testing.assert_allclose(value[:, 35], 26.0)
    assert np.all(np.diff(value[0, 35:50]) > 0) and value[0, 49] < 40.0
    # a flat roof's edge holds no face beyond the hole
    flat, background, image = _ridge_scene(35, beyond="flat")
    assert not faces_by_colour(flat, background, image)[0].any()
    # sides alike in colour: nothing to tell the face by
    disp, background, image = _ridge_scene(35)
    image[:] = image[:, :1]
    assert not faces_by_colour(disp, background, image)[0].any()
    # a dark shadow, unlike both sides, in the roof-side part: left alone
    disp, background, image = _ridge_scene(35)
    image[:, 35:50] = 20
    assert not faces_by_colour(disp, background, image)[0].any()


def _raised_block_pair(seed: int = 5):
    """A colour pair of random texture: ground at 4 px, a block at 20 px over columns
    100..159 of rows 30..89 (left image); the left image built from the right one, so
    every left pixel has its match."""
    rng = np.random.default_rng(seed)
    h, w, d_ground, d_roof = 120, 220, 4, 20
    right = cv2.GaussianBlur(rng.uniform(0, 255, (h, w, 3)).astype(np.float32), (0, 0), 0.7)
    truth = np.full((h, w), float(d_ground), np.float32)
    truth[30:90, 100:160] = d_roof
    cols = np.arange(w)[None, :] - truth.astype(int)
    left = right[np.arange(h)[:, None], np.clip(cols, 0, w - 1)]
    return left, right, truth


def test_sharpen_steps_gives_a_roof_carried_onto_the_street_back_to_the_street():
    from recon3d.stereo.match import sharpen_steps

    left, right, truth = _raised_block_pair()
    disp = truth.copy()
    disp[30:90, 97:100] = 20.0  # the census window's fattening: 3 street pixels at roof height
    disp[30:90, 160:162] = 20.0
    disp[:, :24] = np.nan  # no match left of the right image
    changed = sharpen_steps(disp, left, right, ratio=1.2)
    np.testing.assert_array_equal(disp[30:90, 97:100], 4.0)
    np.testing.assert_array_equal(disp[30:90, 160:162], 4.0)
    # the roof keeps all but its outermost pixels, whose 3 x 3 windows straddle the wall
    np.testing.assert_array_equal(disp[31:89, 101:159], 20.0)
    assert 5 * 60 <= changed <= 5 * 60 + 2 * 60 + 2 * 58
    # without the ratio's lean to the lower side, the street pixels still go back
    disp = truth.copy()
    disp[30:90, 97:100] = 20.0
    disp[:, :24] = np.nan
    sharpen_steps(disp, left, right, ratio=1.0)
    assert np.mean(disp[30:90, 97:100] == 4.0) > 0.9


def test_sharpen_steps_leaves_a_uniform_roof_that_its_disparity_explains_well():
    """On a roof of one flat colour every disparity matches about as well, sensor noise
    deciding: the pixel's own match, no worse than the pair's typical one, keeps it."""
    from recon3d.stereo.match import sharpen_steps

    left, right, truth = _raised_block_pair()
    roof = truth == 20.0
    left[roof] = (200.0, 60.0, 40.0)
    right[30:90, 80:140] = (200.0, 60.0, 40.0)  # where the left roof's matches land
    rng = np.random.default_rng(1)
    left += rng.normal(0.0, 3.0, left.shape).astype(np.float32)
    right += rng.normal(0.0, 3.0, right.shape).astype(np.float32)
    disp = truth.copy()
    disp[:, :24] = np.nan
    sharpen_steps(disp, left, right, ratio=1.2)
    np.testing.assert_array_equal(disp[31:89, 101:159], 20.0)
    # textured street pixels wrong by 10 px (within the window's reach of the street):
    # the lower side wins
    left, right, truth = _raised_block_pair()
    disp = truth.copy()
    disp[30:90, 97:100] = 14.0
    disp[:, :24] = np.nan
    sharpen_steps(disp, left, right, ratio=1.2)
    np.testing.assert_array_equal(disp[30:90, 97:100], 4.0)


def test_match_reports_the_pixels_it_gives_back_to_the_lower_side():
    """``MatchParams.sharpen_steps`` end to end: off by default, and when on, run.json's
    ``sharpened_percent`` says how much of the map it changed."""
    left, right, _ = _raised_block_pair()
    params = MatchParams(min_disparity=0, max_disparity=32, fill_foreground=True)
    plain = match(left, right, params)
    sharp = match(left, right, dataclasses.replace(params, sharpen_steps=1.2), guide=left, guide_right=right)
    assert "sharpened_percent" not in plain.params
    assert 0 < sharp.params["sharpened_percent"] < 1.0
