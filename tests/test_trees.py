"""Buildings among trees (issue 19 items 1 and 2) on surveys of the random LiDAR family.

While developing, seeds 0 to 39 were looked at (0, 7, 13, 20, 22, 25, 31 in detail),
and 43, 54, 60, 74, 75, 78, 105, 109, 118 once the rules existed, 74 and 154 for the
crowns found after roof modelling; the other surveys here (40 to 59, 100 to 129) were
scored only in the batch tables of ``scripts/bench_trees.py``.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import shapely
from affine import Affine

from recon3d.buildings import classes, detect
from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster
from recon3d.synthetic.city import make_city
from recon3d.synthetic.lidar import random_survey

_SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
if str(_SCRIPTS) not in sys.path:  # the benchmark imports its helpers (_bench) as a script would
    sys.path.insert(0, str(_SCRIPTS))
_SPEC = importlib.util.spec_from_file_location("bench_trees", _SCRIPTS / "bench_trees.py")
bench = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench)

CFG = BuildingsConfig()
UNITS = Units()


@pytest.mark.parametrize("seed, group", [
    (52, "groves"),  # a 60 m dense town with a grove (before: not measured, the family had none)
    (55, "groves"),
    (42, "over"),  # crowns over the roof
    (44, "beside"),
    (47, "beside"),
])
def test_trees_are_not_buildings(tmp_path, seed, group):
    row = bench.run_case(seed, tmp_path)
    assert row["group"] == group
    assert row["buildings"] == row["true_buildings"] and row["false_detections"] == 0
    # against the true footprints: measured 98.95-99.84 % complete, 95.7-98.9 % correct
    # (99.1-100 % and 93.2-97.9 % while the outlines were drawn through each fine cell's
    # highest point, half a cell wide of the walls on average)
    assert row["completeness"] >= 98.5 and row["correctness"] >= 95.5
    assert row["class_completeness"] >= 95.0 and row["class_correctness"] >= 95.0  # against the true classes
    assert row["vegetation_as_building"] <= 0.02 * row["vegetation_points"]  # measured 0 %


@pytest.mark.parametrize("seed, group, before", [
    # held out; "before" is what the detection before issue 19 gave (buildings found / true)
    (104, "over", "2/1"),
    (106, "groves", "7/4"),
    (112, "beside", "7/2"),
    (114, "beside", "2/1"),
    (122, "groves", "7/2"),
])
def test_trees_are_not_buildings_held_out(tmp_path, seed, group, before):
    row = bench.run_case(seed, tmp_path)
    assert row["group"] == group
    assert row["buildings"] == row["true_buildings"] and row["false_detections"] == 0
    # measured 98.0-100 % complete, 89.0-99.3 % correct (98.6-100 % and 84.4-95.9 %
    # with the outlines drawn through each fine cell's highest point)
    assert row["completeness"] >= 97.5 and row["correctness"] >= 88.0
    assert row["class_completeness"] >= 94.5  # measured 94.8-99.2 % (97.6-99.9 % before)
    # measured 96.2-99.6 % (91.5-98.8 % with the highest points; before issue 19, against
    # the true footprints: 52.6-83.7 %)
    assert row["class_correctness"] >= 96.0
    # measured 0-0.18 % (0-3.2 % with each point's own echo as the only multi-return
    # evidence; before issue 19: 20.8-71.6 %)
    assert row["vegetation_as_building"] <= 0.02 * row["vegetation_points"]


def test_sparse_crowns_with_no_roof_plane_are_trees(tmp_path):
    """Seed 154 (1.2 points per m2, crowns splitting 5 % of their pulses, trees beside
    the houses): two crowns of 25 m2 passed the detection, whose planar test is eased
    at such densities, and roof modelling found no plane in either. Before: 6 buildings
    for 4, 34.5 % of the vegetation points labelled building."""
    row = bench.run_case(154, tmp_path)
    assert row["buildings"] == row["true_buildings"] == 4 and row["false_detections"] == 0
    assert row["vegetation_as_building"] <= 0.02 * row["vegetation_points"]
    # measured 96.6 % / 95.8 % (98.6 % / 94.2 % with the outlines drawn through each fine
    # cell's highest point; the crowns cost nothing)
    assert row["completeness"] >= 96.0 and row["correctness"] >= 95.5


def test_buildings_that_contradict_the_input_classes_are_a_warning(tmp_path, monkeypatch):
    """The self-check against the provider's classes: with the crowns of seed 154 kept
    as buildings (the rule above switched off), 28.4 % of its vegetation points are
    building in cloud.laz, and the run says so on the terminal and in the report."""
    from recon3d.pipeline import run as pipeline

    monkeypatch.setattr(pipeline, "_drop_crowns", lambda r: None)
    spec = random_survey(154)
    spec["file"].update(classes=True, with_crs=True)
    from recon3d.synthetic.lidar import write_survey

    path, _ = write_survey(tmp_path / "in", spec)
    state = pipeline.run(path, tmp_path / "out")
    share = state.report["buildings_vs_provider_area"]["vegetation_as_building_percent"]
    assert share > 25.0
    assert any("input's own classes call vegetation" in w for w in state.warnings), state.warnings
    assert any("input's own classes call vegetation" in w for w in state.report["warnings"])


def test_groves_in_the_family():
    """Two surveys in five with trees get groves: closed canopies of 75 m2 and more."""
    seeds = [s for s in range(40, 80) if random_survey(s)["city"].get("groves")]
    assert 5 <= len(seeds) <= 20
    city = make_city(**random_survey(seeds[0])["city"])
    crowns = shapely.union_all([shapely.Point(t.x, t.y).buffer(t.crown_radius) for t in city.trees])
    parts = getattr(crowns, "geoms", [crowns])
    assert max(p.area for p in parts) >= 75.0
    # the surveys of the earlier family keep every value they had
    assert "groves" not in random_survey(5)["city"] and random_survey(5)["city"]["trees"] == "none"


def _raster(data, res=0.5):
    data = np.asarray(data, np.float32)
    return Raster(data, Affine(res, 0.0, 0.0, 0.0, -res, data.shape[0] * res))


def test_blob_off_planes_is_vegetation():
    ndsm = np.zeros((80, 80))
    ndsm[10:30, 10:30] = 6.0  # a flat roof, 100 m2
    ndsm[45:70, 45:70] = 9.0  # a dense canopy, 156 m2, smooth in the DSM and with no vegetation evidence
    planar = np.ones(ndsm.shape)
    planar[45:70, 45:70] = 0.3
    none = np.zeros(ndsm.shape, np.float32)
    blobs = detect.find_blobs(_raster(ndsm), none, CFG, UNITS, planar=planar)
    assert blobs.kept.sum() == 1 and blobs.reason.count("vegetation") == 1
    assert detect.find_blobs(_raster(ndsm), none, CFG, UNITS).kept.sum() == 2  # without planarity: two buildings


def test_with_colours_planarity_alone_rejects_no_blob():
    """A survey with colours tells crowns by their colour: a smooth blob with no
    vegetation point is a roof however noisy its points about their planes (a stereo
    cloud's gables), and one with a few vegetation points is still judged by planarity."""
    ndsm = np.zeros((80, 80))
    ndsm[10:30, 10:30] = 6.0
    ndsm[45:70, 45:70] = 9.0
    planar = np.ones(ndsm.shape)
    planar[45:70, 45:70] = 0.3
    none = np.zeros(ndsm.shape, np.float32)
    assert detect.find_blobs(_raster(ndsm), none, CFG, UNITS, planar=planar, colour=True).kept.sum() == 2
    some = none.copy()
    some[45:70, 45:70] = 0.02  # green points in the canopy
    blobs = detect.find_blobs(_raster(ndsm), some, CFG, UNITS, planar=planar, colour=True)
    assert blobs.kept.sum() == 1 and blobs.reason.count("vegetation") == 1


def test_points_above_the_roof_are_not_building():
    grid = _raster(np.zeros((40, 40)))
    labels = np.zeros((40, 40), np.int32)
    labels[5:35, 5:35] = 1
    rng = np.random.default_rng(3)
    xy = rng.uniform(3.0, 17.0, (400, 2))
    z = np.where(np.arange(400) < 300, 6.0, 8.0)  # 300 roof points, 100 crown points 2 m over the roof
    z = z + rng.normal(0.0, 0.03, 400)
    cloud = PointCloud(np.column_stack([xy, z]))
    rough = np.where(np.arange(400) < 300, 0.02, 0.4)
    out = classes.point_classes(
        cloud, np.zeros(400, bool), labels, grid, grid, CFG, UNITS,
        roof_surface=np.full(400, 6.0), roughness=rough, tolerance=0.25, plane_tolerance=0.1,
    )
    inside = (xy >= 2.5).all(axis=1) & (xy < 17.5).all(axis=1)
    assert np.all(out[:300][inside[:300]] == ASPRS.BUILDING)
    assert np.all(out[300:][inside[300:]] == ASPRS.HIGH_VEGETATION)


def test_points_a_roof_would_hide_are_not_building():
    """Below the modelled roof, deep inside the outline, a scan sees no building: a
    crown the footprint took in; near the outline, planar points are its walls."""
    grid = _raster(np.zeros((40, 40)))
    labels = np.zeros((40, 40), np.int32)
    labels[4:36, 4:36] = 1  # x, y 2..18
    xy = np.array([[10.0, 10.0], [10.0, 10.2], [2.3, 10.0], [2.3, 10.2]])
    cloud = PointCloud(np.column_stack([xy, [3.0, 3.0, 3.0, 3.0]]))  # 3 m under a 6 m roof
    out = classes.point_classes(
        cloud, np.zeros(4, bool), labels, grid, grid, CFG, UNITS,
        roof_surface=np.full(4, 6.0), roughness=np.array([0.02, 0.4, 0.02, 0.4]), tolerance=0.25, plane_tolerance=0.1,
    )
    assert out[0] != ASPRS.BUILDING and out[1] == ASPRS.HIGH_VEGETATION  # deep inside: hidden by a roof
    assert out[2] == ASPRS.BUILDING and out[3] == ASPRS.HIGH_VEGETATION  # at the outline: a wall, a crown
