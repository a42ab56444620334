"""Building outlines refined from the images (stereo inputs).

A DSM from image matching blurs roof edges over a cell or two, so the nDSM outline
of a building sits a few decimetres off its eaves. The images hold the edge itself,
at the pixel size. Each edge of the regularised nDSM outline is moved along its
normal to where the images show it:

1. **The roof plane at eave height.** The building's eaves lie at about a low
   percentile of its DSM heights (:data:`EAVE_PERCENTILE`). Projected from a
   horizontal plane at that height, the roof edge lands exactly where it is in plan,
   whatever the camera's tilt and whatever the DSM says near the edge; walls and
   ground below it land beside it, shifted by the relief displacement. (A true
   orthophoto on the DSM inherits the DSM's blurred edge instead, which is why it is
   not used here.)
2. **Where the roof colour ends.** Along each edge, colours are sampled on lines
   across it (every :data:`STEP` metres along, :data:`PROFILE_STEP` across, up to
   :data:`REACH` either side). The roof's own colour is the median of the inner half of
   the profiles (each roof plane has its shade, so per edge, not per building); a
   sample is roof when its colour is nearer to it than to the colour beyond the edge
   (see :func:`_edge_crossing`). The edge is where the share of roof samples across
   the lines falls through one half, going outward (the region growing of Vozikis, section 4,
   run along the edge's normal so that the outline's directions stay regularised).
3. **Two images must agree.** The two most nadir images that see the building are
   searched independently. A roof edge at eave height lands at the same place in
   both; a wall seen beyond it, or a shadow, lands elsewhere in each (they lie below
   the plane). An edge moves only where both images find it within
   :data:`AGREEMENT` metres of each other, to the mean of the two.

The new corners are the intersections of consecutive moved edges (the directions of
the regularised outline are kept). Measured on the synthetic survey family
(``scripts/bench_image_outlines.py``): see the README's building section.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import shapely
from scipy import ndimage

from recon3d.buildings.outline import ring_corners
from recon3d.core.raster import Raster

__all__ = ["OutlineRefinement", "refine_outline", "refine_outlines"]

#: Percentile of the DSM heights inside a building (1 m in from its outline) taken as
#: its eave height, the plane the images are projected from.
EAVE_PERCENTILE = 15.0
#: Spacing (m) of the lines across an edge, and of the samples along each line.
STEP = 0.25
PROFILE_STEP = 0.1
#: Quantile (%) of the inner samples' colour distances that bounds "roof colour".
ROOF_QUANTILE = 95.0
#: Least colour distance (0-255 levels) counted as a change, for roofs of one flat colour.
MIN_COLOUR_STEP = 8.0
#: Share of roof samples required at the inner end of the lines, and allowed at the outer end.
INNER_ROOF, OUTER_ROOF = 0.6, 0.35
#: Largest difference (m) between the edge positions the two images give.
AGREEMENT = 0.25
#: Edges shorter than this (m) are not searched (they follow their neighbours' corners).
MIN_EDGE = 1.5
#: Farthest (m) an edge moves either way.
REACH = 1.5
#: Depth (m) inside the outline of the DSM cells that give the eave height.
EAVE_INSET = 1.0


class OutlineRefinement(NamedTuple):
    """The outline of one building after the image search.

    Attributes
    ----------
    polygon : shapely.Polygon
        The refined outline, or the nDSM outline when no edge moved.
    source : str
        "images" when at least one edge moved, else "ndsm".
    moved_share : float
        Share of the outline's length (edges searched) the two images agreed on.
    mean_shift : float
        Length-weighted mean absolute shift of the moved edges (m).
    """

    polygon: shapely.Polygon
    source: str
    moved_share: float
    mean_shift: float


def refine_outlines(
    polygons: Sequence[shapely.Polygon], views: Sequence[Any], dsm: Raster, *, metre: float = 1.0,
    blur: float = 1.0,
) -> list[OutlineRefinement]:
    """:func:`refine_outline` for every building, the images smoothed once.

    Parameters
    ----------
    polygons : sequence of shapely.Polygon
        nDSM outlines in the DSM's CRS.
    views : sequence of recon3d.stereo.ortho.View
        The images (``image`` (h, w, bands)) and their ``project(x, y, z)``.
    dsm : Raster
        (rows, cols) heights, NaN where unknown.
    metre : float
        One metre in CRS units (the lengths of this module are in metres).
    blur : float
        Gaussian sigma (pixels) applied to the images against sensor noise and texture.
    """
    import cv2

    smooth = [cv2.GaussianBlur(np.asarray(v.image, dtype=np.float32), (0, 0), blur) for v in views]
    smooth = [s[..., None] if s.ndim == 2 else s for s in smooth]
    return [refine_outline(p, views, smooth, dsm, metre=metre) for p in polygons]


def refine_outline(
    polygon: shapely.Polygon, views: Sequence[Any], images: Sequence[np.ndarray], dsm: Raster, *,
    metre: float = 1.0,
) -> OutlineRefinement:
    """One building's outline moved edge by edge to where two images see its eaves.

    Parameters
    ----------
    polygon : shapely.Polygon
    views : sequence of View
    images : sequence of (h, w, bands) float32
        The views' images, smoothed.
    dsm : Raster
    metre : float
        One metre in CRS units.

    Returns
    -------
    OutlineRefinement
    """
    unchanged = OutlineRefinement(polygon, "ndsm", 0.0, 0.0)
    z = eave_height(polygon, dsm, EAVE_INSET * metre)
    if not np.isfinite(z):
        return unchanged
    pair = nadir_views(views, images, polygon, z)[:2]
    if len(pair) < 2:
        return unchanged
    ring = np.asarray(shapely.geometry.polygon.orient(polygon, 1.0).exterior.coords)[:-1]
    (o1, f1), (o2, f2) = (edge_offsets(ring, view, image, z, metre) for view, image in pair)
    agree = f1 & f2 & (np.abs(o1 - o2) <= AGREEMENT * metre)
    if not agree.any():
        return unchanged
    offsets = np.where(agree, 0.5 * (o1 + o2), 0.0)
    moved = _moved_ring(ring, offsets)
    if moved is None:
        return unchanged
    new = shapely.Polygon(moved, [r.coords for r in polygon.interiors])
    if not new.is_valid or not 0.6 < new.area / polygon.area < 1.6:
        return unchanged
    length = np.linalg.norm(np.roll(ring, -1, axis=0) - ring, axis=1)
    searched = length >= MIN_EDGE * metre
    share = float(length[agree].sum() / max(length[searched].sum(), 1e-12))
    shift = float((length * np.abs(offsets))[agree].sum() / length[agree].sum())
    return OutlineRefinement(new, "images", share, shift)


def eave_height(polygon: shapely.Polygon, dsm: Raster, inner: float) -> float:
    """:data:`EAVE_PERCENTILE` of the DSM heights at least ``inner`` inside the outline (NaN if none)."""
    core = polygon.buffer(-inner)
    if core.is_empty:
        core = polygon
    t = dsm.transform
    x0, y0, x1, y1 = core.bounds
    c0, c1 = max(int((x0 - t.c) / t.a), 0), min(int(math.ceil((x1 - t.c) / t.a)), dsm.shape[1])
    r0, r1 = max(int((y1 - t.f) / t.e), 0), min(int(math.ceil((y0 - t.f) / t.e)), dsm.shape[0])
    if c1 <= c0 or r1 <= r0:
        return float("nan")
    x = t.c + (np.arange(c0, c1) + 0.5) * t.a
    y = t.f + (np.arange(r0, r1) + 0.5) * t.e
    heights = dsm.data[r0:r1, c0:c1]
    inside = shapely.contains_xy(core, *np.meshgrid(x, y)) & np.isfinite(heights)
    return float(np.percentile(heights[inside], EAVE_PERCENTILE)) if inside.any() else float("nan")


def nadir_views(
    views: Sequence[Any], images: Sequence[np.ndarray], polygon: shapely.Polygon, z: float
) -> list[tuple[Any, np.ndarray]]:
    """The (view, image) pairs that see the building's centre at height ``z``, most nadir
    first (smallest relief displacement: pixels per 10 m of height)."""
    c = polygon.representative_point()
    x, y = np.array([c.x]), np.array([c.y])
    ranked = []
    for k, (view, image) in enumerate(zip(views, images, strict=True)):
        col0, row0 = view.project(x, y, np.array([z]))
        col1, row1 = view.project(x, y, np.array([z + 10.0]))
        h, w = image.shape[:2]
        if not (np.isfinite([col0[0], row0[0], col1[0], row1[0]]).all() and 0 <= col0[0] < w and 0 <= row0[0] < h):
            continue
        ranked.append((float(np.hypot(col1[0] - col0[0], row1[0] - row0[0])), k))
    return [(views[k], images[k]) for _, k in sorted(ranked)]


def edge_offsets(ring: np.ndarray, view: Any, image: np.ndarray, z: float, metre: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Where one image puts each edge of a counter-clockwise ring, along its outward normal.

    Parameters
    ----------
    ring : (n, 3 or 2) float
        Outline vertices, counter-clockwise, not closed.
    view, image : View and its smoothed (h, w, bands) image
    z : float
        Eave height.
    metre : float
        One metre in CRS units.

    Returns
    -------
    offsets : (n,) float
        Outward shift of edge i (from vertex i to i + 1); 0 where not found.
    found : (n,) bool
    """
    ring = ring[:, :2]
    n = len(ring)
    reach = REACH * metre
    across = np.arange(-reach, reach + 1e-9 * metre, PROFILE_STEP * metre)
    inner, outer = across <= -0.5 * reach, across >= 0.5 * reach
    offsets, found = np.zeros(n), np.zeros(n, bool)
    for i in range(n):  # a loop over edges (a handful per building); each edge is vectorised
        a, b = ring[i], ring[(i + 1) % n]
        length = float(np.hypot(*(b - a)))
        if length < MIN_EDGE * metre:
            continue
        along = (b - a) / length
        normal = np.array([along[1], -along[0]])  # outward for a counter-clockwise ring
        s = np.arange(0.15 * length, 0.85 * length + 1e-9 * metre, STEP * metre)
        xy = a + s[:, None, None] * along + across[None, :, None] * normal  # (lines, samples, 2)
        colour = _colours(view, image, xy[..., 0], xy[..., 1], z)
        t = _edge_crossing(colour, inner, outer, across)
        if t is not None:
            offsets[i], found[i] = t, True
    return offsets, found


def _edge_crossing(colour: np.ndarray, inner: np.ndarray, outer: np.ndarray, across: np.ndarray) -> float | None:
    """Offset where the share of roof-coloured samples on the (lines, samples, bands)
    profiles falls through 0.5 going outward; None when the profiles show no such edge.

    The roof colour is the median of the ``inner`` samples; the colour beyond the edge
    the median of the ``outer`` samples that are not roof (further from it than
    :data:`ROOF_QUANTILE` of the inner ones, at least :data:`MIN_COLOUR_STEP`). A sample is
    roof when it is nearer the roof colour than that one: a blurred edge is found half
    way up its step, not where it starts.
    """
    inside = colour[:, inner].reshape(-1, colour.shape[-1])
    inside = inside[np.isfinite(inside).all(axis=1)]
    if len(inside) < 10:
        return None
    roof = np.median(inside, axis=0)
    bound = max(float(np.percentile(np.linalg.norm(inside - roof, axis=1), ROOF_QUANTILE)), MIN_COLOUR_STEP)
    beyond = colour[:, outer].reshape(-1, colour.shape[-1])
    beyond = beyond[np.isfinite(beyond).all(axis=1)]
    beyond = beyond[np.linalg.norm(beyond - roof, axis=1) > bound]
    if len(beyond) < 10:
        return None
    other = np.median(beyond, axis=0)
    with np.errstate(invalid="ignore"):  # NaN samples (outside the image) count as not roof
        is_roof = np.linalg.norm(colour - roof, axis=-1) < np.linalg.norm(colour - other, axis=-1)
    share = is_roof.mean(axis=0)
    if share[0] < INNER_ROOF or share[-1] > OUTER_ROOF:
        return None
    k = int(np.flatnonzero(share < 0.5)[0])
    if k == 0:
        return None
    return float(across[k - 1] + (share[k - 1] - 0.5) / (share[k - 1] - share[k]) * (across[k] - across[k - 1]))


def _colours(view: Any, image: np.ndarray, x: np.ndarray, y: np.ndarray, z: float) -> np.ndarray:
    """(..., bands) bilinear colours of the image where points (x, y) at height z project; NaN outside."""
    col, row = view.project(x, y, np.full_like(x, z))
    coords = np.stack([np.nan_to_num(row, nan=-10.0).ravel(), np.nan_to_num(col, nan=-10.0).ravel()])
    bands = [ndimage.map_coordinates(image[..., k], coords, order=1, mode="constant", cval=np.nan)
             for k in range(image.shape[-1])]
    return np.stack(bands, axis=-1).reshape(*x.shape, image.shape[-1])


def _moved_ring(ring: np.ndarray, offsets: np.ndarray) -> np.ndarray | None:
    """(n, 2) corners of the ring whose edges moved by ``offsets`` along their outward normals.

    A corner is where its two moved edges meet (:func:`~recon3d.buildings.outline.ring_corners`);
    between two nearly parallel edges (within 10 degrees: a step in the outline, where
    the intersection runs far off), the midpoint of their moved ends.
    """
    a = ring[:, :2]
    b = np.roll(a, -1, axis=0)
    along = (b - a) / np.maximum(np.linalg.norm(b - a, axis=1, keepdims=True), 1e-12)
    outward = np.column_stack([along[:, 1], -along[:, 0]])
    start, end = a + offsets[:, None] * outward, b + offsets[:, None] * outward
    corner = ring_corners(outward, np.einsum("ij,ij->i", start, outward))
    d0 = np.roll(along, 1, axis=0)
    parallel = np.abs(d0[:, 0] * along[:, 1] - d0[:, 1] * along[:, 0]) < math.sin(math.radians(10.0))
    corner[parallel] = 0.5 * (np.roll(end, 1, axis=0) + start)[parallel]
    return corner if np.isfinite(corner).all() else None
