"""True orthophotos of a stereo input, and the image-difference map that checks a DSM.

A true orthophoto shows every cell of a surface (DSM, DTM, or the DTM with the
building model) as seen straight from above: each cell centre, at its surface height,
is projected into every image; the images that see it (a z-buffer in image space: on
one ray the highest surface is the one seen) offer its colour, and the most nadir one
gives it, so roofs lean nowhere and the ground hidden behind them is nodata where no
image saw it. A majority vote over 5 x 5 cells keeps a cell's source from flickering
between images.

The difference map follows the AMOBE study's quality control without ground truth:
where the DSM is right, two images orthorectified on it agree; where it is wrong, the
same ground lands at different places in the two and they differ. Per matched pair,
both images are orthorectified on the DSM, their local normalised cross-correlation
computed over a window of about 2 m (where both are textured), and ``1 - NCC``
averaged over the pairs and over the orthophoto cells of each DSM cell.

Both work for frame cameras (COLMAP model) and RPC cameras alike: a :class:`View` only
needs an image and a ground-to-image projection.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from affine import Affine

from recon3d.core.raster import Raster

__all__ = ["OrthoImage", "View", "doubtful_cells", "doubtful_regions", "frame_views", "image_gsd", "local_ncc", "ortho_difference",
           "looks_on", "ortho_grid", "satellite_views", "true_ortho"]

#: Pixels per side of the image-space bins of the z-buffer: an orthophoto cell at the
#: image's ground sample distance projects to about one pixel, so 2 x 2 pixel bins
#: leave no gap through a roof.
ZBUFFER_BIN_PX = 2

#: Side of the window (orthophoto cells) of the local cross-correlation and of the
#: majority vote on a cell's source image.
NCC_WINDOW = 7
SOURCE_WINDOW = 5

#: Least standard deviation (grey levels of 0-255, after normalisation) both images
#: must have in a window for their correlation to say anything: flat roofs and
#: asphalt of one colour agree whatever the DSM.
MIN_TEXTURE = 4.0


class View(NamedTuple):
    """An image and how the ground projects into it.

    Attributes
    ----------
    name : str
    image : (h, w, bands) uint8 or float32
        RGB for frame images, one band for panchromatic ones.
    project : callable
        ``project(x, y, z) -> (col, row)``: world coordinates (arrays of one shape,
        the output CRS) to float pixel coordinates, (0, 0) the centre of the top-left pixel.
    """

    name: str
    image: np.ndarray
    project: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


class OrthoImage(NamedTuple):
    """A true orthophoto on a grid of ``transform``.

    Attributes
    ----------
    data : (bands, rows, cols) uint8 or float32
        Colours (RGB) or grey values; 0 (uint8) or NaN where no image sees the cell.
    seen : (rows, cols) bool
        Cells some image sees.
    source : (rows, cols) int16
        Index of the view each cell comes from, -1 where none.
    transform : affine.Affine
    """

    data: np.ndarray
    seen: np.ndarray
    source: np.ndarray
    transform: Affine


# --------------------------------------------------------------------------- views


def frame_views(scene) -> list[View]:
    """The images of a COLMAP scene (:class:`~recon3d.io.colmap.StereoScene`) as views, RGB."""
    import cv2

    offset = np.asarray(scene.offset, dtype=np.float64)
    views = []
    for cam in scene.cameras:
        image = cv2.imread(str(cam.image_path), cv2.IMREAD_COLOR)
        if image is None:
            raise ValueError(f"{cam.image_path}: unreadable image")

        def project(x, y, z, cam=cam):
            xyz = np.column_stack([np.ravel(x), np.ravel(y), np.ravel(z)]) - offset
            uv, depth = cam.project(xyz, distort=True)
            uv[depth <= 0] = np.nan
            return uv[:, 0].reshape(np.shape(x)), uv[:, 1].reshape(np.shape(x))

        views.append(View(cam.name, cv2.cvtColor(image, cv2.COLOR_BGR2RGB), project))
    return views


def satellite_views(cameras, crs, bias_px=(0.0, 0.0)) -> list[View]:
    """Two RPC images (:class:`~recon3d.io.rpc.RPCCamera`) as views, one band float32.

    Parameters
    ----------
    cameras : sequence of RPCCamera
    crs : pyproj.CRS
        CRS of the world coordinates (the products'); heights are those of the DSM.
    bias_px : (2,) float
        (col, row) shift of the second image found by matching (``relative_bias_px``).
    """
    import pyproj
    import rasterio

    to_lonlat = pyproj.Transformer.from_crs(crs, 4326, always_xy=True)
    views = []
    for k, cam in enumerate(cameras):
        with rasterio.open(cam.image_path) as src:
            image = src.read(1).astype(np.float32)
            image[~src.read_masks(1).astype(bool)] = np.nan
        shift = np.asarray(bias_px if k else (0.0, 0.0), dtype=np.float64)

        def project(x, y, z, cam=cam, shift=shift):
            lon, lat = to_lonlat.transform(x, y)
            row, col = cam.project(lon, lat, z)
            return col + shift[0], row + shift[1]

        views.append(View(cam.name or str(k), image[:, :, None], project))
    return views


# --------------------------------------------------------------------------- grid


def ortho_grid(surface: Raster, gsd: float) -> tuple[Raster, int]:
    """The surface resampled to cells of about ``gsd``, a whole fraction of its own.

    Returns
    -------
    heights : Raster
        (rows * k, cols * k) bilinear heights (NaN where the surface has none nearby).
    k : int
        Orthophoto cells per surface cell along each axis.
    """
    k = max(1, int(round(surface.resolution / max(gsd, 1e-9))))
    rows, cols = surface.shape
    t = surface.transform
    transform = Affine(t.a / k, t.b, t.c, t.d, t.e / k, t.f)
    x = t.c + (np.arange(cols * k) + 0.5) * t.a / k
    y = t.f + (np.arange(rows * k) + 0.5) * t.e / k
    xx, yy = np.meshgrid(x, y)
    z = surface.sample(xx.ravel(), yy.ravel(), bilinear=True).reshape(xx.shape)
    near = np.repeat(np.repeat(surface.data, k, axis=0), k, axis=1)
    z = np.where(np.isfinite(z), z, near)  # bilinear needs four neighbours; the cell's own value else
    return Raster(z.astype(np.float32), transform, surface.crs), k


def image_gsd(views: list[View], surface: Raster) -> float:
    """Median ground size of a pixel of ``views`` at the surface's centre (CRS units)."""
    x0, y0 = surface.transform @ (surface.shape[1] / 2, surface.shape[0] / 2)
    z0 = float(np.nanmedian(surface.data)) if np.isfinite(surface.data).any() else 0.0
    sizes = [1.0 / p for p in (pixels_per_unit(v, x0, y0, z0) for v in views) if p > 0]
    return float(np.median(sizes)) if sizes else surface.resolution


def pixels_per_unit(view: View, x: float, y: float, z: float) -> float:
    """Image pixels per CRS unit of horizontal ground at (x, y, z) in ``view``, the mean
    of both axes; 0 where the point does not land."""
    col, row = view.project(np.array([x, x + 1.0, x]), np.array([y, y, y + 1.0]), np.full(3, z))
    col, row = np.asarray(col, np.float64), np.asarray(row, np.float64)
    scale = 0.5 * (np.hypot(col[1] - col[0], row[1] - row[0]) + np.hypot(col[2] - col[0], row[2] - row[0]))
    return float(scale) if np.isfinite(scale) else 0.0


def _cell_centres(grid: Raster) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = grid.cell_centers()
    return np.meshgrid(xs, ys)


# --------------------------------------------------------------------------- orthophoto


def _look(view: View, x, y, z, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where each cell lands in the view, whether the view sees it, and how obliquely.

    Returns
    -------
    col, row : (rows, cols) float32
    visible : (rows, cols) bool
        On the image and within ``tolerance`` of the highest surface landing in the
        same bin of :data:`ZBUFFER_BIN_PX` pixels (on one ray, the highest point is seen).
    lean : (rows, cols) float
        Image displacement per unit of height over that per unit of ground distance:
        the tangent of the viewing angle off nadir.
    """
    h, w = view.image.shape[:2]
    col, row = view.project(x, y, z)
    c_up, r_up = view.project(x, y, z + 1.0)
    c_east, r_east = view.project(x + 1.0, y, z)
    lean = np.hypot(c_up - col, r_up - row) / np.maximum(np.hypot(c_east - col, r_east - row), 1e-9)
    finite = np.isfinite(z) & np.isfinite(col) & np.isfinite(row)
    on = finite & (col >= -0.5) & (col <= w - 0.5) & (row >= -0.5) & (row <= h - 0.5)
    b = ZBUFFER_BIN_PX
    nb = (w // b + 1)

    def bin_of(c, r):  # the z-buffer bin of pixel coordinates on the image
        return (np.floor(r + 0.5).astype(np.int64) // b) * nb + np.floor(c + 0.5).astype(np.int64) // b

    bins = bin_of(np.where(on, col, 0), np.where(on, row, 0))
    top = np.full((h // b + 1) * nb, -np.inf)
    np.maximum.at(top, bins[on], z[on])
    wall_col, wall_row, wall_z = _wall_samples(view, x, y, z, col, row, tolerance)
    np.maximum.at(top, bin_of(wall_col, wall_row), wall_z)
    visible = on & (z >= top[bins] - tolerance - _slope_allowance(z, x, col, row))
    if view.image.dtype != np.uint8:  # no-data pixels of a satellite image see nothing
        r = np.clip(np.rint(np.nan_to_num(row)), 0, h - 1).astype(np.int64)
        c = np.clip(np.rint(np.nan_to_num(col)), 0, w - 1).astype(np.int64)
        visible &= np.isfinite(view.image[r, c, 0])
    return col.astype(np.float32), row.astype(np.float32), visible, lean


def _wall_samples(view: View, x, y, z, col, row, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on the walls of the surface, for the z-buffer: (m,) float pixel columns
    and rows on the image, and (m,) heights.

    A grid of heights has no cell on a wall, yet in an oblique view the wall hides the
    ground behind its building: without it, the ground cells whose rays cross the wall
    (and land in the image where the wall is) counted as seen, and took the wall's
    colours. Each cell standing more than ``tolerance`` above its lowest 4-neighbour
    is extended down to it by points every half a z-buffer bin along the wall's image.
    """
    h, w = view.image.shape[:2]
    p = np.pad(z, 1, constant_values=np.nan)
    low = np.fmin(np.fmin(p[:-2, 1:-1], p[2:, 1:-1]), np.fmin(p[1:-1, :-2], p[1:-1, 2:]))
    wall = np.isfinite(z) & (z - low > tolerance) & np.isfinite(col) & np.isfinite(row)  # NaN compares False
    top_z, foot_z = z[wall], low[wall]
    c0, r0 = col[wall].astype(np.float64), row[wall].astype(np.float64)
    c1, r1 = (np.asarray(v, np.float64) for v in view.project(x[wall], y[wall], foot_z))
    ok = np.isfinite(c1) & np.isfinite(r1)
    top_z, foot_z, c0, r0, c1, r1 = (v[ok] for v in (top_z, foot_z, c0, r0, c1, r1))
    steps = np.ceil(np.hypot(c1 - c0, r1 - r0) / (0.5 * ZBUFFER_BIN_PX)).astype(np.int64) + 1
    owner = np.repeat(np.arange(len(steps)), steps)
    # from the top (t = 0) down to just above the foot, which is the neighbour's own cell
    t = (np.arange(len(owner)) - (np.cumsum(steps) - steps)[owner]) / steps[owner]
    cs, rs = c0[owner] + t * (c1 - c0)[owner], r0[owner] + t * (r1 - r0)[owner]
    zs = top_z[owner] + t * (foot_z - top_z)[owner]
    inside = (cs >= -0.5) & (cs <= w - 0.5) & (rs >= -0.5) & (rs <= h - 0.5)
    return cs[inside], rs[inside], zs[inside]


def _slope_allowance(z: np.ndarray, x: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Height a sloped surface drops across one z-buffer bin: cells of one bin come from
    neighbouring rays, so on a roof seen at a grazing angle the lower ones are not hidden
    by the higher ones. Slope (capped at 2, a wall's edge is no slope) times the bin's
    ground size."""
    cell = float(np.nanmedian(np.abs(np.diff(x[0, :2])))) if x.shape[1] > 1 else 1.0
    gy, gx = np.gradient(np.nan_to_num(z, nan=float(np.nanmedian(z)) if np.isfinite(z).any() else 0.0), cell)
    pixels = np.hypot(*np.gradient(np.nan_to_num(col, nan=0.0))) + 1e-9  # image pixels per cell
    return np.minimum(np.hypot(gx, gy), 2.0) * ZBUFFER_BIN_PX * cell / np.minimum(pixels, 1e3)


def _sample(view: View, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """(rows, cols, bands) bilinear image values at float pixel coordinates."""
    import cv2

    image = view.image
    out = cv2.remap(image, np.nan_to_num(col, nan=-10.0), np.nan_to_num(row, nan=-10.0), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(*col.shape, image.shape[2])


def looks_on(surface: Raster, views: list[View], gsd: float, *, tolerance: float) -> tuple[Raster, int, list]:
    """The orthophoto grid of ``surface`` (see :func:`ortho_grid`) and, per view, where its
    cells land, whether the view sees them and how obliquely (see :func:`_look`)."""
    grid, k = ortho_grid(surface, gsd)
    x, y = _cell_centres(grid)
    z = grid.data.astype(np.float64)
    return grid, k, [_look(v, x, y, z, tolerance) for v in views]


def true_ortho(surface: Raster, views: list[View], gsd: float, *, tolerance: float, looks=None,
               objects: np.ndarray | None = None) -> OrthoImage:
    """True orthophoto of ``views`` on ``surface`` at about ``gsd``.

    Each cell comes from the most nadir view that sees it, smoothed by a majority vote
    over :data:`SOURCE_WINDOW` cells. With ``objects`` (raised objects: buildings,
    trees) each object takes one view wherever that view sees it, the one seeing most
    of it (the most nadir on a tie), so that seamlines between images run on low ground
    and never through a roof, where the images' relief displacement differs most.

    Parameters
    ----------
    surface : Raster
        (rows, cols) heights (DSM, DTM or model DSM), NaN where unknown.
    views : list of View
    gsd : float
        Target cell size (the images' ground sample distance), CRS units.
    tolerance : float
        Height below the highest surface on the same ray still counted as seen (CRS units).
    looks : tuple, optional
        :func:`looks_on` of the same arguments, when already computed.
    objects : (rows, cols) int, optional
        Object labels on the surface's grid (0: none), e.g. :func:`raised_objects`.

    Returns
    -------
    OrthoImage
        On the surface's grid refined ``k`` times (see :func:`ortho_grid`).
    """
    from scipy import ndimage

    grid, k, looks = looks or looks_on(surface, views, gsd, tolerance=tolerance)
    lean = np.stack([np.where(vis, ln, np.inf) for _, _, vis, ln in looks])  # (views, rows, cols)
    best = np.argmin(lean, axis=0)
    seen = np.isfinite(lean).any(axis=0)
    votes = np.stack([ndimage.uniform_filter((best == v) & seen, SOURCE_WINDOW, mode="nearest")
                      for v in range(len(views))])
    votes[~np.isfinite(lean)] = -1.0  # a view that does not see the cell cannot win it
    source = np.where(seen, np.argmax(votes, axis=0), -1).astype(np.int16)
    if objects is not None and objects.any():
        source = _one_view_per_object(source, lean, np.repeat(np.repeat(objects, k, axis=0), k, axis=1))
    bands = views[0].image.shape[2]
    dtype = views[0].image.dtype
    data = np.zeros((*grid.shape, bands), dtype) if dtype == np.uint8 else np.full((*grid.shape, bands), np.nan, dtype)
    for k, (view, (col, row, _, _)) in enumerate(zip(views, looks, strict=True)):
        mine = source == k
        if mine.any():
            data[mine] = _sample(view, col, row)[mine]
    return OrthoImage(np.moveaxis(data, -1, 0), seen, source, grid.transform)


def _one_view_per_object(source: np.ndarray, lean: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """``source`` with each object's cells taken from the view that sees most of it
    (the lowest mean lean on a tie) wherever that view sees them.

    Parameters
    ----------
    source : (rows, cols) int16
    lean : (views, rows, cols) float
        inf where the view does not see the cell.
    objects : (rows, cols) int
    """
    n = int(objects.max()) + 1
    inside = objects > 0
    label = objects[inside]
    sees = np.isfinite(lean[:, inside])  # (views, cells)
    count = np.stack([np.bincount(label, weights=s, minlength=n) for s in sees])
    mean_lean = np.stack([np.bincount(label, weights=np.where(s, ln, 0.0), minlength=n)
                          for s, ln in zip(sees, lean[:, inside], strict=True)]) / np.maximum(count, 1)
    # most cells seen first, then the smaller lean: one sortable key per (view, object)
    key = count - mean_lean / (1.0 + mean_lean.max(initial=0.0))
    chosen = np.argmax(key, axis=0)  # (objects,)
    view = chosen[label]
    out = source.copy()
    mine = sees[view, np.arange(len(label))]
    flat = out[inside]
    flat[mine] = view[mine]
    out[inside] = flat
    return out


def raised_objects(ndsm: Raster, min_height: float, margin: int = 2) -> np.ndarray:
    """(rows, cols) int32 labels of the connected raised objects of an nDSM (above
    ``min_height``), each grown by ``margin`` cells to take in its walls and eaves."""
    from scipy import ndimage

    raised = np.nan_to_num(ndsm.data, nan=0.0) >= min_height
    labels, _ = ndimage.label(raised)
    if margin > 0 and labels.any():
        grown = ndimage.grey_dilation(labels, size=2 * margin + 1)
        labels = np.where(labels > 0, labels, grown)
    return labels.astype(np.int32)


# --------------------------------------------------------------------------- difference map


def _grey(view: View, col, row) -> np.ndarray:
    values = _sample(view, col, row).astype(np.float32)
    return values.mean(axis=2) if values.shape[2] > 1 else values[..., 0]


def _normalised(grey: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Grey values moved to mean 128, standard deviation 40 over ``mask`` (radiometric normalisation)."""
    v = grey[mask]
    if v.size < 2 or not np.std(v) > 0:
        return np.zeros_like(grey)
    return (grey - v.mean()) / v.std() * 40.0 + 128.0


def local_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray, window: int = NCC_WINDOW) -> np.ndarray:
    """(rows, cols) normalised cross-correlation of two images over a moving window.

    NaN outside ``mask`` and where either image has less than :data:`MIN_TEXTURE`
    standard deviation in the window (nothing to compare).
    """
    from scipy import ndimage

    m = mask.astype(np.float64)
    n = ndimage.uniform_filter(m, window, mode="constant")
    a, b = np.where(mask, a, 0.0), np.where(mask, b, 0.0)

    def mean(v):
        with np.errstate(invalid="ignore", divide="ignore"):
            return ndimage.uniform_filter(v, window, mode="constant") / n

    ma, mb = mean(a), mean(b)
    va, vb = mean(a * a) - ma**2, mean(b * b) - mb**2
    cov = mean(a * b) - ma * mb
    textured = (va > MIN_TEXTURE**2) & (vb > MIN_TEXTURE**2) & (n > 0.5)
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = cov / np.sqrt(va * vb)
    return np.where(mask & textured, np.clip(ncc, -1.0, 1.0), np.nan)


def ortho_difference(dsm: Raster, views: list[View], pairs: list[tuple[int, int]], gsd: float, *,
                     tolerance: float, looks=None) -> Raster:
    """The image-difference map of ``pairs`` of views on ``dsm``: ``1 - NCC`` per DSM cell.

    Returns
    -------
    Raster
        (rows, cols) float32 on the DSM grid, 0 where the two images of every pair
        agree perfectly, up to 2; NaN where no pair sees the cell in both images with
        texture. ``looks``: :func:`looks_on` of the DSM, when already computed.
    """
    grid, k, looks = looks or looks_on(dsm, views, gsd, tolerance=tolerance)
    total = np.zeros(grid.shape)
    count = np.zeros(grid.shape)
    for i, j in pairs:
        (ci, ri, seen_i, _), (cj, rj, seen_j, _) = looks[i], looks[j]
        both = seen_i & seen_j
        a = _normalised(_grey(views[i], ci, ri), both)
        b = _normalised(_grey(views[j], cj, rj), both)
        ncc = local_ncc(a, b, both)
        judged = np.isfinite(ncc)
        total[judged] += 1.0 - ncc[judged]
        count[judged] += 1
    rows, cols = dsm.shape
    with np.errstate(invalid="ignore"):
        per_cell = total.reshape(rows, k, cols, k).sum(axis=(1, 3)) / count.reshape(rows, k, cols, k).sum(axis=(1, 3))
    return dsm.like(per_cell.astype(np.float32), product="image difference (1 - NCC)")


def doubtful_cells(diff: Raster, threshold: float) -> np.ndarray:
    """(rows, cols) bool: cells whose 3 x 3 median difference exceeds ``threshold`` (one
    cell of disagreement is texture noise, not a wrong DSM; unjudged cells count as agreement)."""
    from scipy import ndimage

    return ndimage.median_filter(np.nan_to_num(diff.data, nan=0.0), 3, mode="nearest") > threshold


def doubtful_regions(diff: Raster, threshold: float, min_area: float, labels: np.ndarray | None = None,
                     ids: list[str] | None = None) -> list[dict]:
    """Connected areas of :func:`doubtful_cells` of ``min_area`` or more.

    Parameters
    ----------
    diff : Raster
        The map of :func:`ortho_difference`.
    threshold : float
    min_area : float
        CRS units squared.
    labels : (rows, cols) int, optional
        1 + building index per cell (0 elsewhere), with the buildings' ``ids``.

    Returns
    -------
    list of dict
        ``area``, ``centre`` [x, y], ``mean`` difference and ``buildings`` (ids
        touched), largest first.
    """
    from scipy import ndimage

    regions, n = ndimage.label(doubtful_cells(diff, threshold))
    if not n:
        return []
    cells = np.bincount(regions.ravel(), minlength=n + 1)
    keep = np.flatnonzero(cells[1:] * diff.resolution**2 >= min_area) + 1
    boxes = ndimage.find_objects(regions)
    out = []
    for r in keep:
        box = boxes[r - 1]
        inside = regions[box] == r
        values = diff.data[box][inside]
        if not np.isfinite(values).any():  # only cells the median filter reached, none judged
            continue
        rows, cols = np.nonzero(inside)
        x, y = diff.transform @ (box[1].start + cols.mean() + 0.5, box[0].start + rows.mean() + 0.5)
        touched = (sorted({ids[v - 1] for v in np.unique(labels[box][inside]) if v > 0})
                   if labels is not None and ids else [])
        out.append({"area": round(float(cells[r] * diff.resolution**2), 1), "centre": [round(x, 2), round(y, 2)],
                    "mean": round(float(np.nanmean(values)), 3), "buildings": touched})
    return sorted(out, key=lambda d: -d["area"])
