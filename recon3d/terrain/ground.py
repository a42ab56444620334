"""Ground filtering: which points lie on the bare earth.

Every method starts from the same minimum surface (lowest point per cell, low outliers
removed, holes filled) and differs in how it finds the cells that are not terrain:

``smrf``
    Progressive morphological filter in the style of SMRF (Pingel et al., 2013):
    openings with growing windows; a cell that drops by more than the terrain slope
    allows over the window is an object.
``tophat``
    The criteria of the classic semi-automatic DSM/DTM production line: a cell is an
    object when its morphological top-hat (height above the opening with the largest
    building window) is large, when it stands above its neighbours, or when the
    surface is steep there; points with a poor matching score (stereo) are not used.
``drape``
    A surface-based filter for stereo DSMs in the spirit of CNES Bulldozer: a cloth
    rises from below on a coarse-to-fine pyramid, held back by its tension, and settles
    on the terrain without entering buildings. It needs no multiple returns and
    tolerates noise and holes.

The remaining terrain cells are interpolated into a provisional surface, and every
point within a slope- and noise-dependent tolerance of it is ground.
``auto`` (the default) picks ``smrf`` for LiDAR (clouds with return numbers) and for
clouds without returns whose minimum surface is clean (noise under 0.2 m), ``tophat``
for noisier ones (:func:`pick_method`), with parameters measured on the data. On
LiDAR-derived surfaces degraded to stereo quality (holes, and 0.1, 0.3 or 0.5 m of
noise), DTM RMS (m) against the provider's ground:

======  =====================  =====================  =====================
file    0.1 m: tophat smrf      0.3 m: tophat smrf      0.5 m: tophat smrf
======  =====================  =====================  =====================
delft   0.279  0.190            0.384  0.408            0.512  0.728
ign     0.088  0.075            0.197  0.169            0.233  0.282
autzen  0.582  0.661            0.888  0.920            1.106  1.140
======  =====================  =====================  =====================

``drape`` was never the lowest (0.097-1.167), so it is offered, not chosen.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from affine import Affine
from scipy import ndimage

from recon3d.config import GroundConfig
from recon3d.core.geo import Units
from recon3d.core.pointcloud import ASPRS, PointCloud
from recon3d.core.raster import Raster, grid_for_bounds
from recon3d.errors import InputError
from recon3d.terrain.dsm import grid_points
from recon3d.terrain.dtm import fill_gaps, fill_nearest

log = logging.getLogger(__name__)

__all__ = [
    "METHODS",
    "GroundResult",
    "MinimumSurface",
    "classify_ground",
    "ground_tolerances",
    "label_ground",
    "lowest_points",
    "minimum_surface",
    "pick_method",
    "quality_cut",
    "surface_cell",
    "surface_grid",
    "terrain",
    "terrain_gradient",
]


@dataclass
class GroundResult:
    """Ground labels and the parameters the filter used.

    Attributes
    ----------
    is_ground : (n,) bool
    for_dtm : (n,) bool
        The ground points close enough to the provisional terrain to shape the DTM;
        the rest of the ground (grass, low vegetation up to the threshold) would lift it.
    params : dict
        Every parameter, with ``{"value": ..., "reason": ...}`` for those chosen from
        the data, ready for run.json.
    terrain : Raster or None
        The provisional terrain the points were compared with.
    """

    is_ground: np.ndarray
    for_dtm: np.ndarray | None = None
    params: dict = field(default_factory=dict)
    terrain: Raster | None = None

    def __post_init__(self) -> None:
        if self.for_dtm is None:
            self.for_dtm = self.is_ground


@dataclass
class MinimumSurface:
    """The lowest point per cell and the data-driven parameters every method shares.

    Attributes
    ----------
    raster : Raster
        Hole-free minimum surface (CRS height units).
    measured : (rows, cols) bool
        Cells that hold at least one (non-outlier) point.
    window : float
        Largest object width to remove, CRS units.
    slope : float
        Terrain slope tolerated, rise over run (dimensionless, metric).
    noise : float
        Height noise of the surface, CRS height units (NMAD of second differences).
    trend : (rows, cols) float
        Large-scale terrain shape (opening with the largest window, smoothed). The
        methods filter ``raster - trend``, so that a steep hillside is as flat to them as
        a plain and the slope tolerance only has to cover the terrain's local relief.
    """

    raster: Raster
    measured: np.ndarray
    window: float
    slope: float
    noise: float
    trend: np.ndarray

    @property
    def cell(self) -> float:
        return self.raster.resolution

    @property
    def data(self) -> np.ndarray:
        """(rows, cols) the surface minus its trend."""
        return self.raster.data.astype(np.float64) - self.trend

    def terrain(self, residual: np.ndarray, objects: np.ndarray) -> Raster:
        """Terrain raster: residual cells that are not objects, gaps interpolated, trend added back."""
        return self.raster.like(fill_gaps(residual, ~objects & self.measured) + self.trend)


def classify_ground(
    cloud: PointCloud, config: GroundConfig, units: Units, cell: float, *, grid: tuple | None = None
) -> GroundResult:
    """Label ground points with the method named in ``config``.

    The whole cloud at once; the pipeline runs the same steps tile by tile
    (:func:`lowest_points`, :func:`minimum_surface`, :func:`terrain`, :func:`label_ground`).

    Parameters
    ----------
    cloud : PointCloud
    config : GroundConfig
    units : Units
        Units of the cloud's CRS; metric parameters are converted with it.
    cell : float
        DSM cell size (CRS units); the minimum surface uses it or 1 m, whichever is coarser.
    grid : (transform, shape), optional
        The minimum surface's grid; by default :func:`surface_grid` over the cloud's bounds.

    Raises
    ------
    InputError
        ``method="provider"`` on a cloud without class 2, or too few points to filter.
    """
    if config.method == "provider":
        c = cloud.classification
        if c is None or not np.any(c == ASPRS.GROUND):
            raise InputError("ground.method='provider' but the input has no ground points (class 2)")
        return GroundResult(c == ASPRS.GROUND, params={"method": "provider"})
    if len(cloud) < 3:
        raise InputError(f"the point cloud has {len(cloud)} point(s); ground filtering needs at least 3")
    params: dict = {"method": None}  # chosen once the surface's noise is measured
    gcell, why = surface_cell(config, units, cell)
    params["cell"] = _chosen(gcell, why)
    if grid is None:
        grid = surface_grid(cloud.bounds, gcell)
    cut = quality_cut(cloud.attributes.get("quality"))
    if cut is not None:
        params["quality_cut"] = _chosen(cut, QUALITY_CUT_REASON)
    zmin = lowest_points(cloud, *grid, quality_cut=cut)
    surface = minimum_surface(zmin, grid[0], config, units, params)
    method, why = pick_method(config, "number_of_returns" in cloud.attributes, surface.noise * units.vertical)
    params["method"] = _chosen(method, why)
    found = terrain(surface, method, units)
    is_ground, for_dtm, tolerance_params = label_ground(cloud.xyz, found, config, units, noise=surface.noise)
    params.update(tolerance_params)
    log.info("%s: %d of %d points ground (%.1f %%)", method, is_ground.sum(), len(cloud), 100 * is_ground.mean())
    return GroundResult(is_ground, for_dtm, params, found)


#: Height noise of the minimum surface (m) below which a cloud without return numbers
#: is filtered with SMRF rather than the top-hat criteria (see :func:`pick_method`).
SMRF_MAX_NOISE = 0.2


def pick_method(config: GroundConfig, returns: bool, noise: float) -> tuple[str, str]:
    """The filter to run and why.

    ``returns``: the points carry return numbers (LiDAR); ``noise``: the minimum
    surface's height noise in metres (:attr:`MinimumSurface.noise`). Without return
    numbers, SMRF below :data:`SMRF_MAX_NOISE`, the top-hat criteria above: on the
    survey family rendered at 400 px, SMRF brought two hilly surveys' ground check
    points from 4.40 and 1.82 m RMS to 0.12 and 0.13 m (the top-hat's 60 m opening
    shaved their hilltops), and on LiDAR turned into stereo-like surfaces (module
    table) it had the lower DTM error at 0.1 m of noise on two files of three, the
    top-hat at 0.3 m on two of three and at 0.5 m on all three.
    """
    if config.method != "auto":
        return config.method, "config"
    if returns:
        return "smrf", "LiDAR (the points carry return numbers)"
    if noise < SMRF_MAX_NOISE:
        return "smrf", (f"no return numbers, surface noise {noise:.2f} m < {SMRF_MAX_NOISE} m: "
                        "the progressive filter measured best on clean surfaces, and follows hills")
    return "tophat", (f"no return numbers, surface noise {noise:.2f} m >= {SMRF_MAX_NOISE} m: "
                      "top-hat criteria measured best on noisy, holed surfaces")


def surface_cell(config: GroundConfig, units: Units, dsm_cell: float) -> tuple[float, str]:
    """Cell of the minimum surface (CRS units) and why."""
    if config.cell:
        return units.length(config.cell), "config"
    return max(dsm_cell, units.length(1.0)), "1 m, or the DSM cell when coarser: finer minimum surfaces only add noise"


def surface_grid(bounds: np.ndarray, cell: float) -> tuple[Affine, tuple[int, int]]:
    """The minimum surface's grid over ``bounds`` ((2, 2+) lowest and highest corner):
    cells of ``cell``, snapped to multiples of it (:func:`~recon3d.core.raster.grid_for_bounds`).

    Returns
    -------
    transform : Affine
    shape : (rows, cols)
    """
    lo, hi = bounds
    return grid_for_bounds(lo[0], lo[1], hi[0], hi[1], cell)


#: Why the stereo points of the worst matching scores do not shape the minimum surface.
QUALITY_CUT_REASON = "stereo matching score: worst 10 % not used"


def quality_cut(score: np.ndarray | None) -> float | None:
    """The matching score (stereo ``quality``) below which a point is not trusted, None without scores."""
    return None if score is None or not len(score) else float(np.percentile(score, 10))


def lowest_points(
    cloud: PointCloud, transform, shape: tuple[int, int], *, quality_cut: float | None = None,
    origin: tuple[int, int] = (0, 0),
) -> np.ndarray:
    """(rows, cols) float64 lowest trusted point per cell of the minimum surface's grid, NaN where none.

    Points classified noise, stereo points scoring below ``quality_cut`` and stereo
    guesses (``observed`` 0: a filled-in disparity, which on a hillside filled from the
    far, lower side lies metres under the ground) are not trusted.
    ``origin`` as in :func:`recon3d.terrain.dsm.grid_points`.
    """
    keep = np.ones(len(cloud), bool)
    if cloud.classification is not None:
        keep &= cloud.classification != ASPRS.NOISE
    observed = cloud.attributes.get("observed")
    if observed is not None:
        keep &= observed > 0
    score = cloud.attributes.get("quality")
    if score is not None and quality_cut is not None:
        keep &= score >= quality_cut
    keep = None if keep.all() or not keep.any() else keep
    return grid_points(cloud.xyz, transform, shape, reducer="min", origin=origin, keep=keep)


def minimum_surface(
    zmin: np.ndarray, transform: Affine, config: GroundConfig, units: Units, params: dict
) -> MinimumSurface:
    """The minimum surface from the lowest points per cell, with window, slope and noise measured on it.

    Parameters
    ----------
    zmin : (rows, cols) float64
        Lowest trusted point per cell (:func:`lowest_points`), NaN where none.
    transform : Affine
        Its grid's.
    params : dict
        Filled with the parameters chosen (run.json's record).
    """
    cell = transform.a
    zmin = _drop_low_outliers(np.asarray(zmin, np.float64), units)
    measured = np.isfinite(zmin)
    surface = fill_nearest(zmin)

    if config.max_window:
        window = units.length(config.max_window)
        params["max_window"] = _chosen(config.max_window, "config")
    else:
        window, why = _auto_window(surface, cell, units)
        params["max_window"] = _chosen(round(window * units.horizontal, 1), why)
    trend = _trend(surface, measured, cell, window)
    if config.slope is not None:
        slope = config.slope
        params["slope"] = _chosen(slope, "config")
    else:
        slope, why = _auto_slope(surface - trend, cell, window, units)
        params["slope"] = _chosen(round(slope, 3), why)
    gy, gx = np.gradient(trend, cell)
    params["terrain_trend_slope"] = _chosen(
        round(float(np.percentile(np.hypot(gx, gy), 90)) * units.vertical / units.horizontal, 3),
        "90th percentile gradient of the large-scale terrain, removed before filtering",
    )
    noise = _noise(surface, measured)
    params["noise"] = _chosen(round(noise * units.vertical, 3), "NMAD of the minimum surface's second differences")
    return MinimumSurface(Raster(surface, transform), measured, window, slope, noise, trend)


def terrain(surface: MinimumSurface, method: str, units: Units) -> Raster:
    """The provisional terrain of ``method`` (:data:`METHODS`) on the minimum surface's grid."""
    return METHODS[method](surface, units)


#: Frame stereo: pits of the provisional terrain narrower than this (m) and deeper than
#: :data:`PIT_DEPTH` are filled before the ground points are picked (:func:`fill_pits`).
#: Matched points a few metres under the ground, too many for the low-outlier test and
#: above the tie points' 10 m margin, sank the terrain there (random_20 of the frame
#: family: ground check points 0.53 -> 0.08 m RMS, bulldozer-dtm 0.09 m); a stereo
#: survey shows no narrower real hollow that deep. The window is square (separable,
#: like the filters'): a wider basin keeps its floor but its rim is rounded where the
#: square does not fit inside it.
PIT_WIDTH = 30.0
PIT_DEPTH = 2.0
PIT_REASON = (f"frame stereo: terrain cells in hollows narrower than {PIT_WIDTH:g} m and deeper than {PIT_DEPTH:g} m "
              "raised to their rim (a grey closing) before picking ground points: mismatches under the ground")


def fill_pits(terrain: Raster, width: float, depth: float, measured: np.ndarray | None = None) -> tuple[Raster, int]:
    """The terrain with its pits narrower than ``width`` and deeper than ``depth`` filled
    by a grey closing (CRS units); and how many cells were raised. Planes and slopes pass
    a closing unchanged; a narrow hollow does not.

    With ``measured`` (the minimum surface's cells holding a point), the closing looks
    at those cells only, as the filter's openings do: a pit at the data's edge, copied
    over the empty grid beyond it, would otherwise be a basin open to the border that
    no closing fills."""
    data = np.asarray(terrain.data, np.float64)
    finite = np.isfinite(data)
    if not finite.any():
        return terrain, 0
    size = max(3, int(round(width / terrain.resolution)) | 1)
    closed = _close_measured(data, measured, size)
    pit = finite & (closed - data > depth)
    if not pit.any():
        return terrain, 0
    return terrain.like(np.where(pit, closed, data).astype(terrain.data.dtype), **terrain.tags), int(pit.sum())


def _close_measured(data: np.ndarray, measured: np.ndarray | None, size: int) -> np.ndarray:
    """Grey closing of ``data`` with a ``size``-cell square, over the ``measured`` cells
    only when given; -inf where no measured cell is within reach."""
    if measured is None or not measured.any() or measured.all():
        return ndimage.grey_closing(fill_nearest(data), size=size, mode="nearest")
    kernel = np.ones((size, size), np.uint8)
    closed = _erode_measured(_dilate_measured(data, measured, kernel), measured, kernel)
    return np.where(closed < _FAR / 2, closed.astype(np.float64), -np.inf)


# --------------------------------------------------------------------------- methods


def smrf_terrain(s: MinimumSurface, units: Units) -> Raster:
    """Terrain of the progressive morphological filter (SMRF style).

    The openings look at the measured cells only (:func:`_open_measured`), as the
    trend's do: a frame-stereo grid is mostly cells filled from their nearest measured
    one, which spread a roof or a cluster of mismatches at the data's edge into
    plateaus and basins wider than any window. On random_52 of the frame family the
    terrain stood 4-8 m high over a corner of the data (ground check points 0.82 m
    RMS; 0.13 m so).
    """
    slope = s.slope * units.horizontal / units.vertical
    objects = np.zeros(s.data.shape, bool)
    current = s.data.astype(np.float32)
    radii = range(1, max(1, math.ceil(s.window / s.cell / 2)) + 1)
    for r in radii:  # the openings' values outside the data are never read again: not filled
        opened = _open_measured(current, s.measured, r, fill=False)
        objects |= (current - opened) > slope * r * s.cell + 2.0 * s.noise
        current = opened
    return s.terrain(s.data, objects)


def tophat_terrain(s: MinimumSurface, units: Units) -> Raster:
    """Terrain from the classic production-line criteria: top-hat, local height, slope."""
    z = s.data
    slope = s.slope * units.horizontal / units.vertical
    radius = max(1, math.ceil(s.window / s.cell / 2))
    tophat = z - _open(z.astype(np.float32), radius)
    # the opening follows the terrain up to the slope the window spans
    high = tophat > units.height(1.0) + slope * radius * s.cell * 0.5 + 3.0 * s.noise
    ring = np.ones((5, 5), np.uint8)
    ring[1:4, 1:4] = 0
    neighbours = cv2.erode(z.astype(np.float32), ring)  # lowest cell two cells away
    above = (z - neighbours) > units.height(1.0) + 2.0 * slope * s.cell + 3.0 * s.noise
    gy, gx = np.gradient(z, s.cell)
    steep = np.hypot(gx, gy) > 3.0 * slope + 2.0 * s.noise / s.cell
    objects = high | above | ndimage.binary_dilation(steep & (tophat > 3.0 * s.noise))
    return s.terrain(z, objects)


RISE = 2.0


def drape_terrain(s: MinimumSurface, units: Units) -> Raster:
    """A cloth rising from below on a coarse-to-fine pyramid (Bulldozer-like).

    At the coarsest level a cell is wider than the widest object, so the lowest value
    per cell is terrain. At each finer level the upsampled cloth rises by at most the
    height the terrain slope allows over a coarse cell, in small steps, each followed by
    a 3 x 3 smoothing (tension), and never above the surface. Buildings, wider than the
    cells of the levels where the cloth may still rise, are never entered.
    """
    slope = s.slope * units.horizontal / units.vertical
    z = s.data
    levels = max(0, math.ceil(math.log2(max(s.window / s.cell, 1.0))))
    pyramid = [z]
    for _ in range(levels):
        p = pyramid[-1]
        rows, cols = (p.shape[0] + 1) // 2 * 2, (p.shape[1] + 1) // 2 * 2
        p = np.pad(p, ((0, rows - p.shape[0]), (0, cols - p.shape[1])), mode="edge")
        pyramid.append(p.reshape(rows // 2, 2, cols // 2, 2).min(axis=(1, 3)))
    cloth = pyramid[-1]
    steps = 8
    for level in range(levels - 1, -1, -1):
        target = pyramid[level]
        up = cv2.resize(cloth.astype(np.float32), None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)
        cloth = up[: target.shape[0], : target.shape[1]]
        cloth = np.minimum(cloth.astype(np.float64), target)
        rise = RISE * slope * s.cell * 2**level + 2.0 * s.noise
        for _ in range(steps):
            cloth = np.minimum(cv2.blur(cloth, (3, 3), borderType=cv2.BORDER_REPLICATE) + rise / steps, target)
    objects = (z - cloth) > units.height(0.5) + 3.0 * s.noise
    return s.terrain(z, objects)


#: Ground filters by name; each maps a minimum surface to a provisional terrain.
METHODS: dict[str, Callable[[MinimumSurface, Units], Raster]] = {
    "smrf": smrf_terrain,
    "tophat": tophat_terrain,
    "drape": drape_terrain,
}


# --------------------------------------------------------------------------- helpers


#: Points sampled on the terrain at a time: bounds the sampling's temporaries to ~100 MB.
SAMPLE_CHUNK = 1 << 20


def label_ground(
    xyz: np.ndarray, terrain: Raster, config: GroundConfig, units: Units, *, noise: float,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Ground points: within threshold + scalar x local slope x cell of the terrain.

    Parameters
    ----------
    xyz : (n, 3) float
    terrain : Raster
        The provisional terrain (:func:`terrain`), or a window of it around the points
        (one cell wider than they reach, for the gradient).
    config : GroundConfig
    units : Units
    noise : float
        Height noise of the minimum surface (:class:`MinimumSurface`).

    Returns the ground mask, the mask of ground points within the DTM band (at most
    0.3 m, or four times the noise, above the terrain) and the parameters used.
    """
    threshold, band, params = ground_tolerances(config, units, noise)
    cell = terrain.resolution
    gradient = terrain.like(terrain_gradient(terrain.data, cell))
    height = np.empty(len(xyz))
    for start in range(0, len(xyz), SAMPLE_CHUNK):  # bilinear sampling makes ~15 temporaries per point
        part = slice(start, start + SAMPLE_CHUNK)
        height[part] = xyz[part, 2] - terrain.sample(xyz[part, 0], xyz[part, 1])
    off = np.abs(height)
    is_ground = off <= threshold
    # the slope term only decides the points between the bare threshold and the widest
    # tolerance; sampling the gradient at those alone gives the same labels (on a window,
    # its steepest cell is at least as steep as those of the points)
    widest = threshold + max(config.scalar, 0.0) * float(np.nanmax(gradient.data, initial=0.0)) * cell
    undecided = np.flatnonzero(~is_ground & (off <= widest)) if config.scalar >= 0 else np.arange(len(xyz))
    g = gradient.sample(xyz[undecided, 0], xyz[undecided, 1], bilinear=False)
    is_ground[undecided] = off[undecided] <= threshold + config.scalar * np.nan_to_num(g) * cell
    for_dtm = is_ground & (height <= band)
    return is_ground, for_dtm, params


def ground_tolerances(config: GroundConfig, units: Units, noise: float) -> tuple[float, float, dict]:
    """How far from the terrain a point is ground, and a ground point shapes the DTM
    (:func:`label_ground`): the threshold and the band (CRS units), and their record for
    run.json (``threshold``, ``scalar``, ``dtm_band``, metres)."""
    if config.threshold is not None:
        threshold, why = units.height(config.threshold), "config"
    else:
        threshold = max(units.height(0.5), 3.0 * noise)
        why = "0.5 m, or 3 x the measured noise when larger"
    band = max(units.height(0.3), 4.0 * noise)
    return threshold, band, {
        "threshold": _chosen(round(threshold * units.vertical, 3), why),
        "scalar": config.scalar,
        "dtm_band": _chosen(round(band * units.vertical, 3), "0.3 m, or 4 x the noise when larger: "
                            "grass and low vegetation labelled ground must not lift the DTM"),
    }


def terrain_gradient(z: np.ndarray, cell: float) -> np.ndarray:
    """(rows, cols) float64 slope magnitude (rise over run) of a terrain grid; on a window
    one cell wider than the cells it is read at, the same as on the whole grid."""
    gy, gx = np.gradient(np.asarray(z, np.float64), cell)
    return np.hypot(gx, gy)


def _chosen(value, reason: str) -> dict:
    return {"value": value, "reason": reason}


def _open(z: np.ndarray, radius: int) -> np.ndarray:
    """Grey opening with a (2r+1)-cell square window (separable, O(cells))."""
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.morphologyEx(z.astype(np.float32), cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REPLICATE)


def _drop_low_outliers(zmin: np.ndarray, units: Units) -> np.ndarray:
    """NaN out cells far below their neighbourhood (multipath, reflections under water)."""
    if not np.isfinite(zmin).any():
        return zmin
    median = cv2.medianBlur(fill_nearest(zmin).astype(np.float32), 5)
    low = zmin < median - units.height(2.0)
    if low.any():
        log.info("ground: %d low-outlier cells ignored", int(low.sum()))
    out = zmin.copy()
    out[low] = np.nan
    return out


def _noise(surface: np.ndarray, measured: np.ndarray) -> float:
    """Height noise: NMAD of the Laplacian over measured cells, scaled to one height.

    The discrete Laplacian of white noise of std s has std s x sqrt(20); terrain and
    roofs, locally planar, contribute little, and edges are outliers the NMAD ignores.
    """
    lap = cv2.Laplacian(surface.astype(np.float32), cv2.CV_32F, ksize=1)
    v = lap[measured & ndimage.binary_erosion(measured, iterations=1)]
    if v.size < 10:
        return 0.0
    return float(1.4826 * np.median(np.abs(v - np.median(v))) / math.sqrt(20.0))


def _auto_window(surface: np.ndarray, cell: float, units: Units) -> tuple[float, str]:
    """Largest opening window (CRS units) from the widest raised object in the data.

    A 60 m opening marks cells more than 2.5 m above its result as raised objects;
    the opening must exceed the largest object's inscribed diameter to remove it.
    """
    big = max(1, round(units.length(60.0) / cell / 2))
    raised = (surface - _open(surface, big)) > units.height(2.5)
    radius = float(ndimage.distance_transform_edt(raised).max()) * cell if raised.any() else 0.0
    width_m = 2.0 * radius * units.horizontal
    window_m = float(np.clip(width_m * 1.2 + 2.0, 10.0, 60.0))
    return units.length(window_m), f"widest raised object {width_m:.1f} m across (bounded to 10-60 m)"


def _trend(surface: np.ndarray, measured: np.ndarray, cell: float, window: float) -> np.ndarray:
    """Large-scale terrain: a plane, plus the opening of the rest with the largest window, smoothed.

    The plane is fitted to the opened surface first, because openings near the border
    of a tilted tile see the replicated edge as a plateau. Both the openings and the
    fit look at the ``measured`` cells only: the cells filled from their nearest
    neighbour outside the data (four fifths of the grid of a frame-stereo survey seen
    at an angle) copy what stands at the data's edge over areas far wider than any
    window: a roof at a corner of the data became a plateau of "terrain", and
    mismatches under the ground at the edge tilted the plane (on random_52 of the
    frame family both together put the trend over 2 m under the flat ground at half
    the data's cells).

    Parameters
    ----------
    surface : (rows, cols) float
        Hole-free minimum surface.
    measured : (rows, cols) bool
        Cells of ``surface`` that hold a point.
    cell, window : float
        Cell size and largest object width, CRS units.

    Returns
    -------
    (rows, cols) float64
    """
    k = max(1, round(window / cell / 2))
    rows, cols = np.indices(surface.shape, dtype=np.float64)
    opened = _open_measured(surface, measured, k)
    design = np.column_stack([rows.ravel(), cols.ravel(), np.ones(surface.size)])
    fit = measured.ravel() if measured.sum() >= 3 else slice(None)
    coef = np.linalg.lstsq(design[fit], opened.ravel()[fit], rcond=None)[0]
    plane = (design @ coef).reshape(surface.shape)
    rest = _open_measured(surface - plane, measured, k)
    return plane + ndimage.uniform_filter(rest, size=k + 1, mode="nearest")


def _open_measured(z: np.ndarray, measured: np.ndarray, radius: int, *, fill: bool = True) -> np.ndarray:
    """Grey opening of the ``measured`` cells of ``z``, the others filled from the nearest measured cell.

    The erosion takes the minimum over the measured cells of each window and the
    dilation the maximum over the measured cells' erosions, so cells without data
    neither lower nor raise the result.

    Parameters
    ----------
    z : (rows, cols) float
    measured : (rows, cols) bool
    radius : int
        Half the window, cells.
    fill : bool
        False: leave the cells without data unfilled (float32, meaningless there), for
        callers that read the measured cells only.

    Returns
    -------
    (rows, cols) float64, or float32 when not ``fill``
    """
    if not measured.any() or measured.all():
        opened = _open(z, radius)
        return opened.astype(np.float64) if fill else opened
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    opened = _dilate_measured(_erode_measured(z, measured, kernel), measured, kernel)
    return fill_nearest(np.where(measured, opened, np.nan)) if fill else opened


#: Stand-in height of the cells without data in the masked erosions and dilations.
_FAR = np.finfo(np.float32).max


def _erode_measured(z: np.ndarray, measured: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """(rows, cols) float32: the minimum of ``z`` over the ``measured`` cells of each window (+_FAR if none)."""
    return cv2.erode(np.where(measured, z, _FAR).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)


def _dilate_measured(z: np.ndarray, measured: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """(rows, cols) float32: the maximum of ``z`` over the ``measured`` cells of each window (-_FAR if none)."""
    return cv2.dilate(np.where(measured, z, -_FAR).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)


def _auto_slope(residual: np.ndarray, cell: float, window: float, units: Units) -> tuple[float, str]:
    """Slope tolerance: the 90th percentile gradient of the opened, detrended terrain."""
    k = max(1, round(window / cell / 2))
    smooth = ndimage.uniform_filter(_open(residual, k).astype(np.float64), size=3, mode="nearest")
    gy, gx = np.gradient(smooth, cell)
    g = np.hypot(gx, gy) * units.vertical / units.horizontal
    p90 = float(np.percentile(g, 90))
    slope = float(np.clip(p90 * 1.5, 0.15, 1.0))
    return slope, f"90th percentile gradient of the detrended terrain {p90:.3f} x 1.5, bounded to 0.15-1.0"
