"""Blocks split into buildings at height steps (issue 19 item 3).

A row of attached houses comes out of the nDSM as one connected block; it is cut where
the roofs step by more than the slope explains (``split_step``), into pieces that are
buildings (:func:`recon3d.buildings.detect.split_at_steps`). Ridges, valleys and
dormers are no party walls; a row of equal roofs stays whole; given footprints are
never split. Scene: houses 10 m deep on 0.5 m cells, 5 cm noise, the row turned 25
degrees off the grid.
"""

import numpy as np
import pytest
import shapely
import shapely.affinity
from affine import Affine

from recon3d.buildings import detect
from recon3d.config import BuildingsConfig
from recon3d.core.geo import Units
from recon3d.core.raster import Raster

UNITS = Units()
RES, SIZE, ANGLE = 0.5, 120, 25.0
ORIGIN = (1000.0, 2000.0)
CENTRE = (ORIGIN[0] + SIZE * RES / 2, ORIGIN[1] + SIZE * RES / 2)


def _row(widths, eaves, rise=0.0, *, ridge="along", depth=10.0, dormer=None, seed=0):
    """nDSM (Raster) of a row of houses and their true outlines.

    ``ridge``: "along" the row (the slope runs across the party walls' direction, at
    right angles to them) or "across" it (each house a gable of its own, valleys between);
    ``dormer``: (house, width, depth, height above the eaves) of a box on the front slope.
    """
    x0, y0 = CENTRE[0] - sum(widths) / 2, CENTRE[1] - depth / 2
    edges = x0 + np.r_[0.0, np.cumsum(widths)]
    transform = Affine(RES, 0.0, ORIGIN[0], 0.0, -RES, ORIGIN[1] + SIZE * RES)
    c, r = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    wx, wy = transform.c + c * RES, transform.f - r * RES
    t = np.radians(ANGLE)  # back into the row's own frame
    dx, dy = wx - CENTRE[0], wy - CENTRE[1]
    lx, ly = CENTRE[0] + dx * np.cos(t) + dy * np.sin(t), CENTRE[1] - dx * np.sin(t) + dy * np.cos(t)
    house = np.searchsorted(edges, lx) - 1
    inside = (house >= 0) & (house < len(widths)) & (ly >= y0) & (ly <= y0 + depth)
    k = np.clip(house, 0, len(widths) - 1)
    if ridge == "along":
        shape = 1 - np.abs(ly - (y0 + depth / 2)) / (depth / 2)
    else:
        mid, half = (edges[k] + edges[k + 1]) / 2, np.asarray(widths)[k] / 2
        shape = 1 - np.abs(lx - mid) / half
    z = np.asarray(eaves, float)[k] + rise * np.clip(shape, 0, 1)
    if dormer is not None:
        i, w, d, top = dormer
        mid = (edges[i] + edges[i + 1]) / 2
        on = (k == i) & (np.abs(lx - mid) <= w / 2) & (ly >= y0 + 1.0) & (ly <= y0 + 1.0 + d)
        z = np.where(on, np.maximum(z, eaves[i] + top), z)
    z = np.where(inside, z, 0.0) + np.random.default_rng(seed).normal(0, 0.05, z.shape)
    houses = [
        shapely.affinity.rotate(shapely.box(edges[i], y0, edges[i + 1], y0 + depth), ANGLE, origin=CENTRE)
        for i in range(len(widths))
    ]
    return Raster(z.astype(np.float32), transform), houses


def _detect(ndsm, **overrides):
    return detect.detect_buildings(ndsm, np.zeros(ndsm.shape, bool), BuildingsConfig(**overrides), UNITS)


def _best_iou(houses, polygons):
    return [max(h.intersection(p).area / h.union(p).area for p in polygons) for h in houses]


@pytest.mark.parametrize(
    "widths, eaves, rise, ridge",
    [
        ([6.0, 7.0, 5.5, 6.5], [7.0, 8.2, 9.5, 8.3], 0.0, "along"),  # flat roofs, steps of 1.2-1.3 m
        ([6.0, 7.0, 6.5], [7.0, 8.0, 9.4], 3.0, "along"),  # gables along the row, 1-1.4 m steps
        ([6.5, 7.0, 6.0, 7.5], [6.0, 7.5, 6.2, 7.4], 2.5, "across"),  # a gable each, 1.2-1.5 m steps
    ],
)
def test_row_with_steps_splits_into_its_houses(widths, eaves, rise, ridge):
    """Every step is under the 2 m of ``split_height``: without the step split the row
    is one building; with it, one building per house, each IoU >= 0.8 with its house."""
    ndsm, houses = _row(widths, eaves, rise, ridge=ridge)
    assert len(_detect(ndsm, split_step=0.0)) == 1
    polygons = _detect(ndsm)
    assert len(polygons) == len(houses)
    assert min(_best_iou(houses, polygons)) >= 0.8, _best_iou(houses, polygons)


@pytest.mark.parametrize("ridge, rise", [("along", 4.0), ("across", 5.0), ("along", 7.0)])
def test_ridge_roof_is_not_split(ridge, rise):
    """A steep gable (up to 54 degrees, 1.4 m a cell across the grid) is one building:
    its steps between cells are the slope's, ridge and eaves included."""
    ndsm, (house,) = _row([12.0], [6.0], rise, ridge=ridge)
    (polygon,) = _detect(ndsm)
    assert _best_iou([house], [polygon])[0] >= 0.9


def test_dormer_does_not_split_its_house():
    """A dormer 3 m wide, 2.5 m deep, its front 1.5 m out of the slope, stays with its
    house (under ``min_area``), and its neighbours are still cut off at their steps."""
    ndsm, houses = _row([7.0, 9.0, 7.0], [6.0, 7.5, 6.0], 3.5, dormer=(1, 3.0, 2.5, 2.5))
    polygons = _detect(ndsm)
    assert len(polygons) == 3
    assert min(_best_iou(houses, polygons)) >= 0.8


@pytest.mark.parametrize("pitch", [30.0, 35.0])
def test_gables_of_equal_houses_part_at_their_valleys(pitch):
    """A terrace of equal houses, each its own gable across the row (no step at all):
    the valleys between the gables cut it into its houses down to 30 degrees of pitch
    (a 0.8 m rule kept every terrace under 39 degrees whole)."""
    widths = [6.5, 7.0, 6.0, 7.5]
    rise = np.tan(np.radians(pitch)) * min(widths) / 2
    ndsm, houses = _row(widths, [7.0] * 4, rise, ridge="across")
    polygons = _detect(ndsm)
    assert len(polygons) == len(houses)
    assert min(_best_iou(houses, polygons)) >= 0.8, _best_iou(houses, polygons)


def test_row_of_equal_roofs_stays_one_building():
    """Nothing in the heights tells equal houses apart: the row stays one block."""
    for rise, ridge in ((0.0, "along"), (3.0, "along")):
        ndsm, houses = _row([6.0, 6.0, 6.0, 6.0], [8.0] * 4, rise, ridge=ridge)
        (polygon,) = _detect(ndsm)
        assert polygon.intersection(shapely.union_all(houses)).area >= 0.95 * polygon.area


def test_narrow_annex_stays_attached():
    """A lean-to 3.5 m wide (under ``min_split_width``), 1 m lower than its house, is no
    building of its own; a 5 m wide one is."""
    ndsm, houses = _row([10.0, 3.5], [8.0, 7.0])
    (polygon,) = _detect(ndsm)
    assert polygon.area == pytest.approx(shapely.union_all(houses).area, rel=0.1)
    assert len(_detect(ndsm, min_split_width=0.0)) == 2
    ndsm, houses = _row([10.0, 5.0], [8.0, 7.0])
    assert min(_best_iou(houses, _detect(ndsm))) >= 0.8


def test_step_strength_ignores_slopes_and_finds_steps():
    """The misfit is 0 on a steep plane and over a ridge, the step height at a party wall."""
    ndsm, _ = _row([8.0, 8.0], [6.0, 7.0], 5.0, ridge="along")
    labels = (ndsm.data > 2.5).astype(np.int32)
    strength = detect.step_strength(ndsm.data, labels, min_step=0.3)
    steep, _ = _row([16.0], [6.0], 5.0, ridge="across")
    assert (detect.step_strength(steep.data, (steep.data > 2.5).astype(np.int32), min_step=0.3) > 0).mean() < 0.01
    # the party wall: a line of cells with misfits near the 1 m step
    assert np.median(strength[strength > 0]) == pytest.approx(1.0, abs=0.25)


def test_given_footprints_are_never_split(ign_footprints_run):
    """With --footprints the buildings are the footprints, one each, none a BuildingPart."""
    s = ign_footprints_run
    assert [b.id for b in s.city] == [f.id for f in s.footprints]
    assert all(b.parent is None for b in s.city)


def _l_house(pitch, *, wing=16.0, depth=8.0, seed=1):
    """nDSM of a cross-gabled L house (one building) turned ``ANGLE`` off the grid.

    Wing A runs along x with its ridge along x; wing B rises from A's back wall along y,
    its ridge meeting A's: two valleys run from the inner corners to where the ridges
    meet, sloping ``pitch`` degrees on both sides.
    """
    transform = Affine(RES, 0.0, ORIGIN[0], 0.0, -RES, ORIGIN[1] + SIZE * RES)
    c, r = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    t = np.radians(ANGLE)
    dx, dy = transform.c + c * RES - CENTRE[0], transform.f - r * RES - CENTRE[1]
    lx, ly = dx * np.cos(t) + dy * np.sin(t) + wing / 2, -dx * np.sin(t) + dy * np.cos(t) + wing / 2
    rise = np.tan(np.radians(pitch)) * depth / 2
    in_a = (lx >= 0) & (lx <= wing) & (ly >= 0) & (ly <= depth)
    in_b = (lx >= 0) & (lx <= depth) & (ly >= depth / 2) & (ly <= wing)
    za = np.where(in_a, 6.0 + rise * (1 - np.abs(ly - depth / 2) / (depth / 2)), 0.0)
    zb = np.where(in_b, 6.0 + rise * (1 - np.abs(lx - depth / 2) / (depth / 2)), 0.0)
    z = np.maximum(za, zb) + np.random.default_rng(seed).normal(0, 0.05, za.shape)
    footprint = shapely.union_all([shapely.box(0, 0, wing, depth), shapely.box(0, depth / 2, depth, wing)])
    footprint = shapely.affinity.translate(footprint, CENTRE[0] - wing / 2, CENTRE[1] - wing / 2)
    return Raster(z.astype(np.float32), transform), shapely.affinity.rotate(footprint, ANGLE, origin=CENTRE)


@pytest.mark.parametrize("pitch", [30.0, 40.0, 45.0])
def test_l_shaped_gable_house_stays_one_building(pitch):
    """The valleys of a cross-gabled L house are no party walls (the Delft strip has such
    houses): up to 45 degrees of pitch it is one building, IoU >= 0.85 with its outline,
    and not one cell of its valleys is taken for a cut (a 0.4 m rule took a dozen)."""
    ndsm, house = _l_house(pitch)
    labels = (ndsm.data > 2.5).astype(np.int32)
    cut = detect.valley_depth(ndsm.data, labels, reach=round(detect.VALLEY_REACH / RES), min_drop=detect.VALLEY_DROP)
    assert not cut.any()
    (polygon,) = _detect(ndsm)
    assert _best_iou([house], [polygon])[0] >= 0.85


@pytest.mark.parametrize("shift", detect.NEIGHBOURS)
def test_neighbour_views_pair_each_cell_with_the_one_behind(shift):
    a = np.arange(5 * 7).reshape(5, 7)
    here, there = detect._neighbours(shift)
    padded = np.pad(a, 1, constant_values=-1)
    r, c = shift
    behind = padded[1 - r : 6 - r, 1 - c : 8 - c]  # the cell (r, c) before each, -1 outside
    assert np.array_equal(a[there], behind[here])
    assert (behind == -1).sum() == a.size - a[here].size  # every cell with a neighbour is paired


def test_distance_is_the_euclidean_transform():
    from scipy import ndimage

    rng = np.random.default_rng(5)
    mask = rng.random((80, 120)) > 0.03
    mask[:, :4] = True  # open to the grid's edge
    np.testing.assert_allclose(detect._distance(mask), ndimage.distance_transform_edt(mask), atol=1e-5)


def _mosaic() -> np.ndarray:
    """(240, 360) nDSM of rows of houses of every kind, some of them touching."""
    a, b, c = (_row(w, e, rise, ridge=ridge, seed=k)[0].data for k, (w, e, rise, ridge) in enumerate((
        ([6.0, 7.0, 5.5, 6.5], [7.0, 8.2, 9.5, 8.3], 0.0, "along"),
        ([6.0, 7.0, 6.5], [7.0, 8.0, 9.4], 3.0, "along"),
        ([6.5, 7.0, 6.0, 7.5], [6.0, 7.5, 6.2, 7.4], 2.5, "across"),
    )))
    touching = np.maximum(b, np.roll(a + 4.0 * (a > 2.5), 22, axis=0))  # a block higher by 4 m against b
    tiles = [[a, b, c], [c, touching, a]]
    return np.block(tiles).astype(np.float32)


def _split(height: np.ndarray) -> np.ndarray:
    labels, _ = detect.split_by_height(height, height > 2.5, 2.0)
    cfg = BuildingsConfig()
    return detect.split_at_steps(height, labels, RES, min_step=cfg.split_step, min_area=cfg.min_area,
                                 min_width=cfg.min_split_width, valley_drop=detect.VALLEY_DROP, valley_reach=detect.VALLEY_REACH)[0]


@pytest.mark.parametrize("window", [16, 50, 130])
def test_blocks_cut_a_window_at_a_time_as_over_the_whole_grid(monkeypatch, window):
    """Windows of any size give the labels of one window over the whole grid: each part
    is cut from its own cells and numbered as one labelling of the grid numbers it."""
    height = _mosaic()
    whole = _split(height)
    assert whole.max() >= 18  # the six rows' houses (two pairs of rows touch)
    monkeypatch.setattr(detect, "SPLIT_WINDOW", window)
    monkeypatch.setattr(detect, "STRIP_ROWS", 7)
    assert np.array_equal(_split(height), whole)


def test_components_by_height_are_those_of_the_whole_grid_graph(monkeypatch):
    """split_by_height window by window: the connected components of the graph of
    4-neighbours within ``split`` of each other, numbered in raster order of their first cells."""
    from scipy import sparse
    from scipy.sparse import csgraph

    rng = np.random.default_rng(3)
    height = np.round(rng.uniform(0.0, 6.0, (90, 70)), 0)
    mask = rng.uniform(size=height.shape) < 0.7
    rows, cols = np.nonzero(mask)
    index = np.full(height.shape, -1)
    index[rows, cols] = np.arange(len(rows))
    edges = []
    for dr, dc in ((0, 1), (1, 0)):
        a = mask[: mask.shape[0] - dr, : mask.shape[1] - dc] & mask[dr:, dc:]
        a &= np.abs(height[: mask.shape[0] - dr, : mask.shape[1] - dc] - height[dr:, dc:]) <= 1.0
        r, c = np.nonzero(a)
        edges.append(np.column_stack([index[r, c], index[r + dr, c + dc]]))
    e = np.concatenate(edges)
    n, comp = csgraph.connected_components(sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])),
                                                             shape=(len(rows), len(rows))), directed=False)
    expected = np.zeros(height.shape, np.int32)
    expected[rows, cols] = comp + 1
    monkeypatch.setattr(detect, "SPLIT_WINDOW", 8)
    labels, count = detect.split_by_height(height, mask, 1.0)
    assert count == n
    assert np.array_equal(labels, expected)


def test_roughness_by_strips_is_that_of_the_whole_grid(monkeypatch):
    """The 3 x 3 plane-fit roughness, strip by strip, has the whole grid's bits."""
    z = np.random.default_rng(5).normal(10.0, 2.0, (53, 41)).astype(np.float32)
    whole = detect._strip_roughness(z)
    monkeypatch.setattr(detect, "STRIP_ROWS", 5)
    assert np.array_equal(detect._roughness(z), whole)


def test_cut_straightness_is_the_rms_off_the_best_line():
    """A straight run of border edges is 0 off its line, at any angle; an L of two 10-cell
    arms is about 2 cells off it (no party wall), a staircase of one-cell steps 0.35."""
    t = np.arange(20.0)
    line = np.c_[t, 0.5 * t + 3.0]
    ell = np.r_[np.c_[np.zeros(10), np.arange(10.0)], np.c_[np.arange(1.0, 11.0), np.full(10, 9.0)]]
    stairs = np.c_[np.repeat(np.arange(10.0), 2)[:19], np.repeat(np.arange(10.0), 2)[1:20]]
    points = np.r_[line, ell, stairs]
    group = np.repeat([0, 1, 2], [len(line), len(ell), len(stairs)])
    off = detect._off_line(points, group, np.bincount(group))
    assert off[0] == pytest.approx(0.0, abs=1e-9)
    assert off[1] > 1.5
    assert off[2] < 0.5


def test_overlap_goes_to_the_part_whose_cells_lie_in_it():
    """Two parts whose regularised outlines overlap along their shared wall: the overlap
    is cut from the one with fewer of its own cells in it, the larger one included;
    without cells the smaller one loses it, as before."""
    transform = Affine(1.0, 0.0, 0.0, 0.0, -1.0, 20.0)
    labels = np.zeros((20, 30), np.int32)
    labels[2:18, 2:20] = 1  # the large part: columns 2-19
    labels[2:18, 20:27] = 2  # the small one: columns 20-26
    large, small = shapely.box(2, 2, 22, 18), shapely.box(20, 2, 27, 18)  # the large one reaches 2 m too far
    out = detect._remove_overlaps([large, small], 1.0, 1.0, owners=[1, 2], labels=labels, transform=transform)
    assert {round(p.area) for p in out} == {16 * 18, 16 * 7}
    assert not out[0].intersection(out[1]).area
    plain = detect._remove_overlaps([large, small], 1.0, 1.0)
    assert {round(p.area) for p in plain} == {16 * 20, 16 * 5}


def test_overlap_cut_leaves_no_sliver():
    """A neighbour whose wall runs half a millimetre inside this part's wall leaves no
    sliver of that width behind when its overlap is cut out (a building with such a
    sliver failed the mesh check on a random survey)."""
    transform = Affine(0.5, 0.0, 0.0, 0.0, -0.5, 10.0)
    labels = np.ones((20, 20), np.int32)
    labels[10:, 4:10] = 2  # the neighbour's cells: x 2-5, y 0-5
    part, neighbour = shapely.box(0, 0, 10, 10), shapely.box(2, 0.0005, 5, 5)
    out = detect._remove_overlaps([part, neighbour], 1.0, 0.5, owners=[1, 2], labels=labels, transform=transform)
    cut = next(p for p in out if not p.equals(neighbour))
    assert cut.is_valid and cut.area == pytest.approx(85.0, abs=1e-4)
    opened = cut.buffer(-0.001, join_style="mitre").buffer(0.001, join_style="mitre")
    assert opened.area == pytest.approx(cut.area, abs=1e-6)
