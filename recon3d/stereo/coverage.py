"""Which DSM cells a stereo run's images show, and what a matcher left unseen.

Plain functions of the DSM grid and the cameras: the area both images of a matched
pair see (frame and satellite), the holes in it that the matching lost, how much of it
the DSM fills, the filled-in cells that both images would have seen at their height
(hidden ground, lowered to the DTM), and how much of what both images see unhidden the
matcher missed.
"""

from __future__ import annotations

import numpy as np
import pyproj
from scipy import ndimage

from recon3d.core.geo import Units
from recon3d.core.raster import Raster
from recon3d.terrain.dsm import grid_points, seen_by_all
from recon3d.terrain.dtm import fill_nearest

__all__ = [
    "COMMON_AREA_MARGIN_PX",
    "MIN_COMMON_FILLED",
    "MIN_MATCHED_OF_VISIBLE",
    "NEIGHBOURHOOD",
    "common_area",
    "common_area_fill",
    "holes_both_saw",
    "open_to_ground",
    "roof_holes",
    "rpc_common_area",
    "seen_by_a_pair",
    "unmatched_in_view",
    "unseen_guesses",
]

#: Pixels along the image borders left out of the common area: their matches are the
#: least sure, and a hole there is better left empty than filled from the wrong side.
COMMON_AREA_MARGIN_PX = 2.0

#: Least share (percent) of the area two images both see that a frame-stereo DSM must
#: fill without a warning.
MIN_COMMON_FILLED = 95.0

#: Least share (percent) of the part of the common area both images see unhidden that
#: a frame-stereo run must match without a warning: below it the matcher, not what
#: stands in the way of one image, lost the area. Visibility is judged on the DSM, so
#: ground behind an occluder the matcher also lost (a tree crown at a wide base) counts
#: as missed: the synthetic survey family gives 84-99 % (wide_base, B/H 1.0, lowest),
#: a matcher that fills in half of each image 40 %.
MIN_MATCHED_OF_VISIBLE = 70.0

#: Radius (m) around an empty cell of the surfaces :func:`common_area` judges it by.
#: On the nine surveys of the family run at 1000 px, 2 m rather than 10 m (and the
#: lowest surface rather than the median) raised the DSM's share of the true common
#: area from 95.2-95.9 % to 98.2-99.0 % on three wide-base surveys (B/H 0.5-1.0), and
#: from 85.6 % to 89.4 % on a wide-angle slope, at the same tolerant RMS (within 0.03 m).
NEIGHBOURHOOD = 2.0

#: A roof hole (m): an empty cell within this closing radius of matched cells standing
#: :data:`ROOF_HOLE_HEIGHT` above the DTM is part of that roof, never hidden ground.
#: On 25 surveys of the family at 1000 px (six examined: 100-300 cells kept a survey,
#: most on roofs) the tolerant DSM RMS fell on 22 (by up to 0.04 m; up 0.03 and 0.004 m on two),
#: footprint completeness rose on 17 (by up to 2 points) for up to 0.6 points of
#: correctness, and random_52's roof check point, 18 m under its roof, came back onto
#: it. A 2 m radius also closed courtyards and corners: RMS up on 6 surveys.
ROOF_HOLE_RADIUS = 1.0
ROOF_HOLE_HEIGHT = 2.0
#: A roof stripe (m): the matched roof is also closed along rows and along columns by
#: lines reaching this far either side (whole cells, rounded down), so a stripe up to
#: twice as wide that the matcher missed across a roof (along a ridge or a hip), open
#: onto the ground at one end, is part of that roof; a street wider than that stays
#: open. Such stripes took the DTM's height and put roof check points 10-24 m under
#: small tall roofs. On the 25 development surveys at 1000 px the tolerant DSM RMS fell
#: on 18 (nadir_pair 0.514 -> 0.495 m), rose on 6 by at most 0.003 m, the within-1-m
#: share moved by at most 0.11 points and random_40's roof check point RMS fell from
#: 2.71 to 1.17 m; on the 4 held-out surveys the RMS fell on all four and random_63's
#: roof check point RMS from 3.16 to 2.82 m.
ROOF_STRIPE_REACH = 1.5

#: Least share of the rim of a region of agreed guesses (the matched or lowered cells
#: touching it) that must be ground for the region to be judged as hidden ground
#: (:func:`open_to_ground`).
GROUND_RIM_SHARE = 0.5


def common_area(scene, pairs: list[dict], dsm: Raster, observed: np.ndarray, units: Units) -> np.ndarray:
    """Frame stereo: (rows, cols) bool, the cells both images of a matched pair see.

    A cell is in the common area when its centre lies inside both images of a pair that
    was matched, :data:`COMMON_AREA_MARGIN_PX` or more from their borders (through the
    lens, as the photos were taken), at its own height. A cell without a height takes
    the lowest surface within :data:`NEIGHBOURHOOD` (else the nearest cell's): what a
    matcher leaves empty is mostly ground hidden from one image, and the scene's median
    height, used before, put empty cells on a slope metres off and out of frame. A cell
    holding no matched point must also lie inside them at the height of the highest
    surface within :data:`NEIGHBOURHOOD`, so that the part of a roof the image border
    cuts is not taken for ground in view.

    Parameters
    ----------
    scene : recon3d.io.colmap.Scene
    pairs : list of dict
        run.json's record of each matched pair (``images``: the two names).
    dsm : Raster
        The DSM before its holes are filled.
    observed : (rows, cols) bool
        Cells holding a matched (not filled-in) point.
    units : Units
    """
    cameras = {c.name: c for c in scene.cameras}
    xs, ys = dsm.cell_centers()
    x, y = np.meshgrid(xs, ys)
    finite = np.isfinite(dsm.data)
    size = 2 * int(np.ceil(units.length(NEIGHBOURHOOD) / dsm.resolution)) + 1
    own = _lowest_around(dsm.data, size)
    high = ndimage.maximum_filter(np.where(finite, dsm.data, -np.inf), size=size)
    high = np.where(np.isfinite(high), np.maximum(high, own), own)
    observed = observed.ravel()
    offset = np.asarray(scene.offset)
    points = [np.column_stack([x.ravel(), y.ravel(), z.ravel()]) - offset for z in (own, high)]

    def in_frame(cam, margin: float = COMMON_AREA_MARGIN_PX):
        lo, hi = margin - 0.5, np.array([cam.width, cam.height]) - 0.5 - margin
        inside = []
        for local in points:
            uv, depth = cam.project(local, distort=True)  # the photo as taken, lens and all
            inside.append((depth > 0) & (uv >= lo).all(axis=1) & (uv <= hi).all(axis=1))
        return inside[0] & (observed | inside[1])

    frames = {name: in_frame(cam) for name, cam in cameras.items()}
    common = np.zeros(len(points[0]), bool)
    for record in pairs:
        a, b = record["images"]
        common |= frames[a] & frames[b]
    return common.reshape(dsm.shape)


def _lowest_around(data: np.ndarray, size: int) -> np.ndarray:
    """(rows, cols) float: ``data``, its NaN cells given the lowest value in the
    ``size`` x ``size`` window around them, or the nearest value when the window holds
    none (0 for an all-NaN grid)."""
    finite = np.isfinite(data)
    if not finite.any():
        return np.zeros(data.shape)
    low = ndimage.minimum_filter(np.where(finite, data, np.inf), size=size)
    return np.where(finite, data, np.where(np.isfinite(low), low, fill_nearest(data)))


def holes_both_saw(scene, pairs: list[dict], raw: Raster, area: np.ndarray, max_cells: int) -> np.ndarray:
    """(rows, cols) bool: the empty regions of ``raw`` in ``area``, larger than
    ``max_cells``, holding two or more of the model's sparse points that both images of
    a matched pair observed.

    Ground hidden from one image behind a building holds no such tie point (one image
    cannot see it); an empty region that does is ground both images saw and the
    matching lost, and it is left empty (and warned of) rather than filled from its rim.
    """
    names = [c.name for c in scene.cameras]
    both = np.zeros(len(scene.sparse), bool)
    for record in pairs:
        a, b = (names.index(n) for n in record["images"])
        both |= scene.seen[a] & scene.seen[b]
    holes, n = ndimage.label(~np.isfinite(raw.data) & area)
    if n == 0:
        return np.zeros(area.shape, bool)
    world = scene.sparse[both] + scene.offset
    ties = grid_points(world, raw.transform, raw.shape, reducer="count")
    per_hole = np.bincount(holes.ravel(), weights=np.nan_to_num(ties).ravel(), minlength=n + 1)
    size = np.bincount(holes.ravel(), minlength=n + 1)
    seen = (per_hole >= 2) & (size > max_cells)
    seen[0] = False
    return seen[holes]


def rpc_common_area(cameras, relative_bias: tuple[float, float], dsm: Raster) -> np.ndarray:
    """Satellite pair: (rows, cols) bool, the cells whose surface both images show.

    Each cell centre, at its DSM height (the median where it has none), is projected
    through both RPCs (the second with the relative bias removed by matching) and must
    fall on a finite pixel of each image, :data:`COMMON_AREA_MARGIN_PX` or more from
    its borders.
    """
    import rasterio

    xs, ys = dsm.cell_centers()
    x, y = np.meshgrid(xs, ys)
    finite = np.isfinite(dsm.data)
    h = np.where(finite, dsm.data, float(np.nanmedian(dsm.data)) if finite.any() else 0.0).ravel()
    lon, lat = pyproj.Transformer.from_crs(dsm.crs, 4326, always_xy=True).transform(x.ravel(), y.ravel())
    shift = np.asarray(relative_bias, float)
    common = np.ones(h.shape, bool)
    for cam, extra in zip(cameras, (np.zeros(2), shift), strict=True):
        row, col = cam.project(lon, lat, h)
        col, row = col + extra[0], row + extra[1]
        m = COMMON_AREA_MARGIN_PX
        inside = (col >= m - 0.5) & (col <= cam.width - 0.5 - m) & (row >= m - 0.5) & (row <= cam.height - 0.5 - m)
        with rasterio.open(cam.image_path) as src:
            nodata = ~src.read_masks(1).astype(bool)
        r, c = np.clip(np.rint(row), 0, cam.height - 1).astype(np.int64), np.clip(np.rint(col), 0, cam.width - 1).astype(np.int64)
        common &= inside & ~nodata[r, c]
    return common.reshape(dsm.shape)


def common_area_fill(common: np.ndarray, dsm: Raster, filled: np.ndarray, unobserved: np.ndarray | None,
                     units: Units) -> dict:
    """How much of the common area the DSM fills and observes (run.json's
    ``stereo.common_area``); with ``empty_extent`` where it fills less than
    :data:`MIN_COMMON_FILLED` percent."""
    full = np.isfinite(dsm.data) & common
    observed = full & ~filled & (~unobserved if unobserved is not None else True)
    n = max(1, int(common.sum()))
    area = {
        "cells": int(common.sum()),
        "area_m2": round(float(common.sum() * (dsm.resolution * units.horizontal) ** 2), 1),
        "filled_percent": round(100.0 * float(full.sum()) / n, 2),
        "observed_percent": round(100.0 * float(observed.sum()) / n, 2),
    }
    if area["filled_percent"] < MIN_COMMON_FILLED:
        xs, ys = dsm.cell_centers()
        rows, cols = np.nonzero(common & ~full)
        x, y = xs[cols], ys[rows]
        area["empty_extent"] = [float(x.min()), float(y.min()), float(x.max()), float(y.max())]
        area["empty_cells"] = len(rows)
    return area


def unseen_guesses(scene, pairs: list[dict], dsm: Raster, dtm: Raster, unjudged: np.ndarray, matched: np.ndarray,
                   units: Units, *, tolerance: float, min_area: float, behind_only: bool = False) -> np.ndarray:
    """(rows, cols) bool: stereo DSM cells filled in above the DTM that are hidden ground,
    to take the DTM.

    Cells holding no matched point and no guess with evidence for it (``unjudged``: the
    images agree with it, or it lies beyond an occlusion's width beside a surface) are
    judged, in regions of at least ``min_area``: the few cells the matcher misses on a
    roof or in a crown are noise, not hidden ground, and neither are the holes in a
    matched roof (:func:`roof_holes`). A judged cell is hidden ground when

    - both images of a matched pair would have seen it at its filled-in height (and so
      matched it), or
    - at the DTM's height one image of a matched pair sees it over the matched surface
      and the other does not: ground behind something the matcher did see, or
    - at the DTM's height both images frame it and the matched surface hides it from
      both, and it is not enclosed by raised matched cells: ground in a narrow street
      between buildings and crowns, open at its ends. A roof the matcher missed whole
      stands over ground both images see at the DTM's height (its matched surroundings
      are lower); a part missed inside a matched roof is enclosed by it.

    The second test lowered 300 to 31,000 more cells of the synthetic survey family at
    1000 px, most of them filled from roofs around (median error 0.8-3.2 m before,
    0.07-0.25 m after), and raised the share of common cells within 1 m on each of 17
    surveys (by up to 3.6 points). It trusts the DTM: where the DTM had sunk under
    mismatches (random_52), it lowered ground that was right. The third raised the share
    within 1 m on 19 of 25 surveys (random_45 82.6 -> 88.4 %, random_4 88.8 -> 90.8 %;
    lower on one by 0.02 points) and footprint correctness by 0.25 points on average.

    Parameters
    ----------
    matched : (rows, cols) bool
        Cells holding a matched point: the surface that hides the ground from one image.
    behind_only : bool
        Judge by the second test alone: for guesses the images agree with, whose
        height the first test would only contradict by chance.
    """
    regions, n = ndimage.label(unjudged)
    area = ndimage.sum_labels(np.ones(regions.shape), regions, np.arange(1, n + 1)) * dsm.resolution**2
    judged = unjudged & (np.r_[0.0, area][regions] >= min_area) & (dsm.data > dtm.data + tolerance)
    judged &= ~roof_holes(dsm, dtm, matched, units)
    if behind_only:
        return _hidden_at_ground(scene, pairs, dsm, dtm, judged, matched, None, tolerance=tolerance)
    raised = _raised(dsm, dtm, matched, units)
    enclosed = ndimage.binary_fill_holes(raised) & ~raised
    seen = seen_by_a_pair(scene, pairs, dsm, judged, tolerance=tolerance)
    return seen | _hidden_at_ground(scene, pairs, dsm, dtm, judged & ~seen, matched, ~enclosed, tolerance=tolerance)


def open_to_ground(cells: np.ndarray, ground: np.ndarray, rim: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: the 8-connected regions of ``cells`` at least
    :data:`GROUND_RIM_SHARE` of whose rim is ``ground``.

    The rim of a region is the ``rim`` cells outside it touching it (8 neighbours); a
    cell touching two regions counts for both. Ground hidden from one image opens onto
    the street beyond it; a roof face the matcher missed opens onto its roof.

    Parameters
    ----------
    cells, ground, rim : (rows, cols) bool
        ``ground`` is read on the rim only.
    """
    regions, n = ndimage.label(cells, structure=np.ones((3, 3)))
    out = np.zeros(cells.shape, bool)
    if n == 0:
        return out
    rows, cols = np.nonzero(rim & ~cells & ndimage.binary_dilation(cells, np.ones((3, 3), bool)))
    padded = np.pad(regions, 1)
    around = np.sort(np.stack([padded[rows + 1 + dr, cols + 1 + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)],
                              axis=1), axis=1)  # (k, 9): the labels touching each rim cell
    first = np.concatenate([np.ones((len(rows), 1), bool), np.diff(around, axis=1) != 0], axis=1) & (around > 0)
    label = around[first]
    on_ground = np.broadcast_to(ground[rows, cols][:, None], around.shape)[first]
    total = np.bincount(label, minlength=n + 1)
    opened = (total > 0) & (np.bincount(label, weights=on_ground, minlength=n + 1) >= GROUND_RIM_SHARE * total)
    opened[0] = False
    return opened[regions]


def unsupported_guesses(dsm: Raster, matched: np.ndarray, guessed: np.ndarray, *, reach: float,
                        height: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``guessed`` cells standing more than ``height`` above every ``matched`` cell
    within ``reach`` (a square of that half-width), and the highest of those.

    A hole filled from its rim never stands above the rim, but the matcher's guesses (a
    disparity filled in beside an occlusion) can: beside a building they put single
    cells metres above the roof next to them. A guess higher than everything the images
    matched around it has nothing to hold it up. Cells farther than ``reach`` from any
    match (the inside of a roof face no pixel matched) are not judged.

    Parameters
    ----------
    dsm : Raster
    matched, guessed : (rows, cols) bool
    reach, height : float
        CRS units.

    Returns
    -------
    lower : (rows, cols) bool
    highest : (rows, cols) float
        The highest matched cell within ``reach``; -inf where there is none.
    """
    size = 2 * max(1, int(round(reach / dsm.resolution))) + 1
    heights = np.where(matched & np.isfinite(dsm.data), dsm.data, -np.inf)
    highest = ndimage.maximum_filter(heights, size=size, mode="constant", cval=-np.inf)
    lower = guessed & ~matched & np.isfinite(highest) & (dsm.data > highest + height)  # NaN compares False
    return lower, highest


def roof_holes(dsm: Raster, dtm: Raster, matched: np.ndarray, units: Units) -> np.ndarray:
    """(rows, cols) bool: cells inside the morphological closing, by a disc of radius
    :data:`ROOF_HOLE_RADIUS` or by a horizontal or vertical line reaching
    :data:`ROOF_STRIPE_REACH` either side, of the matched cells at least
    :data:`ROOF_HOLE_HEIGHT` above the DTM: gaps in a roof the matcher saw around them.

    Hidden ground lies beside a building, on the side away from one image, so no
    closing of its roofs reaches it; a roof face the matcher missed between matched
    ones does look like hidden ground to the visibility tests of
    :func:`unseen_guesses`, and took the DTM's height before this.
    """
    import cv2

    raised = _raised(dsm, dtm, matched, units).astype(np.uint8)
    k = 2 * int(round(units.length(ROOF_HOLE_RADIUS) / dsm.resolution)) + 1
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    holes = cv2.morphologyEx(raised, cv2.MORPH_CLOSE, disc).astype(bool)
    reach = int(units.length(ROOF_STRIPE_REACH) / dsm.resolution)  # rounded down: a wider street stays open
    if reach > 0:
        for line in (np.ones((1, 2 * reach + 1), np.uint8), np.ones((2 * reach + 1, 1), np.uint8)):
            holes |= cv2.morphologyEx(raised, cv2.MORPH_CLOSE, line).astype(bool)
    return holes


def _raised(dsm: Raster, dtm: Raster, matched: np.ndarray, units: Units) -> np.ndarray:
    """(rows, cols) bool: matched cells at least :data:`ROOF_HOLE_HEIGHT` above the DTM."""
    return matched & (dsm.data > dtm.data + units.height(ROOF_HOLE_HEIGHT))


def _hidden_at_ground(scene, pairs: list[dict], dsm: Raster, dtm: Raster, cells: np.ndarray, matched: np.ndarray,
                      open_ground: np.ndarray | None, *, tolerance: float) -> np.ndarray:
    """(rows, cols) bool: the ``cells`` whose ground, at the DTM's height, the matched
    surface (the DTM elsewhere) hides from one image of some matched pair, or, where
    ``open_ground`` (not enclosed by raised matched cells; None: nowhere), from both
    although both frame it."""
    offset = scene.offset
    cameras = {c.name: c for record in pairs for c in _pair_cameras(scene, record)}.values()

    def seen_over(surface: Raster) -> dict:  # each image once, however many pairs it is in
        return {c.name: seen_by_all(surface, cells, c.center[None] + offset, tolerance=tolerance,
                                    in_frame=lambda _, xyz, c=c: _in_picture(c, xyz - offset), heights=dtm.data)
                for c in cameras}

    seen = seen_over(Raster(np.where(matched, dsm.data, dtm.data), dsm.transform, dsm.crs))
    framed = seen_over(dtm) if open_ground is not None else None  # the walk is the cost: only when asked
    out = np.zeros(cells.shape, bool)
    for record in pairs:
        a, b = record["images"]
        out |= seen[a] ^ seen[b]
        if framed is not None:
            out |= framed[a] & framed[b] & ~seen[a] & ~seen[b] & open_ground
    return out


def _pair_cameras(scene, record: dict) -> list:
    cameras = {c.name: c for c in scene.cameras}
    return [cameras[name] for name in record["images"]]


def _in_picture(camera, local: np.ndarray) -> np.ndarray:
    """(n,) bool: the (n, 3) model points fall inside ``camera``'s photo (through the lens)."""
    uv, depth = camera.project(local, distort=True)
    return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1)


def seen_by_a_pair(scene, pairs: list[dict], dsm: Raster, cells: np.ndarray, *, tolerance: float) -> np.ndarray:
    """(rows, cols) bool: the ``cells`` that both images of some matched pair see at
    their DSM height, in frame and hidden by no DSM cell (``tolerance`` above the ray;
    :func:`~recon3d.terrain.dsm.seen_by_all`)."""
    offset = np.asarray(scene.offset)
    seen = np.zeros(cells.shape, bool)
    for record in pairs:
        pair = _pair_cameras(scene, record)
        centres = np.array([c.center for c in pair]) + offset
        seen |= seen_by_all(dsm, cells & ~seen, centres, tolerance=tolerance,
                            in_frame=lambda i, xyz, pair=pair: _in_picture(pair[i], xyz - offset))
    return seen


def unmatched_in_view(scene, pairs: list[dict], dsm: Raster, common: np.ndarray, matched: np.ndarray, *,
                      tolerance: float) -> dict:
    """How much of the common area no pixel matched although both images of a pair see
    it (run.json's ``stereo.common_area``), against what one image could not see.

    The area both images frame (``common``) holds matched cells, cells hidden from one
    image behind something taller (no matcher can match them: a wide base hides much
    ground behind buildings and trees) and cells both images see that the matcher
    missed. Visibility is judged on the final DSM, so it is an estimate: filled-in
    heights decide it where nothing was matched.

    Parameters
    ----------
    common, matched : (rows, cols) bool
        The common area, and its cells holding a matched (not filled-in) height.

    Returns
    -------
    dict
        ``hidden_percent`` and ``missed_percent`` of the common area, and
        ``matched_of_visible_percent``: matched / (matched + missed).
    """
    n = max(1, int(common.sum()))
    unmatched = common & ~matched & np.isfinite(dsm.data)
    missed = seen_by_a_pair(scene, pairs, dsm, unmatched, tolerance=tolerance)
    n_matched, n_missed = int((common & matched).sum()), int(missed.sum())
    return {
        "hidden_percent": round(100.0 * float((unmatched & ~missed).sum()) / n, 2),
        "missed_percent": round(100.0 * n_missed / n, 2),
        "matched_of_visible_percent": round(100.0 * n_matched / max(1, n_matched + n_missed), 2),
    }
