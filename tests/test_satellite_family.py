"""Satellite stereo on synthetic RPC pairs over known terrain: steep mountains, a town on hills.

The pairs (:mod:`recon3d.synthetic.satellite`) are two pushbroom images rendered from a
known city, 12-bit panchromatic with photon noise, their RPCs fitted to the cameras, so
the truth is exact. Scenes of 200 m (448 px) keep the tests fast;
``scripts/bench_satellite.py`` runs the full 400 m scenes beside the peers.
"""

import dataclasses
import json

import numpy as np
import pytest
import rasterio
from conftest import copy_scene, run_fails

from recon3d.io.geotiff import read_raster


def _scene(tmp_path_factory, name: str, size: float = 200.0):
    from recon3d.synthetic.satellite import SATELLITE_SCENES, write_satellite_scene

    folder = tmp_path_factory.mktemp(f"sat-{name}") / "scene"
    write_satellite_scene(folder, dataclasses.replace(SATELLITE_SCENES[name], size=size))
    return folder


def _run(folder, out, **kw):
    from recon3d.pipeline.run import run

    return run((folder / "img1.tif", folder / "img2.tif"), out, checkpoints=folder / "truth" / "checkpoints.csv", **kw)


def _score(folder, state):
    from recon3d.synthetic.score import score_stereo

    observed = np.isfinite(state.dsm.data) & ~state.dsm_filled & ~state.dsm_unobserved
    return score_stereo(folder, state.dsm, dtm=state.dtm, footprints=[b.footprint for b in state.city],
                        observed=observed)


@pytest.fixture(scope="module")
def mountain(tmp_path_factory):
    folder = _scene(tmp_path_factory, "mountain")
    state = _run(folder, folder.parent / "out")
    return folder, state, _score(folder, state)


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    folder = _scene(tmp_path_factory, "town")
    state = _run(folder, folder.parent / "out")
    return folder, state, _score(folder, state)


def test_the_rpcs_fit_the_cameras(mountain):
    folder, _, _ = mountain
    record = json.loads((folder / "truth" / "scene.json").read_text())
    assert max(record["rpc_fit_residual_px"]) < 1e-3
    with rasterio.open(folder / "img1.tif") as src:
        assert src.rpcs is not None and src.dtypes[0] == "uint16"


@pytest.mark.parametrize("which", ["mountain", "town"])
def test_dsm_against_the_truth(which, request):
    """Issue 16 targets: NMAD <= 0.5 m, |median| <= 0.3 m; the overlap matched, not filled."""
    folder, state, score = request.getfixturevalue(which)
    # measured: mountain NMAD 0.32 m, median -0.00 m; town 0.31 m, +0.05 m (highest point
    # per cell instead of the median: medians +0.15 m, a noise sigma high)
    assert score["dsm_nmad"] <= 0.5
    assert abs(score["dsm_median"]) <= 0.3
    assert score["coverage"] >= 99.0
    # measured 94 % (mountain: walls and steep faces one view does not see) and 96 % of
    # the common cells observed
    assert score["observed"] >= 90.0
    stereo = state.auto["stereo"]
    assert stereo["matched_percent"] >= 82.0  # measured 89 and 93 % of the overlap's pixels
    assert score["dsm_within_1m"] >= 87.0  # measured 91 %


def test_heights_searched_are_the_tie_points(mountain):
    """The searched interval comes from the tie points, not the RPC's blind height range."""
    folder, state, _ = mountain
    stereo = state.auto["stereo"]
    truth = read_raster(folder / "truth" / "dsm.tif").data
    low, high = float(np.nanmin(truth)), float(np.nanmax(truth))
    t_low, t_high = stereo["tie_heights_m"]
    assert low - 5 <= t_low and t_high <= high + 5  # ties lie on the surface
    search = stereo["tiles"]["per_tile"][0]["search_heights_m"]
    assert search[0] <= low and search[1] >= high - 2  # and cover it
    assert search[1] - search[0] < 1.5 * (high - low) + 25 and stereo["height_interval_m"] == search
    assert np.nanmin(state.dsm.data) >= t_low - 10.0


def test_tie_points_are_on_the_surface(mountain):
    """Tie points that pass the epipolar test triangulate onto the true surface."""
    import pyproj

    from recon3d.io.rpc import read_rpc_camera
    from recon3d.stereo.satellite import (
        _bias_from_ties,
        _epipolar_geometry,
        _tie_points,
        triangulate_ties,
    )

    folder, _, _ = mountain
    a, b = (read_rpc_camera(folder / f"img{i}.tif") for i in (1, 2))
    images = [rasterio.open(folder / f"img{i}.tif").read(1).astype(np.float32) for i in (1, 2)]
    t1, t2 = _tie_points(*images)
    shift, _ = _bias_from_ties(a, b, t1, t2, _epipolar_geometry(a, b)[-1])
    ties = triangulate_ties(a, b, t1, t2, shift)
    assert len(ties.height) >= 0.8 * ties.matched
    lon, lat = a.localize(ties.left[:, 1], ties.left[:, 0], ties.height)
    truth = read_raster(folder / "truth" / "dsm.tif")
    x, y = pyproj.Transformer.from_crs(4326, truth.crs, always_xy=True).transform(lon, lat)
    err = ties.height - truth.sample(x, y)
    err = err[np.isfinite(err)]
    assert np.median(np.abs(err)) < 0.5 and np.mean(np.abs(err) < 2.0) > 0.85


def test_products_only_where_both_images_see(town):
    """No DSM or DTM beyond the common area; buildings only on matched cells."""
    folder, state, score = town
    dsm, dtm = state.dsm.data, state.dtm.data
    assert np.array_equal(np.isfinite(dsm), np.isfinite(dtm))
    views = read_raster(folder / "truth" / "views.tif")
    xs, ys = state.dsm.cell_centers()
    x, y = np.meshgrid(xs, ys)
    seen = views.sample(x.ravel(), y.ravel(), bilinear=False).reshape(dsm.shape)  # NaN off the truth grid
    outside = np.isfinite(dsm) & (seen < 2)  # cells not both images have in frame
    assert outside.sum() <= 0.002 * np.isfinite(dsm).sum()
    # measured completeness 92 %, correctness 90 % of the truth footprints
    assert score["footprint_completeness"] >= 80.0 and score["footprint_correctness"] >= 80.0


def test_dem_narrows_the_search(mountain, tmp_path):
    folder, state, _ = mountain
    narrowed = _run(folder, tmp_path / "out", dem=folder / "truth" / "coarse_dem.tif")
    a = state.auto["stereo"]["tiles"]["per_tile"][0]
    b = narrowed.auto["stereo"]["tiles"]["per_tile"][0]
    assert "DEM" in b["search_from"]
    assert b["search_heights_m"][0] >= a["search_heights_m"][0] - 1e-6
    assert b["search_heights_m"][1] <= a["search_heights_m"][1] + 1e-6
    score = _score(folder, narrowed)
    assert score["dsm_nmad"] <= 0.5


def test_second_image_that_sees_too_little(mountain, tmp_path):
    """The second image cut to its corner: an error naming both files, nothing written."""
    folder, _, _ = mountain
    scene = copy_scene(folder, tmp_path)
    with rasterio.open(scene / "img2.tif") as src:
        profile, data, rpcs = src.profile, src.read(1), src.rpcs
    profile.update(width=150, height=150, tiled=False)
    profile.pop("blockxsize", None), profile.pop("blockysize", None)
    with rasterio.open(scene / "img2.tif", "w", **profile, rpcs=rpcs) as dst:
        dst.write(data[:150, :150], 1)
    run_fails([scene / "img1.tif", scene / "img2.tif"], tmp_path, "img1.tif and", "img2.tif do not overlap enough")


def test_image_with_another_images_rpc(mountain, town, tmp_path):
    """A pair whose RPCs describe other ground: refused before matching."""
    m, _, _ = mountain
    t, _, _ = town
    run_fails([m / "img1.tif", t / "img2.tif"], tmp_path, "img1.tif and", "do not overlap")


def test_dem_that_misses_the_scene(mountain, tmp_path):
    from affine import Affine

    from recon3d.core.raster import Raster
    from recon3d.io.geotiff import write_raster

    folder, _, _ = mountain
    dem = read_raster(folder / "truth" / "coarse_dem.tif")
    far = Raster(dem.data, Affine(dem.transform.a, 0, dem.transform.c + 50_000, 0, dem.transform.e, dem.transform.f), dem.crs)
    write_raster(far, tmp_path / "far_dem.tif")
    run_fails([folder / "img1.tif", folder / "img2.tif", "--dem", tmp_path / "far_dem.tif"], tmp_path,
              "far_dem.tif", "does not cover")


def test_tiles_stitch_without_loss(mountain, tmp_path):
    """Four 224 px tiles, each with its own affine cameras, bias and heights: as good as one."""
    from recon3d.config import PipelineConfig

    folder, _, whole = mountain
    state = _run(folder, tmp_path / "out", config=PipelineConfig().with_overrides(["stereo.tile_size=224"]))
    tiles = state.auto["stereo"]["tiles"]
    assert tiles["count"] == 4 and tiles["failed"] == 0
    assert all(t["bias_tie_points"] >= 10 or "model" in t["bias_from"] for t in tiles["per_tile"])
    score = _score(folder, state)
    # measured NMAD 0.36 m whole, 0.36 m tiled; observed 91 % both
    assert score["dsm_nmad"] <= whole["dsm_nmad"] + 0.05
    assert score["observed"] >= whole["observed"] - 2.0
    assert score["coverage"] >= 99.0
    # no seam: along the tiles' edges the DSM errs no more than elsewhere
    import pyproj

    from recon3d.io.rpc import read_rpc_camera
    from recon3d.synthetic.score import _on_grid

    dsm = state.dsm
    error = np.abs(dsm.data - _on_grid(read_raster(folder / "truth" / "dsm.tif"), dsm))
    xs, ys = dsm.cell_centers()
    x, y = np.meshgrid(xs, ys)
    lon, lat = pyproj.Transformer.from_crs(dsm.crs, 4326, always_xy=True).transform(x.ravel(), y.ravel())
    row, col = read_rpc_camera(folder / "img1.tif").project(lon, lat, np.nan_to_num(dsm.data.ravel()))
    edge = np.abs(np.c_[row, col] - 224).min(axis=1).reshape(dsm.shape) < 3  # within 3 px of a core edge
    ok = np.isfinite(error)
    assert (edge & ok).sum() > 500
    # measured 0.27 m on the edges, 0.25 m elsewhere (median; 90th percentile 1.05 and 1.12 m)
    assert np.median(error[edge & ok]) <= np.median(error[~edge & ok]) + 0.1


def test_self_check_against_the_tie_points(mountain):
    """Every run compares the dense disparities with the SIFT tie points; a contradiction stops it."""
    from recon3d.errors import InputError
    from recon3d.stereo.satellite import tie_self_check

    _, state, _ = mountain
    check = state.auto["stereo"]["self_check"]
    assert check["tie_points"] >= 100 and check["median_px"] < 0.4  # measured 0.16 px
    assert check["within_1px_percent"] >= 90.0  # measured 98.6 %
    ok, warning = tie_self_check(np.full(50, 0.2), 1.0, "a and b")
    assert warning is None and ok["within_1px_percent"] == 100.0
    _, warning = tie_self_check(np.r_[np.full(30, 0.2), np.full(20, 1.5)], 1.0, "a and b")
    assert "60 % of 50 tie points" in warning
    with pytest.raises(InputError, match="contradicts the pair's own tie points"):
        tie_self_check(np.full(50, 3.0), 1.2, "a and b")


def test_dem_without_crs(mountain, tmp_path):
    folder, _, _ = mountain
    with rasterio.open(folder / "truth" / "coarse_dem.tif") as src:
        data, profile = src.read(1), src.profile
    profile.pop("crs", None)
    with rasterio.open(tmp_path / "bare.tif", "w", **profile) as dst:
        dst.write(data, 1)
    run_fails([folder / "img1.tif", folder / "img2.tif", "--dem", tmp_path / "bare.tif"], tmp_path,
              "bare.tif", "has no CRS")
