"""The per-point steps of the terrain stages against plain numpy and scipy references.

Points are binned into cells (highest, lowest, mean, count; a subset picked by a mask),
grids are sampled at points (bilinear between cell centres), and the Delaunay gap fill
inserts its vertices along a Hilbert curve. Random grids, windows of larger grids and
points beyond the grid.
"""

import numpy as np
import pytest
from affine import Affine
from scipy import ndimage

from recon3d.core.raster import Raster
from recon3d.terrain import dsm as dsm_stage
from recon3d.terrain.dtm import hilbert_order


def _random_case(rng):
    res = float(rng.choice([0.25, 0.5, 1.0, 0.3]))
    transform = Affine(res, 0, float(rng.uniform(-1e5, 1e5)), 0, -res, float(rng.uniform(-1e5, 1e5)))
    shape = (int(rng.integers(1, 40)), int(rng.integers(1, 40)))
    n = int(rng.integers(1, 3000))
    xyz = np.column_stack([
        transform.c + rng.uniform(-3, shape[1] * res + 3, n),  # some points beyond the grid
        transform.f - rng.uniform(-3, shape[0] * res + 3, n),
        rng.normal(10.0, 5.0, n),
    ])
    return transform, shape, xyz


def _reference(xyz, transform, shape, origin, reducer):
    """The cells by numpy's floor, the reduction by ``ufunc.at`` and ``bincount``."""
    col = np.floor((xyz[:, 0] - transform.c) / transform.a).astype(np.int64) - origin[1]
    row = np.floor((xyz[:, 1] - transform.f) / transform.e).astype(np.int64) - origin[0]
    on = (row >= 0) & (row < shape[0]) & (col >= 0) & (col < shape[1])
    cell, z = (row * shape[1] + col)[on], xyz[on, 2]
    count = np.bincount(cell, minlength=shape[0] * shape[1]).astype(np.float64)
    if reducer == "count":
        return count.reshape(shape)
    if reducer == "mean":
        total = np.bincount(cell, weights=z, minlength=shape[0] * shape[1])
        with np.errstate(invalid="ignore"):
            return np.where(count > 0, total / count, np.nan).reshape(shape)
    out = np.full(shape[0] * shape[1], np.nan)
    ufunc = np.fmax if reducer == "max" else np.fmin
    ufunc.at(out, cell, z)
    return out.reshape(shape)


@pytest.mark.parametrize("reducer", ["max", "min", "mean", "count"])
def test_points_are_reduced_per_cell_as_numpy_does(reducer):
    """Every reducer, on whole grids and on windows, all points or a kept subset: the same
    bits as numpy's floor and reductions (sums in the points' order)."""
    rng = np.random.default_rng(7)
    for trial in range(60):
        transform, shape, xyz = _random_case(rng)
        if trial % 3 == 0:
            xyz[:, :2] = np.round(xyz[:, :2] / transform.a * 2) * transform.a / 2  # points on cell edges
        origin = (int(rng.integers(-2, 3)), int(rng.integers(-2, 3))) if trial % 2 else (0, 0)
        keep = rng.random(len(xyz)) < 0.6
        got = dsm_stage.grid_points(xyz, transform, shape, reducer=reducer, origin=origin)
        kept = dsm_stage.grid_points(xyz, transform, shape, reducer=reducer, origin=origin, keep=keep)
        assert got.tobytes() == _reference(xyz, transform, shape, origin, reducer).tobytes()
        assert kept.tobytes() == _reference(xyz[keep], transform, shape, origin, reducer).tobytes()


def test_mean_and_count_in_one_pass_match_the_reducers():
    rng = np.random.default_rng(8)
    transform, shape, xyz = _random_case(rng)
    mean, count = dsm_stage.mean_and_count(xyz, transform, shape)
    assert np.array_equal(mean, dsm_stage.grid_points(xyz, transform, shape, reducer="mean"), equal_nan=True)
    assert np.array_equal(count, dsm_stage.grid_points(xyz, transform, shape, reducer="count"))
    assert np.array_equal(np.isfinite(mean), count > 0) and count.sum() <= len(xyz)
    with pytest.raises(ValueError, match="reducer"):
        dsm_stage.grid_points(xyz, transform, shape, reducer="median")


def test_bilinear_sampling_matches_scipy():
    """Bilinear between cell centres, clamped onto the outer centres, as scipy's
    ``map_coordinates`` (order 1, mode "nearest"); NaN outside the grid and next to a NaN
    cell; a window of a larger grid samples as the same cells copied out."""
    rng = np.random.default_rng(9)
    for trial in range(40):
        transform, shape, xyz = _random_case(rng)
        shape = (max(shape[0], 2), max(shape[1], 2))
        origin = (int(rng.integers(0, 3)), int(rng.integers(0, 3)))
        big = rng.normal(0.0, 10.0, (shape[0] + 5, shape[1] + 5)).astype(np.float32)
        window = big[origin[0]:origin[0] + shape[0], origin[1]:origin[1] + shape[1]]
        raster = Raster(window, transform, None, {}, origin)
        assert np.shares_memory(raster.data, big)  # sampled in place, not copied out
        x0, y0 = transform.c + origin[1] * transform.a, transform.f + origin[0] * transform.e
        xyz[:, 0] += x0 - transform.c
        xyz[:, 1] += y0 - transform.f
        got = raster.sample(xyz[:, 0], xyz[:, 1])
        rows = (xyz[:, 1] - y0) / transform.e - 0.5
        cols = (xyz[:, 0] - x0) / transform.a - 0.5
        want = ndimage.map_coordinates(window.astype(np.float64), [rows, cols], order=1, mode="nearest")
        west, south, east, north = raster.bounds
        inside = (xyz[:, 0] >= west) & (xyz[:, 0] <= east) & (xyz[:, 1] >= south) & (xyz[:, 1] <= north)
        assert np.isnan(got[~inside]).all()
        assert np.allclose(got[inside], want[inside], rtol=0, atol=1e-9)
        copied = Raster(window.copy(), transform, None, {}, origin).sample(xyz[:, 0], xyz[:, 1])
        assert copied.tobytes() == got.tobytes()
    data = np.ones((4, 4))
    data[1, 1] = np.nan
    at = Raster(data, Affine(1, 0, 0, 0, -1, 4))
    near, far = at.sample(np.array([1.7, 3.2]), np.array([2.4, 0.6]))
    assert np.isnan(near) and far == 1.0


def test_sampling_keeps_the_shape_of_the_points():
    """Scalars give a 0-d value, grids of points a grid of values, each equal to the
    same point sampled in a flat array, whichever way of sampling."""
    rng = np.random.default_rng(4)
    raster = Raster(rng.normal(0.0, 5.0, (6, 7)), Affine(2.0, 0, 100.0, 0, -2.0, 50.0))
    x, y = rng.uniform(98.0, 116.0, (3, 4)), rng.uniform(36.0, 52.0, (3, 4))
    for bilinear in (True, False):
        flat = raster.sample(x.ravel(), y.ravel(), bilinear=bilinear)
        grid = raster.sample(x, y, bilinear=bilinear)
        assert grid.shape == (3, 4)
        assert grid.ravel().tobytes() == flat.tobytes()
        one = raster.sample(float(x[1, 2]), float(y[1, 2]), bilinear=bilinear)
        assert one.shape == () and (np.isnan(one) and np.isnan(grid[1, 2]) or one == grid[1, 2])
        row = raster.sample(x[0], float(y[0, 0]), bilinear=bilinear)  # one y for a row of x
        assert row.tobytes() == raster.sample(x[0], np.full(4, y[0, 0]), bilinear=bilinear).tobytes()


def test_point_spacing_of_a_regular_grid_of_points():
    """Points every 0.5 m over an L-shaped area: the spacing is 0.5 m, the empty corner of
    the bounding box not counted."""
    x, y = np.meshgrid(np.arange(0, 200, 0.5), np.arange(0, 200, 0.5))
    lshape = (x < 60) | (y < 60)
    xy = np.column_stack([x[lshape], y[lshape]]) + 1e5
    assert dsm_stage.point_spacing(xy) == pytest.approx(0.5, rel=0.05)


def test_hilbert_order_walks_a_full_grid_by_unit_steps():
    """Every point once, each the 4-neighbour of the one before, on square and oblong grids;
    on scattered points, consecutive ones much closer than in row order."""
    for rows, cols in ((8, 8), (64, 64), (5, 37), (33, 2)):
        r, c = np.divmod(np.arange(rows * cols), cols)
        order = hilbert_order(r, c)
        assert np.array_equal(np.sort(order), np.arange(rows * cols))
        if rows == cols:  # the curve covers a power-of-two square step by step
            assert (np.abs(np.diff(r[order])) + np.abs(np.diff(c[order])) == 1).all()
    rng = np.random.default_rng(4)
    r, c = rng.integers(0, 1000, 5000), rng.integers(0, 1000, 5000)
    row_order = np.lexsort((c, r))
    order = hilbert_order(r, c)
    step = np.hypot(np.diff(r[order]), np.diff(c[order])).mean()
    assert step < 0.2 * np.hypot(np.diff(r[row_order]), np.diff(c[row_order])).mean()
