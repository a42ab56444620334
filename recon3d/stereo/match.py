"""Dense matching of a rectified image pair: semi-global matching (SGM).

Convention: a left-image disparity ``d`` at column ``x`` means the same scene point is
at column ``x - d`` of the right image, on the same row (OpenCV, Middlebury). Invalid
disparities are NaN, never 0 or a negative sentinel.

Method (engine ``"census"``, the default)
-----------------------------------------
1. Matching cost per pixel and disparity: Hamming distance of 7 x 9 census transforms
   (robust to gain, offset and any monotonic change of brightness between the images),
   plus a truncated Birchfield-Tomasi intensity term that sharpens the minimum in
   textured areas. Stored as a uint8 cost volume (rows, disparities, cols).
2. Semi-global aggregation along 8 (or 4) scanline directions (Hirschmueller 2008),
   with the large-jump penalty P2 lowered across intensity edges (adaptive P2), where
   depth discontinuities are likely. Compiled with numba (:mod:`recon3d.stereo._sgm`):
   the horizontal paths run one row per thread, the vertical and diagonal ones one
   row after the other with the row's pixels shared among the threads.
3. Winner-takes-all, parabola sub-pixel refinement, uniqueness test; the right-image
   disparity map comes from the same aggregated volume (no second matching pass), and a
   left-right consistency check (``lr_tolerance``, 1.5 px) marks occlusions and mismatches.
4. Speckle removal (small blobs disconnected from their surroundings); with
   ``sharpen_steps``, pixels beside a disparity step that took the raised side but
   whose own colours match the right image better at the lower side's disparity take
   that one (:func:`sharpen_steps`: the census window carries a roof onto the street);
   gap filling from
   the background side (occlusions are background seen by one image only: the second
   smallest of the nearest valid disparities along the row and the column; with
   ``fill_foreground``, the part of a hole beside a surface that both images see, or
   that is coloured like the roof beyond a ridge, from that surface instead), a 5 x 5
   median filter, then an edge-aware weighted median around disparity steps that moves
   them onto the colour edges of the left image (the cost window smears a roof edge by
   a few pixels). ``DisparityResult.filled`` / ``.unfilled`` keep the map as matched.

The ``"sgbm"`` engine runs OpenCV's ``StereoSGBM`` (5 directions, Birchfield-Tomasi cost
on intensity and horizontal gradient) on the intensity stacked with its 3 x 3 rank
transform, on images padded so that no column is left without a disparity; it matches
the mirrored pair for the right-image map and shares step 4. About 3 times faster,
somewhat less accurate.

A coarse pass (``pyramid_levels``) at 1/2 (1/4...) resolution with the fast engine
narrows the searched disparity range to what the scene contains, before the full
resolution pass: fewer disparities, less time and memory, fewer wrong candidates. The
census engine narrows it further per strip of rows, to what the coarse pass saw in
those rows (``params["strip_disparity_ranges"]``): a range set by a few tall buildings
or by a sloping ground is searched in full only where it occurs.

Measured on Middlebury 2003 "cones" (450 x 375, disparities 0..64, non-occluded pixels
with a ground truth, invalid pixels counted as errors; ``scripts/bench_match.py``):

=====================================  =======  =======  ======  =======
matcher                                bad-1 %  bad-2 %  MAE px  density
=====================================  =======  =======  ======  =======
raw StereoSGBM (block 3, uniqueness 10)  12.6     11.8    0.45    90.6 %
``engine="sgbm"``                         3.3      2.5    0.39     100 %
``engine="census"`` (default)             3.2      2.2    0.34     100 %
``engine="census"``, ``unfilled``         5.0      4.3    0.28    97.2 %
=====================================  =======  =======  ======  =======

(The SGM paper reports 3.3 % bad-1 there.) Most of raw StereoSGBM's error is the band of
``max_disparity`` columns on the left that it leaves invalid; padding the images fixes it.

Speed (``scripts/bench_match.py --case large``: 1800 x 1500 pixels, 256 disparities,
a synthetic scene filling the range; 2 cores shared with other jobs, so wall times are
only comparable within one run, CPU times less noisy):

==============================  ======  ======  =======  =======
matcher                         wall s  CPU s   peak MB  bad-1 %
==============================  ======  ======  =======  =======
OpenCV SGBM ``MODE_HH``          24.4     6.6     2425     9.5
OpenCV SGBM ``3WAY``              4.5     1.4      200     9.5
census (numba, default)          21.0     8.3      958     0.17
census, ``pyramid_levels=0``     18-22   8.8-11   1307     0.17
==============================  ======  ======  =======  =======

(The numpy implementation this replaced: 43-55 s wall, 23 CPU s, 1187 MB.)
The kernels are compiled on first use and cached on disk (``cache=True``): the first
match of a fresh install spends about 18 CPU seconds compiling, later processes load
the cache in about one.

Memory
------
The census engine works on horizontal strips of rows, one at a time, each holding a
uint8 cost volume and a uint16 aggregated volume (``3 * rows * cols * disparities``
bytes), bounded by ``strip_memory_mb`` (strips overlap by 32 rows so that vertical
paths are not cut short). Peak memory is about ``strip_memory_mb`` plus a few
(rows, cols) images, whatever the image size: under 1 GB for 1800 x 1500 pixels and
256 disparities with the default (1024 MB). The result depends on ``strip_memory_mb``
(strip borders) but not on ``workers`` nor on the number of threads.
"""

from __future__ import annotations

import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from recon3d.core.memory import require_memory
from recon3d.errors import InputError

log = logging.getLogger(__name__)

__all__ = [
    "ENGINES", "OCCLUSION_MARGIN_PX", "DisparityResult", "MatchParams", "faces_by_colour", "foreground_beyond_occlusion",
    "match", "sharpen_steps",
]

#: Matching engines: ``"census"`` (census cost + own SGM) and ``"sgbm"`` (OpenCV StereoSGBM).
ENGINES = ("census", "sgbm")

#: Rows shared by neighbouring strips of the census engine (context for vertical paths).
STRIP_OVERLAP = 32

#: Bytes per pixel and disparity of a census strip: uint8 cost and two uint16 sums (the
#: paths running down and up the rows, aggregated at once on two threads).
STRIP_BYTES_PER_VOXEL = 5

#: Smallest image side accepted.
MIN_SIZE = 8

_SGBM_INVALID = -(2**15)  # marker of invalid pixels in OpenCV's int16 speckle filter


@dataclass(frozen=True)
class MatchParams:
    """Parameters of :func:`match`.

    Defaults are usual SGM values checked on Middlebury cones: changing any one of them
    within a factor of about 2 moves bad-1 by at most 0.3 points, except switching off
    adaptive P2 (+1.2), the intensity term (+0.4), the left-right check (+0.5) or the
    median filter (+0.4), and an ``lr_tolerance`` of 0.5 (+0.8). Not tuned further, to
    avoid fitting one image. ``lr_tolerance`` 1.5 and ``speckle_size`` 50 (rather than
    1 and 100) keep small tree crowns, whose rough disparity breaks into fragments that
    the stricter values threw away (6 of 32 crowns lost on a rendered city), for +0.1 on
    cones.

    Attributes
    ----------
    min_disparity : int
        Smallest disparity searched (px); may be negative.
    max_disparity : int
        End of the searched range, **exclusive**: disparities ``min_disparity <= d <
        max_disparity`` are searched (``max_disparity - min_disparity`` candidates).
        Disparities never leave this range, sub-pixel refinement included (up to
        half a pixel beyond its ends).
    engine : {"census", "sgbm"}
        ``"census"``: census + intensity cost with this module's SGM (best accuracy).
        ``"sgbm"``: OpenCV StereoSGBM on intensity + rank transform (fastest).
    census_window : (int, int)
        Census window (rows, cols), both odd, at most 65 pixels (64 bits). Census engine.
    slant : float
        Census engine: 0 matches upright windows only (fronto-parallel surfaces). Above
        0, each right window is also sheared for surfaces whose disparity grows by
        ``+-slant`` px per column or per row, and the cheapest of the five costs counts:
        at a wide base a roof face is foreshortened in one view by up to half, and an
        upright window no longer finds it. Costs about 30 % more matching time.
    intensity_weight : float
        Weight of the Birchfield-Tomasi intensity term added to the census Hamming
        distance (cost units per grey level on a 0..255 scale). 0 = census only.
    intensity_truncation : float
        Intensity differences above this (grey levels) cost the same: robustness to
        occlusions and specular highlights.
    block_size : int
        Matching window of the sgbm engine (odd; OpenCV ``blockSize``).
    p1 : int or None
        Penalty for a disparity change of 1 px between neighbours (slanted surfaces).
        None: 8 for the census engine; OpenCV's ``8 * 3 * block_size**2`` for sgbm.
    p2 : int or None
        Penalty for larger jumps (depth discontinuities). None: 120 (census);
        ``32 * 3 * block_size**2`` (sgbm). Must exceed ``p1``.
    p2_min : int
        Census engine: the adaptive P2 never falls below this (nor below ``p1 + 1``).
    p2_gradient_scale : float
        Census engine: P2 is divided by ``1 + |I(p) - I(p - r)| / p2_gradient_scale``
        (grey levels, 0..255 scale) along each path, so that jumps are cheaper across
        intensity edges. 0 disables (constant P2).
    paths : {4, 8}
        Census engine: aggregation directions (4 = horizontal and vertical only: the
        aggregation does a third of the work; cones bad-1 3.2 % either way).
    uniqueness : float
        Percent by which the best aggregated cost must beat the second best (not
        adjacent) for the pixel to be valid; 0 disables. Off by default: the
        left-right check already rejects most ambiguous pixels, and on cones the test
        changed nothing (census) or cost 0.1 point of bad-1 (sgbm, 10 %).
    lr_check : bool
        Left-right consistency check: a pixel is kept only if the right image's
        disparity at ``x - d`` agrees within ``lr_tolerance``.
    lr_tolerance : float
        Largest left-right disagreement kept (px).
    subpixel : bool
        Parabola fit through the aggregated costs around the minimum; otherwise
        whole-pixel disparities.
    speckle_size : int
        Connected regions of at most this many pixels whose disparity differs by more
        than ``speckle_range`` from all around them are removed; 0 disables.
    speckle_range : float
        Largest disparity step (px) inside one connected region for the speckle filter.
    median_size : int
        Median filter applied to the final map (3 or 5 fast; 0 or 1 disables).
    fill_gaps : bool
        Fill invalid pixels (occlusions, mismatches, speckles) from the background side:
        the second smallest of the nearest valid disparities left, right, above and
        below. When False they stay NaN in ``disparity``; the
        filled map is always what the median filter sees.
    fill_foreground : bool
        Fill the far end of a hole that is wider than an occlusion from the surface
        beside it, not from the background (see :func:`foreground_beyond_occlusion`),
        and the part of a hole beside a ridge coloured like the roof (see
        :func:`faces_by_colour`): a roof face foreshortened in one view, next to the
        ground hidden behind its building, is otherwise filled at ground level with
        the hidden ground.
    sharpen_steps : float
        0 (off) or the ratio of :func:`sharpen_steps`: a pixel beside a disparity step
        that took the raised side takes the lower side's disparity when its 3 x 3
        colours match the right image there within this factor of how well they match
        at its own (and its own match is poor for the pair).
        Needs colour in both images to tell a roof from a street reliably.
    fill_confidence : float
        Confidence given to filled pixels, in [0, 1].
    edge_radius : int
        Half size of the window of the edge-aware weighted median applied last, around
        disparity steps only (0 disables): each pixel takes the median of its window's
        disparities weighted by colour similarity to it, so that steps move onto the
        image edges they belong to (the cost window smears them by a few pixels).
    edge_sigma : float
        Colour difference (grey levels, per channel, 0..255 scale) at which the weight of
        the edge-aware median has fallen to exp(-1/2).
    pyramid_levels : int
        Coarse pass at ``1 / 2**pyramid_levels`` resolution (sgbm engine, left-right
        checked) to narrow the disparity range before the full resolution pass; 0
        disables. Only applied when the range has at least 32 disparities, and kept only
        when it saves at least 20 % of them.
    pyramid_margin : int
        Pixels (full resolution) added on both sides of the coarse pass's range.
    strip_memory_mb : int
        Census engine: memory budget of one strip of rows (cost volumes).
    workers : int
        Threads (numba threads of the census engine, at most ``NUMBA_NUM_THREADS``;
        left and right passes of sgbm). Does not change the result.
    """

    min_disparity: int = 0
    max_disparity: int = 64
    engine: str = "census"
    census_window: tuple[int, int] = (7, 9)
    slant: float = 0.0
    intensity_weight: float = 1.0
    intensity_truncation: float = 30.0
    block_size: int = 3
    p1: int | None = None
    p2: int | None = None
    p2_min: int = 16
    p2_gradient_scale: float = 8.0
    paths: int = 8
    uniqueness: float = 0.0
    lr_check: bool = True
    lr_tolerance: float = 1.5
    subpixel: bool = True
    speckle_size: int = 50
    speckle_range: float = 2.0
    median_size: int = 5
    fill_gaps: bool = True
    fill_foreground: bool = False
    sharpen_steps: float = 0.0
    fill_confidence: float = 0.1
    edge_radius: int = 6
    edge_sigma: float = 12.0
    pyramid_levels: int = 1
    pyramid_margin: int = 4
    strip_memory_mb: int = 1024
    workers: int = 2

    def __post_init__(self) -> None:
        problems = []
        if self.max_disparity <= self.min_disparity:
            problems.append(
                f"empty disparity range: max_disparity ({self.max_disparity}) must exceed "
                f"min_disparity ({self.min_disparity}); the range is [min, max)"
            )
        if self.engine not in ENGINES:
            problems.append(f"engine {self.engine!r} is not one of {ENGINES}")
        wy, wx = self.census_window
        if wy < 1 or wx < 1 or wy % 2 == 0 or wx % 2 == 0 or wy * wx - 1 > 64:
            problems.append(
                f"census_window {self.census_window}: need odd sizes with rows * cols <= 65"
            )
        if not 0.0 <= self.slant < 1.0:
            problems.append(f"slant {self.slant}: from 0 (off) to below 1 px per px")
        if self.block_size < 1 or self.block_size % 2 == 0:
            problems.append(f"block_size {self.block_size}: need an odd size >= 1")
        if self.p1 is not None and self.p1 < 0:
            problems.append(f"p1 {self.p1}: must be >= 0")
        if self.engine in ENGINES and self.block_size >= 1:
            p1, p2 = self.resolved_penalties()
            if p2 <= p1:
                problems.append(f"p2 {p2} must exceed p1 {p1}")
            if self.engine == "census" and p2 >= 7900:
                problems.append(f"p2 {p2}: at most 7899 (16-bit aggregation of 8 paths)")
        if self.paths not in (4, 8):
            problems.append(f"paths {self.paths}: 4 or 8")
        if self.intensity_weight < 0 or self.intensity_truncation < 0:
            problems.append("intensity_weight and intensity_truncation must be >= 0")
        if self.uniqueness < 0:
            problems.append(f"uniqueness {self.uniqueness}: must be >= 0")
        if self.lr_tolerance < 0:
            problems.append(f"lr_tolerance {self.lr_tolerance}: must be >= 0")
        if self.speckle_size < 0 or self.speckle_range < 0:
            problems.append("speckle_size and speckle_range must be >= 0")
        if self.median_size < 0 or (self.median_size > 1 and self.median_size % 2 == 0):
            problems.append(f"median_size {self.median_size}: 0, 1 or an odd size")
        if self.sharpen_steps < 0:
            problems.append(f"sharpen_steps {self.sharpen_steps}: 0 (off) or a ratio > 0")
        if not 0.0 <= self.fill_confidence <= 1.0:
            problems.append(f"fill_confidence {self.fill_confidence}: must be in [0, 1]")
        if self.edge_radius < 0 or self.edge_sigma <= 0:
            problems.append("edge_radius must be >= 0 and edge_sigma > 0")
        if not 0 <= self.pyramid_levels <= 4:
            problems.append(f"pyramid_levels {self.pyramid_levels}: 0 to 4")
        if self.pyramid_margin < 0:
            problems.append(f"pyramid_margin {self.pyramid_margin}: must be >= 0")
        if self.strip_memory_mb < 1:
            problems.append(f"strip_memory_mb {self.strip_memory_mb}: at least 1")
        if self.workers < 1:
            problems.append(f"workers {self.workers}: at least 1")
        if problems:
            raise InputError("invalid matching parameters: " + "; ".join(problems))

    def resolved_penalties(self) -> tuple[int, int]:
        """(P1, P2) actually used by the chosen engine (the defaults filled in)."""
        if self.engine == "sgbm":
            area = 3 * self.block_size**2  # 3 channels: intensity, rank, rank
            p1_default, p2_default = 8 * area, 32 * area
        else:
            p1_default, p2_default = 8, 120
        return (
            self.p1 if self.p1 is not None else p1_default,
            self.p2 if self.p2 is not None else p2_default,
        )


@dataclass
class DisparityResult:
    """Output of :func:`match`.

    Attributes
    ----------
    disparity : (H, W) float32
        Left-image disparity in pixels (``x_right = x_left - d``), NaN where invalid.
        With ``fill_gaps`` (default) only pixels that cannot be filled are NaN (left
        image nodata, or no valid pixel in the image).
    confidence : (H, W) float32 in [0, 1]
        0 where NaN; ``fill_confidence`` on filled pixels; elsewhere the product of a
        left-right term ``1 - |d_left - d_right| / (2 * lr_tolerance)`` (1 without the
        check) and, for the census engine, the uniqueness margin
        ``(second best - best) / second best`` of the aggregated costs.
    params : dict
        Everything used, for run.json: the :class:`MatchParams` fields, the resolved
        penalties, the range actually searched and why, densities, timings.
    filled : (H, W) bool or None
        True where the value came from gap filling (not from matching).
    foreground : (H, W) bool or None
        The filled pixels that took the surface beside them rather than the background
        (``fill_foreground``).
    """

    disparity: np.ndarray
    confidence: np.ndarray
    params: dict
    filled: np.ndarray | None = None
    foreground: np.ndarray | None = None

    @property
    def unfilled(self) -> np.ndarray:
        """(H, W) float32: the disparity with filled pixels set back to NaN."""
        if self.filled is None:
            return self.disparity.copy()
        return np.where(self.filled, np.float32(np.nan), self.disparity)

    @property
    def density(self) -> float:
        """Fraction of pixels with a finite disparity."""
        return float(np.isfinite(self.disparity).mean())


def match(
    left: np.ndarray,
    right: np.ndarray,
    params: MatchParams = MatchParams(),
    *,
    guide: np.ndarray | None = None,
    guide_right: np.ndarray | None = None,
    low: np.ndarray | None = None,
    high: np.ndarray | None = None,
    weight: np.ndarray | None = None,
) -> DisparityResult:
    """Dense disparity map of a rectified pair by semi-global matching.

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) array
        Rectified images of the same size; uint8, uint16, other integers or float.
        Colour is averaged to grey (channel order does not matter). Non-finite values
        of float images are nodata: no disparity there in ``left``, no match into them
        in ``right``. Images are jointly stretched to 0..255 (0.1 to 99.9 percentile)
        unless they are uint8.
    params : MatchParams
    guide : (H, W, 3) or (H, W) array, optional
        Image whose edges the edge-aware median aligns disparity steps with (colour
        separates roofs from ground better than grey); default ``left``.
    guide_right : (H, W, 3) or (H, W) array, optional
        The right image in colour, for ``sharpen_steps``; default ``right``.
    low, high : (H, W) float, optional
        Per-pixel disparity bounds (NaN: unbounded), e.g. from a coarse DEM or 3-D
        vectors. Disparities outside them cost more to the census engine (by ``weight``);
        the sgbm engine, and the final map, drop disparities outside the bounds of
        pixels whose weight is 1.
    weight : (H, W) float in [0, 1], optional
        How firmly the bounds hold at each pixel: 1 (the default) forbids disparities
        outside them, smaller values only penalise them (by ``weight`` times the
        largest matching cost), for bounds that may be wrong by a little, such as roof
        heights of a building database.

    Returns
    -------
    DisparityResult
        ``disparity`` and ``confidence`` (H, W) float32, ``filled`` (H, W) bool,
        ``params`` dict.

    Raises
    ------
    InputError
        Images that are not 2-D grey or 3-channel, of different sizes, smaller than
        8 x 8, of a non-numeric type, entirely nodata; a disparity range that is empty
        or outside the image width.
    """
    t0 = time.perf_counter()
    gl, gr, nodata_l, nodata_r = _prepare(left, right)
    h, w = gl.shape
    dmin, dmax = int(params.min_disparity), int(params.max_disparity)
    if dmin >= w or dmax <= -w + 1:
        raise InputError(
            f"disparity range [{dmin}, {dmax}) lies outside the image width ({w} px): "
            "no pixel can match"
        )
    info: dict = asdict(params)
    info["census_window"] = list(params.census_window)
    p1, p2 = params.resolved_penalties()
    info.update(p1=p1, p2=p2)
    timings: dict[str, float] = {}

    bounds = _bounds(low, high, weight, (h, w))
    t = time.perf_counter()
    lo, hi, reason, coarse_pass = _narrow_range(gl, gr, dmin, dmax, params)
    timings["pyramid"] = time.perf_counter() - t
    info["disparity_range_searched"] = {"value": [lo, hi], "reason": reason}

    t = time.perf_counter()
    if params.engine == "census":
        disp, disp_right, cost_conf, ranges = _census_engine(gl, gr, lo, hi, params, bounds, coarse_pass)
        info["strips"] = len(ranges)
        info["strip_disparity_ranges"] = ranges
    else:
        disp, disp_right = _sgbm_engine(gl, gr, lo, hi, params, right=params.lr_check)
        cost_conf = None
    if bounds is not None:
        disp[_outside_hard(disp, bounds)] = np.nan
    timings["matching"] = time.perf_counter() - t

    t = time.perf_counter()
    xs = np.arange(w, dtype=np.float32)[None, :]
    # a match must land inside the right image and on data
    xr = np.rint(xs - disp)
    inside = (xr >= 0) & (xr <= w - 1)
    disp[~inside] = np.nan
    if nodata_r is not None:
        rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
        ok = np.isfinite(disp)
        hit = np.zeros((h, w), bool)
        hit[ok] = nodata_r[rows[ok], xr[ok].astype(np.intp)]
        disp[hit] = np.nan
    if nodata_l is not None:
        disp[nodata_l] = np.nan

    best = disp.copy()  # each pixel's best match, before the checks reject some
    lr_term = np.ones((h, w), np.float32)
    if params.lr_check:
        diff = _lr_difference(disp, disp_right)
        disp[~(diff <= params.lr_tolerance)] = np.nan
        if params.lr_tolerance > 0:
            disagreement = np.nan_to_num(diff, nan=0.0) / (2.0 * params.lr_tolerance)
            lr_term = np.clip(1.0 - disagreement, 0.0, 1.0)
    if params.speckle_size > 0:
        _remove_speckles(disp, params.speckle_size, params.speckle_range, lo)
    colour = None
    if params.fill_foreground or params.edge_radius > 0 or params.sharpen_steps > 0:
        colour = _guide(left if guide is None else guide, gl.shape)
    if params.sharpen_steps > 0:
        sharpened = sharpen_steps(disp, colour, _guide(right if guide_right is None else guide_right, gl.shape),
                                  ratio=params.sharpen_steps)
        info["sharpened_percent"] = round(100.0 * sharpened / (h * w), 2)
    matched = np.isfinite(disp)
    confidence = lr_term if cost_conf is None else lr_term * cost_conf
    confidence = np.where(matched, confidence, 0.0).astype(np.float32)

    full = _fill_background(disp)
    foreground = None
    if params.fill_foreground:
        foreground, heights = _foreground(disp, best, full)
        face, ramp = faces_by_colour(disp, full, colour)  # both judged against the background fill
        face &= ~foreground
        full[foreground] = heights[foreground]
        full[face] = ramp[face]
        foreground |= face
    filled = ~matched & np.isfinite(full)
    if params.median_size > 1:
        full = _median(full, params.median_size)
    if params.edge_radius > 0:
        full = _edge_aware_median(full, colour, params.edge_radius, params.edge_sigma)
    if nodata_l is not None:
        full[nodata_l] = np.nan
        filled &= ~nodata_l
    if bounds is not None:  # filling must not leave the bounds either
        lo_b, hi_b, hard, _ = bounds
        full = np.where(hard, np.clip(full, lo_b, hi_b), full).astype(np.float32)
    if params.fill_gaps:
        disparity = full
        confidence[filled] = params.fill_confidence
    else:
        disparity = np.where(matched, full, np.float32(np.nan))
    disparity = disparity.astype(np.float32, copy=False)
    timings["post"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0

    n = h * w
    info["matched_percent"] = round(100.0 * float(matched.sum()) / n, 2)
    info["filled_percent"] = round(100.0 * float(filled.sum()) / n, 2)
    info["seconds"] = {k: round(v, 3) for k, v in timings.items()}
    log.info(
        "matched %dx%d, disparities [%d, %d) (%s): %.1f %% matched, %.1f %% filled, %.2f s",
        w, h, lo, hi, params.engine, info["matched_percent"], info["filled_percent"],
        timings["total"],
    )
    if foreground is not None:
        foreground &= filled
        info["foreground_percent"] = round(100.0 * float(foreground.sum()) / n, 2)
    if not params.fill_gaps:
        filled = np.zeros((h, w), bool)
        foreground = None
    return DisparityResult(disparity, confidence, info, filled, foreground)


# ----------------------------------------------------------------------------- input


def _prepare(left, right) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Grey float32 images on a joint 0..255 scale (nodata set to 0) and nodata masks."""
    a = _as_gray(left, "left")
    b = _as_gray(right, "right")
    if a.shape != b.shape:
        raise InputError(
            f"left and right images differ in size: {a.shape} vs {b.shape}; rectify them first"
        )
    if min(a.shape) < MIN_SIZE:
        raise InputError(
            f"images of {a.shape[1]} x {a.shape[0]} px are too small to match "
            f"(at least {MIN_SIZE} x {MIN_SIZE})"
        )
    if a.dtype == np.uint8 and b.dtype == np.uint8:
        return a.astype(np.float32), b.astype(np.float32), None, None
    a = a.astype(np.float32)
    b = b.astype(np.float32)
    bad_a, bad_b = ~np.isfinite(a), ~np.isfinite(b)
    if bad_a.all() or bad_b.all():
        raise InputError("an input image has no finite pixel")
    both = np.concatenate([a[~bad_a], b[~bad_b]])
    lo, hi = np.percentile(both, [0.1, 99.9])
    if hi <= lo:
        lo, hi = float(both.min()), float(both.max())
    scale = 255.0 / (hi - lo) if hi > lo else 0.0
    out = []
    for img, bad in ((a, bad_a), (b, bad_b)):
        g = np.clip((img - lo) * scale, 0.0, 255.0)
        g[bad] = 0.0
        out.append(g.astype(np.float32))
    return out[0], out[1], (bad_a if bad_a.any() else None), (bad_b if bad_b.any() else None)


def _as_gray(img, name: str) -> np.ndarray:
    arr = np.asarray(img)
    numeric = np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    if arr.dtype == bool or not numeric:
        raise InputError(
            f"{name} image: unsupported pixel type {arr.dtype}; need integers or floats"
        )
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 3 and arr.shape[2] == 3:
        if arr.dtype == np.uint8:
            return np.rint(arr.astype(np.float32).mean(axis=2)).astype(np.uint8)
        return arr.astype(np.float32).mean(axis=2)
    if arr.ndim != 2:
        raise InputError(
            f"{name} image: shape {arr.shape}; need (rows, cols) grey or (rows, cols, 3) colour"
        )
    return arr


def _to_uint8(g: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(g), 0, 255).astype(np.uint8)


def _bounds(low, high, weight, shape):
    """(low, high, hard, weight): bounds (float32, infinite where none), the pixels where
    they hold firmly (bool) and the weights (float32); None without bounds."""
    if low is None and high is None:
        return None
    lo = np.full(shape, -np.inf, np.float32) if low is None else np.asarray(low, np.float32)
    hi = np.full(shape, np.inf, np.float32) if high is None else np.asarray(high, np.float32)
    if lo.shape != shape or hi.shape != shape:
        raise InputError(f"disparity bounds of shape {lo.shape} / {hi.shape} for images of shape {shape}")
    lo = np.where(np.isfinite(lo), lo, -np.inf).astype(np.float32)
    hi = np.where(np.isfinite(hi), hi, np.inf).astype(np.float32)
    wt = np.ones(shape, np.float32) if weight is None else np.clip(np.nan_to_num(np.asarray(weight, np.float32)), 0, 1)
    hard = (wt >= 1.0) & (np.isfinite(lo) | np.isfinite(hi))
    return lo, hi, hard, wt


def _outside_hard(disp: np.ndarray, bounds) -> np.ndarray:
    lo, hi, hard, _ = bounds
    with np.errstate(invalid="ignore"):
        return hard & ((disp < lo - 0.5) | (disp > hi + 0.5))


# ----------------------------------------------------------------------------- pyramid


@dataclass
class _Coarse:
    """The coarse pass: its disparity map (full-resolution pixels, NaN where it failed),
    at ``1 / scale`` of the image, and the margin (px) kept around what it saw."""

    disparity: np.ndarray
    scale: int
    margin: int

    def rows_range(self, a: int, b: int, lo: int, hi: int) -> tuple[int, int] | None:
        """Range [lo', hi') inside [lo, hi) that the coarse pass saw over image rows a..b,
        widened by the margin; None when it matched under 20 % of those rows' pixels."""
        part = self.disparity[a // self.scale : -(-b // self.scale)]
        valid = np.isfinite(part)
        if part.size == 0 or valid.mean() < 0.2:
            return None
        seen_lo = max(lo, math.floor(float(part[valid].min())) - self.margin)
        seen_hi = min(hi, math.ceil(float(part[valid].max())) + self.margin + 1)
        return (seen_lo, seen_hi) if seen_hi > seen_lo else None


def _narrow_range(gl, gr, dmin: int, dmax: int, params: MatchParams) -> tuple[int, int, str, _Coarse | None]:
    """Disparity range seen by a coarse left-right checked pass, within [dmin, dmax), and
    that pass (None when none ran or it matched too little)."""
    levels = params.pyramid_levels
    if levels == 0:
        return dmin, dmax, "as given (pyramid_levels = 0)", None
    if dmax - dmin < 32:
        return dmin, dmax, "as given (fewer than 32 disparities: not worth a coarse pass)", None
    s = 2**levels
    h, w = gl.shape
    ch, cw = max(1, round(h / s)), max(1, round(w / s))
    if min(ch, cw) < 16:
        return dmin, dmax, "as given (image too small for a coarse pass)", None
    small_l = cv2.resize(_to_uint8(gl), (cw, ch), interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(_to_uint8(gr), (cw, ch), interpolation=cv2.INTER_AREA)
    cmin, cmax = math.floor(dmin / s), math.ceil(dmax / s)
    coarse = MatchParams(
        min_disparity=cmin, max_disparity=max(cmax, cmin + 1), engine="sgbm",
        block_size=params.block_size, workers=params.workers,
    )
    d, dr = _sgbm_engine(small_l.astype(np.float32), small_r.astype(np.float32), cmin, cmax, coarse)
    d[~(_lr_difference(d, dr) <= 1.0)] = np.nan
    _remove_speckles(d, max(params.speckle_size // (s * s), 10), 1.0, cmin)
    valid = np.isfinite(d)
    if valid.mean() < 0.2:
        why = f"the 1/{s} coarse pass matched only {100 * valid.mean():.0f} % of pixels"
        return dmin, dmax, f"as given ({why})", None
    margin = params.pyramid_margin + s
    coarse_pass = _Coarse(d * np.float32(s), s, margin)
    lo = max(dmin, math.floor(float(d[valid].min()) * s) - margin)
    hi = min(dmax, math.ceil(float(d[valid].max()) * s) + margin + 1)
    if hi - lo > 0.8 * (dmax - dmin) or hi <= lo:
        why = f"the 1/{s} coarse pass spans {lo}..{hi}: too little to gain over the whole image"
        return dmin, dmax, f"as given ({why})", coarse_pass
    reason = (
        f"narrowed by a 1/{s} resolution pass: it matched disparities in "
        f"{lo + margin}..{hi - margin - 1}, +-{margin} px"
    )
    log.debug("disparity range [%d, %d) %s", lo, hi, reason)
    return lo, hi, reason, coarse_pass


# ----------------------------------------------------------------------------- sgbm engine


def _rank3(g8: np.ndarray) -> np.ndarray:
    """3 x 3 rank transform (neighbours darker than the centre), scaled to 0..255, uint8."""
    p = cv2.copyMakeBorder(g8, 1, 1, 1, 1, cv2.BORDER_REFLECT_101)
    h, w = g8.shape
    count = np.zeros((h, w), np.uint8)
    for dy in range(3):
        for dx in range(3):
            if dy != 1 or dx != 1:
                count += p[dy : dy + h, dx : dx + w] < g8
    return (count.astype(np.uint16) * 255 // 8).astype(np.uint8)


def _sgbm_engine(
    gl, gr, dmin: int, dmax: int, params: MatchParams, *, right: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Left and right disparity maps (float32, NaN invalid) from OpenCV StereoSGBM.

    The input is the intensity stacked with its 3 x 3 rank transform (twice, so that
    it weighs as much as the intensity): a cheap non-parametric cost term. The right
    map (``right``) comes from matching the mirrored pair.
    """
    l8, r8 = _to_uint8(gl), _to_uint8(gr)
    rank_l, rank_r = _rank3(l8), _rank3(r8)
    a = np.dstack([l8, rank_l, rank_l])
    b = np.dstack([r8, rank_r, rank_r])
    ndisp = 16 * math.ceil((dmax - dmin) / 16)
    p1, p2 = params.resolved_penalties()

    def run(x, y):
        return _sgbm_once(x, y, dmin, ndisp, p1, p2, params)

    flip_b, flip_a = np.ascontiguousarray(b[:, ::-1]), np.ascontiguousarray(a[:, ::-1])
    if not right:
        dl, dr = run(a, b), None
    elif params.workers > 1:
        with ThreadPoolExecutor(2) as pool:
            fl, fr = pool.submit(run, a, b), pool.submit(run, flip_b, flip_a)
            dl, dr = fl.result(), fr.result()
    else:
        dl, dr = run(a, b), run(flip_b, flip_a)
    dl[dl >= dmax] = np.nan  # the range was rounded up to a multiple of 16
    if dr is not None:
        dr = np.ascontiguousarray(dr[:, ::-1])
        dr[dr >= dmax] = np.nan
    return dl, dr


def _sgbm_once(a, b, dmin: int, ndisp: int, p1: int, p2: int, params: MatchParams) -> np.ndarray:
    # StereoSGBM leaves the first min_disparity + num_disparities columns invalid: pad them
    # with a mirror image so that every real column gets a disparity.
    w = a.shape[1]
    pad_l, pad_r = max(dmin + ndisp, 0), max(-dmin, 0)
    a = cv2.copyMakeBorder(a, 0, 0, pad_l, pad_r, cv2.BORDER_REFLECT_101)
    b = cv2.copyMakeBorder(b, 0, 0, pad_l, pad_r, cv2.BORDER_REFLECT_101)
    sgbm = cv2.StereoSGBM_create(
        minDisparity=dmin, numDisparities=ndisp, blockSize=params.block_size, P1=p1, P2=p2,
        disp12MaxDiff=-1, uniquenessRatio=int(round(params.uniqueness)), speckleWindowSize=0,
        speckleRange=0, preFilterCap=15, mode=cv2.STEREO_SGBM_MODE_SGBM,
    )
    raw = sgbm.compute(a, b)[:, pad_l : pad_l + w]
    d = raw.astype(np.float32) / 16.0
    d[raw < dmin * 16] = np.nan
    if not params.subpixel:
        d = np.rint(d)
    return d


# ----------------------------------------------------------------------------- census engine


def _census_engine(gl, gr, dmin: int, dmax: int, params: MatchParams, bounds=None, coarse_pass=None):
    """Left disparity (subpixel, NaN where not unique), right disparity, cost confidence,
    and the range [lo, hi) each strip searched.

    One strip of rows at a time, each matched by the compiled kernels of
    :mod:`recon3d.stereo._sgm` on ``workers`` threads. With a coarse pass, each strip
    searches only the disparities that pass saw in its rows (+- its margin): a scene
    whose range comes from a few tall buildings, or from a sloping ground, needs far
    fewer per strip than over the whole image.
    """
    from recon3d.stereo import _sgm

    h, w = gl.shape
    ndisp = dmax - dmin
    bytes_per_row = w * ndisp * (STRIP_BYTES_PER_VOXEL + (params.slant > 0))  # + the sheared windows' costs
    strips = _strips(h, max(STRIP_OVERLAP, params.strip_memory_mb * 2**20 // bytes_per_row))
    log.debug("census SGM: %d strip(s), %d disparities", len(strips), ndisp)
    # the strips do not adapt to the memory free (the result would depend on the machine)
    tallest = max(b - a for _, _, a, b in strips)
    require_memory(tallest * bytes_per_row,
                   f"matching {w} x {h} px over {ndisp} disparities (strips of {tallest} rows)",
                   "match with a smaller stereo.strip_memory_mb or a narrower disparity range")
    with _numba_threads(params.workers):
        cl, cr, l8, rmin, rmax = _cost_inputs(gl, gr, params, _sgm)
        p1, p2 = params.resolved_penalties()
        p2_min = max(params.p2_min, p1 + 1)
        trunc8, cap = _bt_limits(params)
        ranges = [list((coarse_pass.rows_range(a, b, dmin, dmax) if coarse_pass else None) or (dmin, dmax))
                  for _, _, a, b in strips]
        # buffers of the largest strip, reused: first touching a page costs more than using it
        voxels = max((b - a) * w * (hi - lo) for (_, _, a, b), (lo, hi) in zip(strips, ranges, strict=True))
        cost_buf = np.empty(voxels, np.uint8)
        sheared_buf = np.empty(voxels if len(cr) > 1 else 0, np.uint8)
        down_buf, up_buf = np.empty(voxels, np.uint16), np.empty(voxels, np.uint16)
        parts = []
        for (r0, r1, a, b), (lo, hi) in zip(strips, ranges, strict=True):
            shape = (b - a, w, hi - lo)
            size = math.prod(shape)
            c = cost_buf[:size].reshape(shape)
            sheared = sheared_buf[:size].reshape(shape) if len(cr) > 1 else None
            t_down, t_up = down_buf[:size].reshape(shape), up_buf[:size].reshape(shape)
            for k, right_bits in enumerate(cr):  # the intensity term is the same for every window
                _sgm.cost_volume(cl[a:b], right_bits[a:b], l8[a:b], rmin[a:b], rmax[a:b], lo, trunc8 > 0,
                                 trunc8, np.float32(params.intensity_weight), cap, c if k == 0 else sheared)
                if k:
                    np.minimum(c, sheared, out=c)
            if bounds is not None:
                _sgm.penalise_outside(c, *_outside_penalty(lo, hi - lo, *(x[a:b] for x in bounds)))
            _sgm.aggregate(c, gl[a:b], p1, p2, p2_min, params.p2_gradient_scale, params.paths, t_down, t_up)
            disp, margin, right = _sgm.select(t_down, t_up, lo, params.subpixel, float(params.uniqueness))
            parts.append((disp[r0 - a : r1 - a], right[r0 - a : r1 - a], margin[r0 - a : r1 - a]))
    disp = np.concatenate([p[0] for p in parts])
    disp_right = np.concatenate([p[1] for p in parts])
    conf = np.concatenate([p[2] for p in parts])
    return disp, disp_right, conf, ranges


def _strips(h: int, rows: int) -> list[tuple[int, int, int, int]]:
    """(first, end) of the rows each strip returns and (first, end) of those it matches:
    equal strips of at most ``rows`` rows (at least twice the overlap of their own),
    overlapping by ``STRIP_OVERLAP`` rows so that vertical paths are not cut short."""
    if rows >= h:
        return [(0, h, 0, h)]
    core = max(rows - 2 * STRIP_OVERLAP, 2 * STRIP_OVERLAP)
    core = math.ceil(h / math.ceil(h / core))
    return [(r0, min(h, r0 + core), max(0, r0 - STRIP_OVERLAP), min(h, r0 + core + STRIP_OVERLAP))
            for r0 in range(0, h, core)]


class _numba_threads:
    """Context: numba kernels run on at most ``workers`` threads (the result does not
    depend on it)."""

    def __init__(self, workers: int) -> None:
        self.workers = workers

    def __enter__(self):
        import numba

        self.before = numba.get_num_threads()
        numba.set_num_threads(max(1, min(self.workers, numba.config.NUMBA_NUM_THREADS)))
        return self

    def __exit__(self, *exc) -> None:
        import numba

        numba.set_num_threads(self.before)


def _cost_inputs(gl, gr, params: MatchParams, kernels):
    """Census bit strings of both images (uint64), the left grey levels (uint8) and the
    Birchfield-Tomasi interval [rmin, rmax] the right image spans within +-half a pixel
    (uint8, grey levels; all (H, W)). The right census strings come as a list: the
    upright window's, then with ``params.slant`` those of windows sheared for disparity
    gradients +-slant along the columns and along the rows."""
    wy, wx = params.census_window
    ry, rx = wy // 2, wx // 2
    h = gl.shape[0]
    pl = cv2.copyMakeBorder(gl, ry, ry, rx, rx, cv2.BORDER_REFLECT_101)
    pr = cv2.copyMakeBorder(gr, ry, ry, rx, rx, cv2.BORDER_REFLECT_101)
    cl, cr = kernels.census(pl, 0, h, wy, wx), kernels.census(pr, 0, h, wy, wx)
    if params.slant > 0:
        g, zero = np.float32(params.slant), np.float32(0.0)
        grey = np.ascontiguousarray(gr, np.float32)
        cr = [cr, *(kernels.census_slanted(grey, wy, wx, gx, gy) for gx, gy in ((g, zero), (-g, zero), (zero, g), (zero, -g)))]
    else:
        cr = [cr]
    r = np.clip(np.rint(gr), 0, 255).astype(np.uint16)
    half_l = ((r + np.concatenate([r[:, :1], r[:, :-1]], axis=1)) // 2).astype(np.uint8)
    half_r = ((r + np.concatenate([r[:, 1:], r[:, -1:]], axis=1)) // 2).astype(np.uint8)
    r8 = r.astype(np.uint8)
    rmin = np.minimum(r8, np.minimum(half_l, half_r))
    rmax = np.maximum(r8, np.maximum(half_l, half_r))
    return cl, cr, _to_uint8(gl), rmin, rmax


def _bt_limits(params: MatchParams) -> tuple[np.int32, np.int32]:
    """(truncation, cap) of the intensity term in grey levels; (0, 0) when it is off.

    The cap keeps census + intensity inside uint8."""
    weight, trunc = params.intensity_weight, params.intensity_truncation
    if not (weight > 0 and trunc > 0):
        return np.int32(0), np.int32(0)
    nbits = params.census_window[0] * params.census_window[1] - 1
    return np.int32(min(round(trunc), 255)), np.int32(min(round(trunc * weight), 255 - nbits))


def _outside_penalty(dmin: int, ndisp: int, lo, hi, hard, weight):
    """(first, last, penalty), (H, W): disparity indices ``first..last`` lie inside the
    per-pixel bounds; the others cost ``weight`` times 255 more (uint8, saturating:
    weight 1 makes a disparity as costly as can be)."""
    first = np.clip(np.ceil(lo - 0.5) - dmin, 0, ndisp).astype(np.int32)
    last = np.clip(np.floor(hi + 0.5) - dmin, -1, ndisp - 1).astype(np.int32)
    return first, last, np.rint(weight * 255).astype(np.uint8)


# ----------------------------------------------------------------------------- post-processing


def _lr_difference(disp: np.ndarray, disp_right: np.ndarray) -> np.ndarray:
    """|d_left(x) - d_right(x - d_left(x))|, NaN where either is missing or outside."""
    h, w = disp.shape
    xr = np.rint(np.arange(w, dtype=np.float32)[None, :] - disp)
    ok = np.isfinite(xr) & (xr >= 0) & (xr <= w - 1)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    other = np.full((h, w), np.nan, np.float32)
    other[ok] = disp_right[rows[ok], xr[ok].astype(np.intp)]
    return np.abs(disp - other)


def _remove_speckles(disp: np.ndarray, size: int, max_step: float, dmin: int) -> None:
    """In place: NaN over connected blobs of <= size pixels (OpenCV filterSpeckles)."""
    valid = np.isfinite(disp)
    scaled = np.rint((np.where(valid, disp, dmin) - dmin + 1.0) * 16.0)
    if scaled.max(initial=0) >= 2**15:
        log.warning("speckle filter skipped: disparity span too large for 16-bit")
        return
    buf = scaled.astype(np.int16)
    buf[~valid] = _SGBM_INVALID
    cv2.filterSpeckles(buf, _SGBM_INVALID, int(size), max(1, int(round(max_step * 16))))
    disp[buf == _SGBM_INVALID] = np.nan


def _nearest_index_along_rows(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column of the nearest valid pixel to the left (-1 if none) and to the right (W if
    none) of every pixel; a valid pixel's own column."""
    w = valid.shape[1]
    cols = np.arange(w)[None, :]
    left_i = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    rev = np.maximum.accumulate(np.where(valid[:, ::-1], cols, -1), axis=1)  # in flipped columns
    return left_i, np.where(rev >= 0, w - 1 - rev, w)[:, ::-1]


def _take_along_rows(d: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(H, W) float32: ``d`` at each row's column ``index``, NaN where it is outside."""
    w = d.shape[1]
    inside = (index >= 0) & (index <= w - 1)
    value = np.take_along_axis(d, np.clip(index, 0, w - 1), axis=1)
    return np.where(inside, value, np.nan).astype(np.float32)


def _nearest_along_rows(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest finite value to the left and to the right of every pixel (NaN if none)."""
    left_i, right_i = _nearest_index_along_rows(np.isfinite(d))
    return _take_along_rows(d, left_i), _take_along_rows(d, right_i)


#: Pixels a hole may exceed the occlusion's width by and still be all occlusion
#: (edges of the matched surfaces are uncertain by about this much).
OCCLUSION_MARGIN_PX = 4.0


def foreground_beyond_occlusion(disp: np.ndarray, best: np.ndarray, background: np.ndarray) -> np.ndarray:
    """(H, W) bool: the holes' pixels that are surface the matcher missed, not ground
    the right image cannot see.

    Ground hidden from the right image lies left of the surface that hides it, and
    along a row it is exactly as wide as the disparity step between the two (a
    building's occlusion spans its height's disparity). In a hole whose nearest valid
    disparity on the left is background and on the right is higher, the pixels more
    than that step (plus :data:`OCCLUSION_MARGIN_PX`) from its left end cannot be
    occluded: both images see them. Those whose best match, rejected by the checks,
    lies nearer the right surface than the left one are taken for the right surface
    (a roof face foreshortened in one view, beside the ground its building hides).

    Parameters
    ----------
    disp : (H, W) float
        Checked disparities, NaN in the holes.
    best : (H, W) float
        Every pixel's best disparity before the checks (NaN where none).
    background : (H, W) float
        The background fill of the holes (:func:`_fill_background`): a hole whose left
        side stands above it lies between two raised surfaces (a street between roofs)
        and is left to the background.
    """
    return _foreground(disp, best, background)[0]


def _foreground(disp: np.ndarray, best: np.ndarray, background: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`foreground_beyond_occlusion`'s mask, and its pixels' disparities: each
    one's best match, kept between the disparities on the two sides of its hole.

    (A ramp from the left side's disparity, one occlusion's width into the hole, up to
    the right side's, against guesses that put points beyond the wall, undid most of
    the gain on the rendered surveys: roof completeness fell back to that of the
    background fill.)"""
    left_i, right_i = _nearest_index_along_rows(np.isfinite(disp))
    left, right = _take_along_rows(disp, left_i), _take_along_rows(disp, right_i)
    cols = np.arange(disp.shape[1])[None, :]
    with np.errstate(invalid="ignore"):
        step = right - left  # 0 on valid pixels, NaN where a hole has no side
        beyond = (step > 0) & (cols - left_i > step + OCCLUSION_MARGIN_PX)
        nearer_right = np.abs(best - right) < np.abs(best - left)
        mask = beyond & nearer_right & (left <= background + 1.0)
        return mask, np.clip(best, left, right).astype(np.float32)


#: Least disparity step (px) from a hole's left side to its right side for
#: :func:`faces_by_colour` to look for a roof face in it.
FACE_MIN_STEP_PX = 4.0
#: Least L1 difference (Lab units, lightness weighted by :data:`FACE_LIGHTNESS_WEIGHT`)
#: between the colours on the two sides of a hole for it to be split by colour.
FACE_MIN_CONTRAST = 24.0
#: Weight of lightness against the two colour axes: a face and the ground beside it
#: differ in shading more than in colour, and a shadow changes lightness most.
FACE_LIGHTNESS_WEIGHT = 0.25
#: The face's pixels must lie this close to the roof's colour (mean L1 distance over
#: the contrast): a shadow, unlike both sides, is not taken for the roof. 0.5 gave the
#: same figures on 19 surveys of the family.
FACE_LIKENESS = 0.35
#: A face the right image foreshortens ends at a ridge: the matched roof beyond the
#: hole falls by :data:`FACE_RIDGE_DROP_PX` or more within :data:`FACE_RIDGE_SPAN_PX`.
#: Without this test (in a first version that gave the whole face the ridge's
#: disparity) the wall below a flat roof's edge, coloured like a gravel roof, was taken
#: for a face and raised to the roof: the tolerant DSM RMS rose on each of 15 surveys
#: of the family, by 0.27 m in the median.
FACE_RIDGE_SPAN_PX = 4
FACE_RIDGE_DROP_PX = 1.0


def faces_by_colour(disp: np.ndarray, background: np.ndarray, colour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roof faces the right image sees too foreshortened to match, in the holes beside
    them, told from the ground by the left image's colour.

    At a wide base a roof face that rises towards a ridge away from the left camera is
    squeezed into a few pixels of the right image; the matcher misses it and leaves a
    hole that also holds the ground its building hides from the right image. Along a
    row the hole runs from the matched ground (left) to the ridge (right). The face is
    the part of it coloured like the roof beyond the ridge, the hidden ground the part
    coloured like the ground: the hole is split where the colours change
    (``recon3d.stereo._sgm.face_by_colour``). The face's disparity rises linearly to the
    ridge's from that of its lower edge, which the right image shows where the last
    matched ground pixel lands. Holes that end at a flat roof's edge, whose sides are
    alike in colour, or whose roof-side part is not coloured like the roof are left
    alone.

    Parameters
    ----------
    disp : (H, W) float
        Checked disparities, NaN in the holes.
    background : (H, W) float
        The background fill of the holes (:func:`_fill_background`).
    colour : (H, W, C) float32
        The left image on a 0..255 scale (:func:`_guide`), RGB when it has colour:
        colour is what tells a roof from the ground.

    Returns
    -------
    face : (H, W) bool
    disparity : (H, W) float32
        The face pixels' disparities, NaN elsewhere.
    """
    import cv2
    from recon3d.stereo import _sgm

    shape = disp.shape
    if colour.shape[2] == 3:
        lab = cv2.cvtColor(np.clip(colour, 0, 255).astype(np.uint8), cv2.COLOR_RGB2LAB).astype(np.float32)
        lab[:, :, 0] *= FACE_LIGHTNESS_WEIGHT
    else:
        lab = colour * FACE_LIGHTNESS_WEIGHT
    lab = cv2.blur(lab, (5, 5)).reshape(shape[0], shape[1], -1)  # the texture averaged out
    face = np.zeros(shape, bool)
    value = np.full(shape, np.nan, np.float32)
    _sgm.face_by_colour(np.ascontiguousarray(disp, np.float32), np.ascontiguousarray(background, np.float32),
                        np.ascontiguousarray(lab, np.float32), np.float32(FACE_MIN_STEP_PX),
                        np.float32(FACE_MIN_CONTRAST), 3, FACE_RIDGE_SPAN_PX, np.float32(FACE_RIDGE_DROP_PX),
                        np.float32(FACE_LIKENESS), face, value)
    return face, value


def _colour_cost(left: np.ndarray, right: np.ndarray, rows: np.ndarray, cols: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(n,) mean L1 colour difference over the 3 x 3 window of left pixels (rows, cols)
    and the right pixels ``d`` to their left (whole pixels); inf where the window leaves
    either image."""
    h, w = left.shape[:2]
    total = np.zeros(len(rows), np.float32)
    out = np.zeros(len(rows), bool)
    shift = np.rint(d).astype(np.int64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            y, x = rows + dy, cols + dx
            xr = x - shift
            bad = (y < 0) | (y >= h) | (x < 0) | (x >= w) | (xr < 0) | (xr >= w)
            out |= bad
            y, x, xr = np.clip(y, 0, h - 1), np.clip(x, 0, w - 1), np.clip(xr, 0, w - 1)
            total += np.abs(left[y, x] - right[y, xr]).sum(axis=1)
    return np.where(out, np.inf, total / 9.0)


#: Half size (px) of the window in which :func:`sharpen_steps` looks for a disparity step.
SHARPEN_RADIUS = 3
#: Least disparity step (px) that :func:`sharpen_steps` judges.
SHARPEN_STEP_PX = 2.0
#: Matched pixels sampled for the pair's typical colour match in :func:`sharpen_steps`.
SHARPEN_SAMPLE = 20_000
#: A pixel's own colour match must be this many times worse than the pair's typical
#: (median) one for :func:`sharpen_steps` to judge it. With 1, 95 pixels of a roof of
#: one flat colour under sensor noise (3 grey levels) sank to the street's disparity
#: within the window's reach of a wall (a unit test, ratio 1.2); with 2, none did. On
#: the rendered surveys, whose roofs all have texture, 1 did a little better
#: (heading_180 0.394 against 0.409 m tolerant DSM RMS at ratio 1.5).
SHARPEN_POOR = 2.0


def sharpen_steps(disp: np.ndarray, colour_left: np.ndarray, colour_right: np.ndarray, *, ratio: float) -> int:
    """In place: pixels beside a disparity step that took the raised side but belong to
    the lower one take the lower side's disparity. Returns how many changed.

    The census window (7 x 9) of a street pixel next to a wall holds part of the roof,
    whose texture outweighs the street's, so the roof's disparity wins a pixel or two
    onto the street; triangulated, those pixels stand at roof height beside the
    building, metres of error in the DSM cells along its walls. A pixel's own colours
    tell better: over its 3 x 3 neighbourhood, the mean colour difference to the right
    image at its disparity against that at the lowest disparity within
    :data:`SHARPEN_RADIUS` px. A pixel at least :data:`SHARPEN_STEP_PX` above that
    lowest one takes it when the lower side matches within ``ratio`` times as well, and
    its own match is :data:`SHARPEN_POOR` times worse than the pair's typical (median)
    match: a pixel its own disparity explains well keeps it, whatever the other (a
    uniform roof matches equally well at many disparities).

    Parameters
    ----------
    disp : (H, W) float32
        Checked disparities, NaN where rejected; changed in place.
    colour_left, colour_right : (H, W, C) float32
        The two images on a 0..255 scale (:func:`_guide`).
    ratio : float
        How much worse (a factor) the lower side's colour match may be and still win:
        above 1 favours the lower side, as the cost window's bias is towards the
        raised one.
    """
    from scipy import ndimage

    finite = np.isfinite(disp)
    size = 2 * SHARPEN_RADIUS + 1
    lowest = ndimage.minimum_filter(np.where(finite, disp, np.inf), size, mode="nearest")
    highest = ndimage.maximum_filter(np.where(finite, disp, -np.inf), size, mode="nearest")
    rows, cols = np.nonzero(finite & (highest - lowest > SHARPEN_STEP_PX) & (disp - lowest > SHARPEN_STEP_PX))
    if not len(rows):
        return 0
    own, low = disp[rows, cols], lowest[rows, cols]
    cost = _colour_cost(colour_left, colour_right, rows, cols, own)
    mr, mc = np.nonzero(finite)
    every = max(1, len(mr) // SHARPEN_SAMPLE)  # the typical match, from an even sample of the matched pixels
    typical = float(np.median(_colour_cost(colour_left, colour_right, mr[::every], mc[::every],
                                           disp[mr[::every], mc[::every]])))
    lower = (_colour_cost(colour_left, colour_right, rows, cols, low) < ratio * cost) & (cost > SHARPEN_POOR * typical)
    disp[rows[lower], cols[lower]] = low[lower]
    return int(lower.sum())


def _fill_background(disp: np.ndarray) -> np.ndarray:
    """Invalid pixels take the background among the nearest valid disparities left,
    right, above and below: the second smallest of those found (the smallest when only
    one is), as in Hirschmueller's SGM.

    Rows alone would fill a gap between two raised objects (a tree beside a building)
    at their height; the columns bring in the ground seen above and below the gap, and
    taking the second smallest keeps one stray low value from winning.

    A pixel the right image cannot see takes the smallest when that is its left
    neighbour's (Hirschmueller's occlusions, told from mismatches): ground hidden behind
    a raised surface lies left of that surface in the left image, and where the ground's
    disparity would put it in the right image, the right image shows the nearer surface
    instead (:func:`_hidden_from_right`). Its second smallest neighbour, above or below
    it along the raised surface's edge, is often that surface, which carried roofs onto
    hidden ground.
    """
    out = disp.copy()
    holes = ~np.isfinite(out)
    if not holes.any():
        return out
    left, right = _nearest_along_rows(out)
    up, down = _nearest_along_rows(np.ascontiguousarray(out.T))
    found = np.stack([left[holes], right[holes], up.T[holes], down.T[holes]])
    found = np.sort(found, axis=0)  # NaN sorts last
    count = np.isfinite(found).sum(axis=0)
    fill, lowest = np.where(count >= 2, found[1], found[0]), found[0]
    occluded = (np.abs(left[holes] - lowest) <= 1.0) & (fill > lowest)
    if occluded.any():
        rows, cols = np.nonzero(holes)
        occluded[occluded] = _hidden_from_right(disp, rows[occluded], cols[occluded], lowest[occluded])
        fill[occluded] = lowest[occluded]
    out[holes] = fill
    return out


def _hidden_from_right(disp: np.ndarray, rows: np.ndarray, cols: np.ndarray, candidate: np.ndarray) -> np.ndarray:
    """(n,) bool: left pixels (``rows``, ``cols``) that, at the ``candidate`` disparities,
    land on right-image pixels showing a matched surface nearer by more than 1 px.

    The right image's view is that of the matched left pixels: each right pixel shows
    the largest disparity landing on it."""
    h, w = disp.shape
    seen = np.full((h, w), -np.inf, np.float32)
    r, c = np.nonzero(np.isfinite(disp))
    d = disp[r, c]
    xr = np.rint(c - d).astype(np.int64)
    on = (xr >= 0) & (xr < w)
    np.maximum.at(seen, (r[on], xr[on]), d[on])
    x = np.rint(cols - candidate).astype(np.int64)
    inside = (x >= 0) & (x < w)
    hidden = np.zeros(len(rows), bool)
    hidden[inside] = seen[rows[inside], x[inside]] > candidate[inside] + 1.0
    return hidden


def photo_consistency(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, window: int = 7) -> np.ndarray:
    """Zero-mean normalised cross-correlation of each left pixel's window with the right
    image at its disparity (nearest pixel), in [-1, 1]; NaN where the disparity is.

    Parameters
    ----------
    left, right : (H, W) array
        Rectified grey images (NaN nodata allowed).
    disparity : (H, W) float
    window : int
        Odd window size.
    """
    h, w = disparity.shape
    a = np.nan_to_num(np.asarray(left, np.float32))
    b = np.nan_to_num(np.asarray(right, np.float32))
    xr = np.clip(np.rint(np.arange(w)[None, :] - np.nan_to_num(disparity)), 0, w - 1).astype(np.intp)
    b = b[np.arange(h)[:, None], xr]  # the right image warped onto the left by the disparity

    def mean(x):
        return cv2.boxFilter(x, -1, (window, window))

    ma, mb = mean(a), mean(b)
    cov = mean(a * b) - ma * mb
    var = np.maximum((mean(a * a) - ma * ma) * (mean(b * b) - mb * mb), 1e-6)
    out = (cov / np.sqrt(var)).astype(np.float32)
    out[~np.isfinite(disparity)] = np.nan
    return out


def _guide(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, C) float32 guide on a 0..255 scale (NaN set to 0)."""
    g = np.asarray(image, dtype=np.float32)
    if g.ndim == 2:
        g = g[:, :, None]
    if g.shape[:2] != shape:
        raise InputError(f"guide image of {g.shape[1]} x {g.shape[0]} px, expected {shape[1]} x {shape[0]}")
    g = np.nan_to_num(g, nan=0.0)
    if image.dtype != np.uint8:
        lo, hi = np.percentile(g, [0.1, 99.9])
        g = np.clip((g - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255)
    return g


def _edge_aware_median(disp: np.ndarray, guide: np.ndarray, radius: int, sigma: float, step: float = 2.0) -> np.ndarray:
    """Weighted median of the disparities in a (2r+1)^2 window, weights from colour
    similarity to the centre pixel and distance, at pixels whose window spans a step
    of more than ``step`` px and that differ from that median by more than 1 px;
    elsewhere, and at NaN pixels, the map is unchanged.

    Parameters
    ----------
    disp : (H, W) float32
    guide : (H, W, C) float32
    """
    from scipy import ndimage

    h, w = disp.shape
    size = 2 * radius + 1
    finite = np.isfinite(disp)
    lo = ndimage.minimum_filter(np.where(finite, disp, np.inf), size, mode="nearest")
    hi = ndimage.maximum_filter(np.where(finite, disp, -np.inf), size, mode="nearest")
    todo = np.flatnonzero(finite & (hi - lo > step))
    if todo.size == 0:
        return disp
    from recon3d.stereo import _sgm

    off = np.arange(-radius, radius + 1, 2 if radius > 3 else 1)  # a sparse lattice: same reach, 1/4 of the work
    oy, ox = (a.ravel().astype(np.int64) for a in np.meshgrid(off, off, indexing="ij"))
    spatial = np.exp(-(oy**2 + ox**2) / (2.0 * radius**2)).astype(np.float32)
    out = disp.copy()
    _sgm.weighted_median(np.ascontiguousarray(disp, np.float32), np.ascontiguousarray(guide, np.float32),
                         todo.astype(np.int64), oy, ox, spatial, np.float32(-0.5 / sigma**2), out)
    return out


def _median(disp: np.ndarray, size: int) -> np.ndarray:
    """Median filter that leaves NaN pixels NaN and does not spread them."""
    holes = ~np.isfinite(disp)
    stand_in = np.float32(np.nanmedian(disp)) if not holes.all() else np.float32(0)
    src = np.where(holes, stand_in, disp).astype(np.float32)
    if size <= 5:
        out = cv2.medianBlur(src, size)
    else:
        from scipy import ndimage

        out = ndimage.median_filter(src, size=size, mode="nearest")
    out[holes] = np.nan
    return out
