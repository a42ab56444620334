"""The roof label grid: a building's footprint rastered into cells, each labelled with
the roof plane (or roof part) its points lie on.

This is the first layer of the LoD1.3 and LoD2.2 solids (see :mod:`recon3d.buildings.lod`):
the grid's regions become the planar partition of :mod:`recon3d.buildings.partition`,
which :mod:`recon3d.buildings.extrude` turns into a solid. Coordinates are the city
model's local frame.
"""

from __future__ import annotations

import math as _math
from typing import NamedTuple

import numpy as np

from recon3d.core.memory import available_memory

__all__ = ["LodFailure", "RoofGrid", "height_levels", "label_grid", "plane_height", "unpinch"]


class LodFailure(Exception):
    """A LoD that cannot be built: ``reason`` is one of ``lod.LOD_REASONS``; ``codes``
    are the val3dity error codes of the solid that failed the check (``invalid_mesh``)."""

    def __init__(self, reason: str, detail: str = "", codes: tuple[int, ...] = ()) -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.codes = codes


class RoofGrid(NamedTuple):
    labels: np.ndarray  # (h, w) int, -1 outside the footprint
    inside: np.ndarray  # (h, w) bool
    transform: object  # affine.Affine
    cell: float
    xy: np.ndarray  # (n, 2) the roof points in plan
    point_labels: np.ndarray  # (n,) their labels, -1 for none


def label_grid(fp, points, labels, cell, min_area, *, planes=None, step=0.5) -> RoofGrid:
    """Raster of plane labels over the footprint (every touched cell labelled).

    With the ``planes`` of the labels, the clean-up (majority filter, small patches)
    never moves a cell onto a plane more than ``step`` off its points while its own
    plane fits them: a strip of roof one cell wide (the steep eave of a mansard beside
    a lower annex) would otherwise go to the lower neighbour and drop its points by
    the whole step.
    """
    import affine
    import rasterio.features
    from scipy import ndimage

    minx, miny, maxx, maxy = fp.bounds
    x0 = _math.floor(minx / cell) * cell - cell
    y1 = _math.ceil(maxy / cell) * cell + cell
    w = int(_math.ceil((maxx - x0) / cell)) + 1
    h = int(_math.ceil((y1 - miny) / cell)) + 1
    transform = affine.Affine(cell, 0.0, x0, 0.0, -cell, y1)
    inside = rasterio.features.rasterize(
        [(fp, 1)], out_shape=(h, w), transform=transform, all_touched=True, dtype="uint8"
    ).astype(bool)
    lab = np.asarray(labels)
    keep = lab >= 0
    if not keep.any():
        raise LodFailure("no_roof_planes")
    nl = int(lab.max()) + 1
    need = h * w * (nl * 12 + 64)  # votes (int64) and one-hot scores (float32) per plane, the masks
    if need > available_memory():
        raise LodFailure("too_large", f"a roof grid of {h} x {w} cells and {nl} planes needs {need / 2**30:.1f} GiB")
    col = np.clip(((points[keep, 0] - x0) / cell).astype(np.int64), 0, w - 1)
    row = np.clip(((y1 - points[keep, 1]) / cell).astype(np.int64), 0, h - 1)
    votes = np.bincount((row * w + col) * nl + lab[keep], minlength=h * w * nl).reshape(h * w, nl)
    grid = np.where(votes.max(axis=1) > 0, votes.argmax(axis=1), -1).reshape(h, w)
    grid[~inside] = -1
    grid = _fill(grid, inside)
    # majority filter (3 x 3) against single-cell noise, then small patches to neighbours
    onehot = np.stack([(grid == k) for k in range(nl)]).astype(np.float32)
    score = ndimage.uniform_filter(onehot, size=(1, 3, 3), mode="constant")
    smooth = np.where(inside, score.argmax(axis=0), -1)
    smooth[inside & (score.max(axis=0) <= 0)] = grid[inside & (score.max(axis=0) <= 0)]
    raw, grid = grid, smooth
    min_cells = max(1, int(round(min_area / cell**2)))
    for _ in range(2):
        small = np.zeros_like(inside)
        for k in np.unique(grid[inside]):
            comp, count = ndimage.label(grid == k)
            if count:
                sizes = np.bincount(comp.ravel())
                sizes[0] = 0
                small |= (sizes < min_cells)[comp] & (comp > 0)
        if not small.any() or small[inside].all():
            break
        grid[small] = -1
        grid = _fill(grid, inside)
    if planes is not None:
        grid = _keep_fitting(grid, raw, points[keep], row * w + col, planes, step)
    point_labels = np.where(keep, lab, -1)
    return RoofGrid(unpinch(grid, inside), inside, transform, cell, points[:, :2], point_labels)


def _keep_fitting(smooth, raw, points, flat, planes, step) -> np.ndarray:
    """``smooth`` with the cells set back to their ``raw`` label where most of the
    cell's points lie on the raw label's plane (within ``step`` / 2) and most lie more
    than ``step`` off the plane the clean-up gave the cell.

    ``points`` (n, 3), the roof points on a plane, fall in the cells ``flat`` (n,)
    (row * width + col) of the grids.
    """
    changed = ((smooth != raw) & (raw >= 0) & (smooth >= 0)).ravel()
    moved = changed[flat]
    if not moved.any():
        return smooth
    cell = flat[moved]
    x, y, z = points[moved].T
    coef = np.asarray(planes)
    on_raw = np.abs(plane_height(coef[raw.ravel()[cell]].T, x, y) - z) < 0.5 * step
    off_new = np.abs(plane_height(coef[smooth.ravel()[cell]].T, x, y) - z) > step
    count = np.bincount(cell, minlength=raw.size)
    back = (2 * np.bincount(cell, weights=on_raw, minlength=raw.size) > count) & (
        2 * np.bincount(cell, weights=off_new, minlength=raw.size) > count
    )
    out = smooth.copy().ravel()
    out[back] = raw.ravel()[back]
    return out.reshape(smooth.shape)


def unpinch(grid: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Labels without checkerboard 2 x 2 windows (two cells of one label touching only
    at a corner). Such a corner would become a vertex where one roof part touches
    itself, and the walls around it an edge shared by four surfaces (val3dity 304);
    one of the two other cells takes the label instead."""
    grid = grid.copy()
    for _ in range(20):
        a, b, c, d = grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]
        main = (a == d) & (a >= 0) & (b != a) & (c != a)
        anti = (b == c) & (b >= 0) & (a != b) & (d != b) & ~main
        if not (main.any() or anti.any()):
            break
        r, q = np.nonzero(main)
        take = inside[r, q + 1]
        grid[r[take], q[take] + 1] = grid[r[take], q[take]]
        r2, q2 = np.nonzero(anti)
        take2 = inside[r2, q2]
        grid[r2[take2], q2[take2]] = grid[r2[take2], q2[take2] + 1]
    return grid


def _fill(grid: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Unlabelled cells inside the footprint take the nearest labelled cell's label."""
    from scipy import ndimage

    known = grid >= 0
    if not known.any():
        raise LodFailure("no_roof_planes")
    if (known | ~inside).all():
        return grid
    idx = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
    out = grid[idx[0], idx[1]]
    out[~inside] = -1
    return out


def plane_height(plane, x, y):
    a, b, c, d = plane
    return -(a * np.asarray(x) + b * np.asarray(y) + d) / c


def height_levels(points: np.ndarray, cell: float, step: float) -> np.ndarray:
    """(n,) label of each roof point: the terraces of a roof cut at every ``step`` of
    height (connected ``cell`` cells whose highest points fall in one band)."""
    import affine

    from recon3d.buildings.detect import split_by_height
    from recon3d.terrain.dsm import grid_points

    x0, y1 = points[:, 0].min() - cell, points[:, 1].max() + cell
    shape = (int((y1 - points[:, 1].min()) / cell) + 2, int((points[:, 0].max() - x0) / cell) + 2)
    transform = affine.Affine(cell, 0.0, x0, 0.0, -cell, y1)
    top = grid_points(points, transform, shape, reducer="max")
    band = np.floor(top / step)
    labels, _ = split_by_height(band, np.isfinite(top), 0.5)  # neighbours join within one band
    col = ((points[:, 0] - x0) / cell).astype(np.int64)
    row = ((y1 - points[:, 1]) / cell).astype(np.int64)
    return labels[row, col].astype(np.int64) - 1
