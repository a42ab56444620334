"""Satellite (RPC) stereo: tiled affine epipolar rectification, matching and ray intersection.

Pushbroom images have no single projection centre, but over a few hundred to a few
thousand pixels each RPC is very close to an affine camera (the s2p observation). The
epipolar direction is then constant over that region: a pixel of one image, lifted
through the RPC heights, traces a straight line in the other. Both images are turned so
that these lines are rows, the second one fitted (affine, least squares) so that
corresponding points share a row, then matched with the frame-stereo matcher. Each
match is intersected by finding the height at which the first image's pixel projects
onto its match in the second image.

Over a large scene the affine approximation drifts, so :func:`dense_cloud_rpc` works on
tiles of the reference image, as s2p does: each tile (its core plus an overlap margin)
gets its own affine approximation of both cameras, its own relative bias from the tie
points inside it, its own rectification, matching and intersection; only points whose
reference pixel lies in the tile's core are kept, so tiles never duplicate points. The
residual vertical parallax of feature matches after rectification is measured per tile
and over all tiles and reported.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import cv2
import numpy as np
import pyproj

from recon3d.core.pointcloud import PointCloud
from recon3d.errors import InputError
from recon3d.io.rpc import RPCCamera

log = logging.getLogger(__name__)

__all__ = [
    "BiasModel",
    "SatellitePair",
    "TiePoints",
    "absolute_shift",
    "auto_tile_size",
    "check_pair",
    "fit_bias_model",
    "dense_cloud_rpc",
    "rectify_rpc_pair",
    "search_heights",
    "tie_self_check",
    "tile_grid",
    "triangulate_ties",
    "utm_crs",
]

SINGLE_TILE_MAX = 1024
"""Images up to this many pixels on their longer side are rectified as one tile by default."""
AUTO_TILE = 800
"""Largest tile core (px) chosen by :func:`auto_tile_size` for larger images."""
TILE_MARGIN = 32
"""Default overlap margin (px) around each tile core: matching context at the core's edges."""
MIN_TIE_POINTS = 10
"""Fewer tie points than this in a tile: the whole image's relative bias is used instead."""


@dataclass
class SatellitePair:
    """Two RPC images resampled to a common epipolar geometry.

    Attributes
    ----------
    left, right : (H, W) float32
        Rectified images, NaN outside the originals.
    A1, A2 : (2, 3) float
        Affine maps from crop pixels (col, row) to rectified (x, y).
    heights : (2,) float
        Height interval (ellipsoidal metres) the disparity range covers.
    disparity_range : (2,) int
    parallax : dict
        Residual vertical parallax of SIFT matches (px) after rectification:
        ``{"median", "p90", "rms", "n", "rejected"}``, over the matches whose left
        point falls in ``core`` (all of them without a core).
    shift : (2,) float
        Relative bias of the second RPC (crop pixels, col and row) removed using tie points.
    bias_ties : int
        Tie points the bias was estimated from (0 when it was not estimated here).
    bias_from : str
        ``"tie points"`` (estimated from this pair's tie points), ``"fallback"`` (too few
        of them: the bias given by the caller) or ``"none"`` (no correction).
    parallax_samples : (k,) float
        The vertical parallaxes (px) summarised in ``parallax``, for pooling over tiles.
    disparity_mid : float
        Disparity (px) of the middle of the height range in this pair's frame: each
        pair has its own frame, so ``disparity_range - disparity_mid`` compares across tiles.
    affine_residual_px : float
        Largest row difference (px) left by the affine approximation on a 15 x 15 grid of
        RPC correspondences over the crop at 5 heights: what tiling keeps small.
    tie_check : (k,) float
        After matching: |dense - tie| disparities (px) at the tie points of the core.
    """

    left: np.ndarray
    right: np.ndarray
    A1: np.ndarray
    A2: np.ndarray
    heights: tuple[float, float]
    disparity_range: tuple[int, int]
    parallax: dict
    shift: np.ndarray
    bias_ties: int = 0
    bias_from: str = "tie points"
    parallax_samples: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    disparity_mid: float = 0.0
    affine_residual_px: float = 0.0
    tie_check: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))


def utm_crs(lon: float, lat: float) -> pyproj.CRS:
    """The WGS 84 / UTM zone CRS of a point (EPSG 326xx north, 327xx south)."""
    zone = int((lon + 180.0) // 6.0) + 1
    return pyproj.CRS.from_epsg((32600 if lat >= 0 else 32700) + zone)


# ---------------------------------------------------------------------------- tiles
def auto_tile_size(width: int, height: int) -> int:
    """Default tile core size (px) for an image: one tile up to ``SINGLE_TILE_MAX`` px.

    Larger images are cut into tiles of at most ``AUTO_TILE`` px, a size over which a
    Pleiades-like pushbroom camera stays affine to well under a pixel.
    """
    longest = max(int(width), int(height))
    return longest if longest <= SINGLE_TILE_MAX else AUTO_TILE


def tile_grid(
    width: int, height: int, tile_size: int, margin: int = TILE_MARGIN
) -> tuple[np.ndarray, np.ndarray]:
    """Cut an image into tiles: cores that partition it, boxes that add an overlap margin.

    Each axis is split into ``ceil(n / tile_size)`` cores of equal size (within a
    pixel), in row-major order (top row of tiles first, left to right).

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    tile_size : int
        Largest core size (px) along each axis.
    margin : int
        Pixels added around each core on every side (clipped to the image).

    Returns
    -------
    cores, boxes : (n, 4) int64
        Half-open pixel boxes ``(col0, row0, col1, row1)``: ``image[row0:row1, col0:col1]``.
        Cores cover every pixel exactly once; each box contains its core.
    """
    if tile_size < 1 or width < 1 or height < 1:
        raise ValueError(f"tile_grid: need positive sizes, got {width} x {height}, tile {tile_size}")

    def edges(n: int) -> np.ndarray:
        k = -(-n // int(tile_size))
        return np.round(np.arange(k + 1) * (n / k)).astype(np.int64)

    ex, ey = edges(int(width)), edges(int(height))
    r0, c0 = np.meshgrid(ey[:-1], ex[:-1], indexing="ij")
    r1, c1 = np.meshgrid(ey[1:], ex[1:], indexing="ij")
    cores = np.column_stack([c0.ravel(), r0.ravel(), c1.ravel(), r1.ravel()])
    limit = np.array([width, height, width, height])
    boxes = np.clip(cores + np.array([-margin, -margin, margin, margin]), 0, limit)
    return cores, boxes


def _in_core(p: np.ndarray, core, width: int, height: int) -> np.ndarray:
    """(k,) bool: crop pixels p (k, 2) (col, row) whose pixel lies in the half-open core.

    A pixel (i, j) covers [i - 0.5, i + 0.5); a core's inner edges are cut there, its
    edges on the image border keep today's rule for a whole image: ``0 <= p <= size - 1``.
    """
    c0, r0, c1, r1 = (int(v) for v in core)
    keep = np.ones(len(p), bool)
    for axis, lo, hi, size in ((0, c0, c1, width), (1, r0, r1, height)):
        v = p[:, axis]
        keep &= (v >= lo - 0.5) if lo > 0 else (v >= 0)
        keep &= (v < hi - 0.5) if hi < size else (v <= size - 1)
    return keep


def _sub_camera(cam: RPCCamera, box, name: str) -> RPCCamera:
    """The camera of the crop ``image[row0:row1, col0:col1]`` of ``cam``'s image."""
    c0, r0, c1, r1 = (int(v) for v in box)
    return dataclasses.replace(
        cam, width=c1 - c0, height=r1 - r0, col0=cam.col0 + c0, row0=cam.row0 + r0, name=name
    )


def _footprint_box(a: RPCCamera, b: RPCCamera, box, shift: np.ndarray, margin: int) -> np.ndarray:
    """Half-open box (col0, row0, col1, row1) of b's image seeing a's box over the height range.

    A 5 x 5 grid over the box at three heights is carried to b, the bias ``shift``
    added, the bounding box widened by ``margin`` and clipped to b's image.

    Raises
    ------
    InputError
        When the box does not fall on b's image.
    """
    c0, r0, c1, r1 = (float(v) for v in box)
    rows, cols = np.meshgrid(np.linspace(r0, r1 - 1, 5), np.linspace(c0, c1 - 1, 5), indexing="ij")
    h0, h1 = a.model.height_range
    rr = np.broadcast_to(rows.ravel(), (3, rows.size)).ravel()
    cc = np.broadcast_to(cols.ravel(), (3, cols.size)).ravel()
    hh = np.repeat(np.linspace(h0, h1, 3), rows.size)
    lon, lat = a.localize(rr, cc, hh)
    r2, c2 = b.project(lon, lat, hh)
    ok = np.isfinite(r2) & np.isfinite(c2)
    if not ok.any():
        raise InputError(f"{a.name}: the tile does not project onto {b.name}")
    c2, r2 = c2[ok] + shift[0], r2[ok] + shift[1]
    out = np.array([
        np.floor(c2.min()) - margin,
        np.floor(r2.min()) - margin,
        np.ceil(c2.max()) + margin + 1,
        np.ceil(r2.max()) + margin + 1,
    ])
    out = np.clip(out, 0, [b.width, b.height, b.width, b.height]).astype(np.int64)
    if out[2] - out[0] < 16 or out[3] - out[1] < 16:
        raise InputError(f"images {a.name} and {b.name}: the tile's footprints do not overlap")
    return out


# ------------------------------------------------------------------ checks
#: Least share of either image the other must see (at some height of the RPC range).
MIN_OVERLAP = 0.2


def check_pair(a: RPCCamera, b: RPCCamera) -> dict:
    """Check that two RPC images can form a stereo pair, before anything is matched.

    Each image must lie within the image domain its RPC describes (a crop whose size or
    offset does not fit its RPC is another image's RPC, or a crop whose offset was
    lost), and each must see at least :data:`MIN_OVERLAP` of the other.

    Returns
    -------
    dict
        ``{"overlap_percent": [share of a that b sees, share of b that a sees]}``.

    Raises
    ------
    InputError
        Naming the image(s) and what does not fit.
    """
    for cam in (a, b):
        m = cam.model
        label = cam.image_path or cam.name
        for axis, start, size, off, scale in (
            ("rows", cam.row0, cam.height, m.line_off, m.line_scale),
            ("columns", cam.col0, cam.width, m.samp_off, m.samp_scale),
        ):
            lo, hi = off - abs(scale), off + abs(scale)
            slack = 0.05 * abs(scale) + 2.0
            if start < lo - slack or start + size - 1 > hi + slack:
                raise InputError(
                    f"{label}: the image ({cam.width} x {cam.height} px) lies outside its RPC validity domain: "
                    f"its {axis} {start:g}..{start + size - 1:g}, the RPC's {lo:.0f}..{hi:.0f} (another image's RPC, "
                    "or a crop whose offset was lost?)"
                )
    share_a, share_b = _seen_share(a, b), _seen_share(b, a)
    if min(share_a, share_b) < MIN_OVERLAP:
        raise InputError(
            f"images {a.image_path or a.name} and {b.image_path or b.name} do not overlap enough for stereo: "
            f"the second sees {100 * share_a:.0f} % of the first, the first {100 * share_b:.0f} % of the second "
            f"(at least {100 * MIN_OVERLAP:.0f} % of each)"
        )
    return {"overlap_percent": [round(100 * share_a, 1), round(100 * share_b, 1)]}


def _seen_share(a: RPCCamera, b: RPCCamera, n: int = 21) -> float:
    """Share of a 21 x 21 grid over ``a`` that falls on ``b``, at the best of 5 heights
    of the RPC range (the ground's height is not known yet)."""
    rows, cols = (g.ravel() for g in np.meshgrid(np.linspace(0, a.height - 1, n), np.linspace(0, a.width - 1, n), indexing="ij"))
    best = 0.0
    for h in np.linspace(*a.model.height_range, 5):
        lon, lat = a.localize(rows, cols, np.full(rows.shape, h))
        r2, c2 = b.project(lon, lat, np.full(rows.shape, h))
        best = max(best, float(np.mean(b.contains(r2, c2))))
    return best


# ------------------------------------------------------------------ rectification
def _correspondences(a: RPCCamera, b: RPCCamera, heights: np.ndarray, n: int = 15):
    """Crop pixels (col, row) of a grid over ``a`` and of the same ground points in ``b``, per height.

    Returns p1 (k, 2), p2 (k, 2) and the height of each pair (k,).
    """
    rows, cols = np.meshgrid(np.linspace(0, a.height - 1, n), np.linspace(0, a.width - 1, n), indexing="ij")
    r, c = rows.ravel(), cols.ravel()
    p1, p2, hh = [], [], []
    for h in heights:
        lon, lat = a.localize(r, c, np.full(r.shape, h))
        r2, c2 = b.project(lon, lat, np.full(r.shape, h))
        ok = np.isfinite(r2) & np.isfinite(c2)
        p1.append(np.column_stack([c[ok], r[ok]]))
        p2.append(np.column_stack([c2[ok], r2[ok]]))
        hh.append(np.full(ok.sum(), h))
    return np.concatenate(p1), np.concatenate(p2), np.concatenate(hh)


def _direction(p_fixed_moving: np.ndarray, n_heights: int) -> np.ndarray:
    """Mean unit direction of the tracks (k, 2) traced as height grows (k = points x heights)."""
    tracks = p_fixed_moving.reshape(n_heights, -1, 2)
    d = (tracks[-1] - tracks[0]).mean(axis=0)
    return d / np.linalg.norm(d)


def _epipolar_geometry(a: RPCCamera, b: RPCCamera):
    """Checks and sampled correspondences of a pair: the part of rectification without images.

    Returns
    -------
    heights : (5,) float
        Sampled heights over the RPC's height range.
    p1, p2 : (k, 2) float
        Crop pixels (col, row) of a grid over ``a`` and their images in ``b``, per height.
    hh : (k,) float
        Height of each pair.
    d1, d2 : (2,) float
        Unit epipolar directions in ``a`` and in ``b``.

    Raises
    ------
    InputError
        When the crops lie outside their RPC domain or do not overlap, or the images are
        the same view (no parallax).
    """
    h0, h1 = a.model.height_range
    heights = np.linspace(h0, h1, 5)
    for cam in (a, b):
        rows = np.array([0, 0, cam.height - 1, cam.height - 1.0])
        cols = np.array([0, cam.width - 1, 0, cam.width - 1.0])
        hm = np.full(4, 0.5 * (h0 + h1))
        lon, lat = cam.localize(rows, cols, hm)
        if not np.all(cam.in_domain(lon, lat, hm)):
            raise InputError(f"image {cam.name}: the crop lies outside its RPC validity domain")
    p1, p2, hh = _correspondences(a, b, heights)
    if len(p1) < 20 or not _overlap(p2, b):
        raise InputError(f"images {a.name} and {b.name}: their footprints do not overlap")
    q2, q1, _ = _correspondences(b, a, heights)
    d2 = _direction(p2, len(heights))  # epipolar direction in b: a's pixel lifted through the heights
    d1 = _direction(q1, len(heights))
    parallax_px = np.linalg.norm(p2.reshape(len(heights), -1, 2)[-1] - p2.reshape(len(heights), -1, 2)[0], axis=1).mean()
    if parallax_px < 2.0:
        raise InputError(
            f"images {a.name} and {b.name}: only {parallax_px:.1f} px of parallax over {h0:.0f}-{h1:.0f} m; "
            "the two images see the ground from the same direction (identical images?)"
        )
    return heights, p1, p2, hh, d1, d2


def rectify_rpc_pair(
    a: RPCCamera,
    b: RPCCamera,
    image_a: np.ndarray,
    image_b: np.ndarray,
    *,
    ties: tuple[np.ndarray, np.ndarray] | None = None,
    fallback_shift: np.ndarray | None = None,
    core=None,
    heights: tuple[float, float] | None = None,
) -> SatellitePair:
    """Affine epipolar rectification of two RPC crops, with the relative RPC bias removed.

    Parameters
    ----------
    a, b : RPCCamera
        Cameras of the two crops (``a`` is the reference).
    image_a : (a.height, a.width) float
    image_b : (b.height, b.width) float
        The crops, NaN = no data.
    ties : ((k, 2) float, (k, 2) float) or None
        Tie points (col, row) in ``a`` and in ``b``; None: SIFT on the two images.
    fallback_shift : (2,) float or None
        Bias used when there are fewer than ``MIN_TIE_POINTS`` tie points (None: no
        correction).
    core : (4,) int or None
        Box (col0, row0, col1, row1) of ``a``: the parallax is measured on the
        features whose left point lies in it (None: everywhere).
    heights : (float, float) or None
        Ellipsoidal height interval (m) the disparity range must cover, e.g. from the
        tie points (see :func:`search_heights`); None: the RPC's height range.

    Returns
    -------
    SatellitePair

    Raises
    ------
    InputError
        When the crops do not overlap, or the images are the same view (no parallax).
    """
    sampled, p1, p2, hh, d1, d2 = _epipolar_geometry(a, b)
    h0, h1 = (float(sampled[0]), float(sampled[-1])) if heights is None else (float(heights[0]), float(heights[1]))
    if ties is None:
        ties = _tie_points(image_a, image_b)
    shift, n_ties = _bias_from_ties(a, b, *ties, d2)
    bias_from = "tie points"
    if shift is not None and fallback_shift is not None:
        off = float(np.linalg.norm(shift - fallback_shift))
        if off > BIAS_AGREEMENT_PX:  # a few ties on one structure: the pair's model knows better
            log.info("RPC pair %s-%s: the tile's bias is %.2f px off the pair's model; the model used", a.name, b.name, off)
            shift, bias_from = np.asarray(fallback_shift, float), f"pair model (the tile's own ties {off:.2f} px off)"
    if shift is None:
        if fallback_shift is None:
            log.warning("RPC pair %s-%s: %d tie points, no bias correction", a.name, b.name, n_ties)
            shift, bias_from = np.zeros(2), "none"
        else:
            log.info("RPC pair %s-%s: %d tie points, the pair's bias model used", a.name, b.name, n_ties)
            shift, bias_from = np.asarray(fallback_shift, float), "pair model (too few tie points in the tile)"
    p2 = p2 + shift
    mid = hh == sampled[len(sampled) // 2]
    A1, A2 = _affine_maps(p1, p2, mid, d1)
    A1, A2, size = _frame(A1, A2, a, b)
    left = _warp(image_a, A1, size)
    right = _warp(image_b, A2, size)
    q1, q2 = _apply(A1, p1), _apply(A2, p2)
    d = q1[:, 0] - q2[:, 0]
    affine_residual = float(np.abs(q1[:, 1] - q2[:, 1]).max())  # the affine cameras' own error
    d_mid = float(np.median(d[mid]))
    if heights is None:
        lo, hi = np.floor(d.min()) - 4, np.ceil(d.max()) + 4
    else:
        lo, hi = _search_range(a, b, A1, A2, shift, (h0, h1))
    samples, rejected = _parallax_samples(left, right, A1, a, core)
    parallax = _parallax_summary(samples, rejected)
    log.info(
        "RPC pair %s-%s: disparity %d..%d, vertical parallax %s (affine model %.3f px)",
        a.name, b.name, lo, hi, parallax, affine_residual,
    )
    return SatellitePair(
        left, right, A1, A2, (h0, h1), (int(lo), int(hi)), parallax, shift,
        n_ties, bias_from, samples, d_mid, affine_residual,
    )


def _search_range(a: RPCCamera, b: RPCCamera, A1, A2, shift, heights) -> tuple[int, int]:
    """Disparities (whole px, +-2) of a grid over ``a`` at the two ``heights``, in the maps' frame."""
    e1, e2, _ = _correspondences(a, b, np.asarray(heights, float))
    d = _apply(A1, e1)[:, 0] - _apply(A2, e2 + shift)[:, 0]
    return int(np.floor(d.min()) - 2), int(np.ceil(d.max()) + 2)


def _affine_maps(p1: np.ndarray, p2: np.ndarray, mid: np.ndarray, d1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Affine epipolar maps of both images, before :func:`_frame`.

    ``a`` is turned so that its epipolar direction ``d1`` is the x axis; ``b``'s map is
    fitted (least squares) so that every correspondence lands on the same row, and the
    points of the middle height on the same column (zero disparity there).

    Parameters
    ----------
    p1, p2 : (k, 2) float
        Corresponding pixels (col, row) in ``a`` and ``b``, over several heights; ``p2``
        where b's image shows the points (RPC projection plus the relative bias).
    mid : (k,) bool
        Correspondences at the middle height.
    d1 : (2,) float
        Unit epipolar direction in ``a``.

    Returns
    -------
    A1, A2 : (2, 3) float
        Maps from image pixels (col, row) to rectified (x, y). A2 takes b's image pixels
        as they are: the bias is in ``p2`` already (removing it again, as an earlier
        version did, doubled the correction and left its size, 0.5 px on the Giza pair,
        as vertical parallax).
    """
    R1 = np.array([d1, [-d1[1], d1[0]]])
    A1 = np.column_stack([R1, np.zeros(2)])
    x1 = p1 @ R1.T
    design = np.column_stack([p2, np.ones(len(p2))])
    y_row = np.linalg.lstsq(design, x1[:, 1], rcond=None)[0]  # same row as in a, for every height
    x_row = np.linalg.lstsq(design[mid], x1[mid, 0], rcond=None)[0]  # zero disparity at the middle height
    return A1, np.array([x_row, y_row])


def _overlap(p2: np.ndarray, b: RPCCamera) -> bool:
    inside = (p2[:, 0] >= 0) & (p2[:, 0] < b.width) & (p2[:, 1] >= 0) & (p2[:, 1] < b.height)
    return inside.mean() > 0.1


def _tie_points(
    image_a: np.ndarray, image_b: np.ndarray, nfeatures: int = 3000
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT tie points (Lowe ratio 0.7) between two crops.

    Returns
    -------
    t1, t2 : (k, 2) float
        Pixel (col, row) in image_a and in image_b; k = 0 when either has no features.
    """
    g1, g2 = _to8(image_a), _to8(image_b)
    sift = cv2.SIFT_create(nfeatures=int(nfeatures))
    k1, s1 = sift.detectAndCompute(g1, None)
    k2, s2 = sift.detectAndCompute(g2, None)
    if s1 is None or s2 is None or len(k1) < 2 or len(k2) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(s1, s2, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < 0.7 * m[1].distance]
    t1 = np.array([k1[m.queryIdx].pt for m in good], float).reshape(-1, 2)
    t2 = np.array([k2[m.trainIdx].pt for m in good], float).reshape(-1, 2)
    return t1, t2


#: A tile's own relative bias may differ from the pair's bias model by this much (px)
#: before the model is trusted over it.
BIAS_AGREEMENT_PX = 0.3


@dataclass
class BiasModel:
    """The relative pointing bias of a pair over the reference image: an affine function.

    RPCs of one pair disagree by an offset that drifts slowly over a scene (attitude
    drift). Only its component across the epipolar lines matters; it is fitted to
    every tie point as ``c0 + c1 * col + c2 * row`` (robustly; the drift terms only
    when they are significant), the global refinement that makes tiles agree.

    Attributes
    ----------
    across : (2,) float
        Unit direction in b's image across the epipolar lines.
    coeffs : (3,) float
        c0 (px), c1 and c2 (px per px of ``a``'s crop).
    rms : float
        RMS (px) of the tie points' offsets about the model.
    ties : int
        Tie points the model was fitted to.
    """

    across: np.ndarray
    coeffs: np.ndarray
    rms: float
    ties: int

    def at(self, col: float, row: float) -> np.ndarray:
        """(2,) shift (col, row) of b's image at a pixel of ``a``'s crop."""
        return self.across * float(self.coeffs @ [1.0, col, row])

    def to_dict(self) -> dict:
        return {"constant_px": round(float(self.coeffs[0]), 3),
                "drift_px_per_1000px": np.round(1000 * self.coeffs[1:], 3).tolist(),
                "rms_px": round(self.rms, 3), "tie_points": self.ties}


def fit_bias_model(a: RPCCamera, b: RPCCamera, t1: np.ndarray, t2: np.ndarray, d2: np.ndarray) -> BiasModel | None:
    """The pair's :class:`BiasModel` from tie points (None: fewer than ``MIN_TIE_POINTS``).

    The drift terms are kept when the ties span the image (at least 30 of them) and
    they change the offset by more than 0.1 px across it.
    """
    offsets, across = _across_offsets(a, b, t1, t2, d2)
    ok = np.isfinite(offsets)
    if ok.sum() < MIN_TIE_POINTS:
        return None
    pos, off = t1[ok], offsets[ok]
    design = np.column_stack([np.ones(len(off)), pos])
    keep = np.abs(off - np.median(off)) < 3.0
    coeffs = np.array([np.median(off[keep]), 0.0, 0.0])
    if keep.sum() >= 30:
        for _ in range(3):  # least squares, then drop the ties 3 robust sigmas off
            fit = np.linalg.lstsq(design[keep], off[keep], rcond=None)[0]
            res = off - design @ fit
            sigma = max(1.4826 * float(np.median(np.abs(res[keep]))), 0.05)
            keep = np.abs(res) <= 3 * sigma
        span = np.abs(fit[1]) * a.width + np.abs(fit[2]) * a.height
        if span > 0.1:
            coeffs = fit
        else:
            coeffs = np.array([np.median(off[keep]), 0.0, 0.0])
    res = off[keep] - design[keep] @ coeffs
    return BiasModel(across, coeffs, float(np.sqrt(np.mean(res**2))), int(keep.sum()))


def _across_offsets(a, b, t1, t2, d2):
    """(k,) offsets (px) of tie points across b's epipolar lines from where the RPCs put them, and that direction."""
    mid = float(np.mean(a.model.height_range))
    lon, lat = a.localize(t1[:, 1], t1[:, 0], np.full(len(t1), mid))
    r2, c2 = b.project(lon, lat, np.full(len(t1), mid))
    across = np.array([-d2[1], d2[0]])
    return (t2 - np.column_stack([c2, r2])) @ across, across


def _bias_from_ties(a: RPCCamera, b: RPCCamera, t1: np.ndarray, t2: np.ndarray, d2: np.ndarray):
    """Shift (col, row) of b's RPC across the epipolar direction, from tie points.

    RPCs of one pair disagree by a near-constant offset; only its component across the
    epipolar lines matters for rectification (along them it is a height offset).

    Parameters
    ----------
    t1, t2 : (k, 2) float
        Tie points (col, row) in ``a``'s and ``b``'s crops.
    d2 : (2,) float
        Unit epipolar direction in ``b``.

    Returns
    -------
    shift : (2,) float or None
        None when there are fewer than ``MIN_TIE_POINTS`` usable tie points.
    n : int
        Tie points used (all of them when too few).
    """
    if len(t1) < MIN_TIE_POINTS:
        return None, len(t1)
    offsets, across = _across_offsets(a, b, t1, t2, d2)
    offsets = offsets[np.isfinite(offsets)]
    if len(offsets) < MIN_TIE_POINTS:
        return None, len(offsets)
    med = np.median(offsets)
    keep = np.abs(offsets - med) < 3.0
    if keep.sum() < MIN_TIE_POINTS:
        return None, int(keep.sum())
    shift = across * float(np.median(offsets[keep]))
    log.info(
        "RPC pair %s-%s: relative bias %.2f px across the epipolar lines (%d tie points)",
        a.name, b.name, med, keep.sum(),
    )
    return shift, int(keep.sum())


@dataclass
class TiePoints:
    """SIFT tie points of a pair that satisfy the RPC epipolar constraint, triangulated.

    Attributes
    ----------
    left, right : (k, 2) float
        Pixels (col, row) in ``a``'s and ``b``'s crops (``right`` as b's image shows them).
    height : (k,) float
        Ellipsoidal height (m) at which the left pixel's ray meets the right pixel's.
    matched : int
        SIFT matches before the epipolar test.
    """

    left: np.ndarray
    right: np.ndarray
    height: np.ndarray
    matched: int

    def inside(self, box_a, box_b=None) -> np.ndarray:
        """(k,) bool: ties whose left point lies in ``box_a`` (and right point in ``box_b``),
        half-open boxes (col0, row0, col1, row1)."""
        keep = np.ones(len(self.height), bool)
        for pts, box in ((self.left, box_a), (self.right, box_b)):
            if box is not None:
                c0, r0, c1, r1 = box
                keep &= (pts[:, 0] >= c0) & (pts[:, 0] < c1) & (pts[:, 1] >= r0) & (pts[:, 1] < r1)
        return keep


#: Largest distance (px) of a tie point's right pixel from the epipolar curve of its
#: left pixel: s2p keeps matches within 1 px of the rectified row; off it they are
#: false matches, whatever their descriptors say.
TIE_EPIPOLAR_PX = 1.0


def triangulate_ties(a: RPCCamera, b: RPCCamera, t1: np.ndarray, t2: np.ndarray, shift: np.ndarray) -> TiePoints:
    """Tie points that lie on their epipolar curves, with their heights.

    Each left pixel's ray is intersected with the right pixel (the relative bias
    ``shift`` removed); a tie whose right pixel lies more than
    :data:`TIE_EPIPOLAR_PX` from the curve its left pixel traces over the heights, or
    whose height falls outside the RPC's height range widened by half its size, is a
    false match and dropped.
    """
    if len(t1) == 0:
        return TiePoints(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0)
    h0, h1 = a.model.height_range
    rpc_right = t2 - shift
    h = _intersect(a, b, t1, rpc_right, h0, h1)
    residual = np.linalg.norm(_lift(a, b, t1, h) - rpc_right, axis=1)
    span = h1 - h0
    ok = np.isfinite(h) & (residual <= TIE_EPIPOLAR_PX) & (h >= h0 - span / 2) & (h <= h1 + span / 2)
    return TiePoints(t1[ok], t2[ok], h[ok], len(t1))


#: Height margin (m) added below and above the tie points' range: the surface between
#: the features (a dark valley floor, a roof's flat middle) may reach beyond them.
SEARCH_MARGIN_M = 10.0


def search_heights(heights: np.ndarray, *, margin: float = SEARCH_MARGIN_M) -> tuple[float, float]:
    """The height interval to search, from tie point heights (the s2p way).

    The 1st to 99th percentile (all of them for fewer than 100 ties: a percentile of a
    few points is their extreme), widened by ``margin`` and by 10 % of its span, so
    that a real surface a little beyond the features is still searched while a
    single stray tie cannot widen the range.
    """
    h = np.sort(np.asarray(heights, float))
    lo, hi = (np.percentile(h, [1, 99]) if len(h) >= 100 else (h[0], h[-1]))
    extra = margin + 0.1 * (hi - lo)
    return float(lo - extra), float(hi + extra)


def _to8(image: np.ndarray) -> np.ndarray:
    v = image[np.isfinite(image)]
    lo, hi = np.percentile(v, [0.5, 99.5]) if v.size else (0.0, 1.0)
    return np.clip((np.nan_to_num(image, nan=lo) - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)


def _apply(A: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ A[:, :2].T + A[:, 2]


def _frame(A1: np.ndarray, A2: np.ndarray, a: RPCCamera, b: RPCCamera):
    """Translate both maps so the rectified images start at (0, 0) and share rows; output size."""
    corners = lambda cam: np.array([[0, 0], [cam.width - 1, 0], [0, cam.height - 1], [cam.width - 1, cam.height - 1]], float)  # noqa: E731
    c1, c2 = _apply(A1, corners(a)), _apply(A2, corners(b))
    y0 = min(c1[:, 1].min(), c2[:, 1].min())
    y1 = max(c1[:, 1].max(), c2[:, 1].max())
    A1, A2 = A1.copy(), A2.copy()
    A1[:, 2] -= [c1[:, 0].min(), y0]
    A2[:, 2] -= [c2[:, 0].min(), y0]
    width = int(np.ceil(max(np.ptp(c1[:, 0]), np.ptp(c2[:, 0])))) + 1
    return A1, A2, (width, int(np.ceil(y1 - y0)) + 1)


def _warp(image: np.ndarray, A: np.ndarray, size) -> np.ndarray:
    valid = cv2.warpAffine(np.ones(image.shape, np.uint8), A, size, flags=cv2.INTER_NEAREST, borderValue=0)
    out = cv2.warpAffine(image.astype(np.float32), A, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out[valid == 0] = np.nan
    return out


def _parallax_samples(
    left: np.ndarray, right: np.ndarray, A1: np.ndarray, a: RPCCamera, core=None, max_features: int = 4000
) -> tuple[np.ndarray, int]:
    """Vertical parallaxes (px) of SIFT matches (Lowe ratio 0.75) between rectified images.

    The method of :func:`recon3d.stereo.rectify.measure_parallax` (matches more than 4 px
    off the row are mismatches), restricted to the matches whose left point maps back
    into ``core`` of ``a`` (see :func:`_in_core`), so that overlapping tiles do not
    count a feature twice.

    Returns
    -------
    dy : (k,) float
        Absolute row differences of the kept matches.
    rejected : int
        Matches (in the core) more than 4 px off the row.
    """
    sift = cv2.SIFT_create(nfeatures=max_features)
    ka, da = sift.detectAndCompute(_to8(left), None)
    kb, db = sift.detectAndCompute(_to8(right), None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return np.zeros(0), 0
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in matches if len(m) == 2 and m[0].distance < 0.75 * m[1].distance]
    pa = np.array([ka[m.queryIdx].pt for m in good], float).reshape(-1, 2)
    pb = np.array([kb[m.trainIdx].pt for m in good], float).reshape(-1, 2)
    if core is not None:
        inside = _in_core(_apply(_invert(A1), pa), core, a.width, a.height)
        pa, pb = pa[inside], pb[inside]
    dy = np.abs(pa[:, 1] - pb[:, 1])
    keep = dy <= 4.0
    return dy[keep], int((~keep).sum())


def _parallax_summary(dy: np.ndarray, rejected: int) -> dict:
    """``{"median", "p90", "rms", "n", "rejected"}`` of vertical parallaxes (px), as in rectify."""
    if dy.size == 0:
        nan = float("nan") if rejected == 0 else float("inf")
        return {"median": nan, "p90": nan, "rms": nan, "n": 0, "rejected": int(rejected)}
    return {
        "median": round(float(np.median(dy)), 3),
        "p90": round(float(np.percentile(dy, 90)), 3),
        "rms": round(float(np.sqrt(np.mean(dy**2))), 3),
        "n": int(dy.size),
        "rejected": int(rejected),
    }


# ------------------------------------------------------------------ dense cloud
def dense_cloud_rpc(
    a: RPCCamera,
    b: RPCCamera,
    image_a: np.ndarray,
    image_b: np.ndarray,
    *,
    tile_size: int | None = None,
    margin: int = TILE_MARGIN,
    engine: str = "census",
    dem=None,
    dem_tolerance: float = 20.0,
    progress=None,
) -> tuple[PointCloud, dict]:
    """Rectify, match and intersect an RPC pair, tile by tile, into a cloud in its UTM zone.

    The reference image ``a`` is cut by :func:`tile_grid`. Each tile (core + margin) is
    rectified with its own local affine approximation of both cameras (over the tile's
    footprint and the RPC height range) and its own relative bias (from the tie points
    inside it; the whole image's when it has fewer than ``MIN_TIE_POINTS``), matched
    and intersected; the points whose reference pixel falls in the tile's core are kept
    and the tiles concatenated in row-major order. A tile that cannot be processed (no
    overlap, no texture, nothing matched) is skipped with a warning.

    Parameters
    ----------
    a, b : RPCCamera
        Cameras of the two crops; ``a`` is the reference.
    image_a : (a.height, a.width) float
    image_b : (b.height, b.width) float
        The crops, NaN = no data.
    tile_size : int or None
        Largest tile core (px); None: :func:`auto_tile_size` (one tile for images up to
        ``SINGLE_TILE_MAX`` px, the whole-image rectification of earlier versions).
    margin : int
        Overlap margin (px) around each core, in the reference image.
    engine : {"census", "sgbm"}
        Matching engine (:class:`~recon3d.stereo.match.MatchParams`).
    dem : Raster or None
        An exogenous elevation model (heights in the RPCs' reference) that narrows each
        tile's searched heights to its range under the tile, +- ``dem_tolerance``.
    dem_tolerance : float
        Metres the surface may stand above or lie below the DEM (objects, DEM error).
    progress : callable or None
        Called with ``"tile k/n"`` as each tile starts.

    Returns
    -------
    cloud : PointCloud
        (n, 3): x, y in WGS 84 / UTM (metres), z ellipsoidal height (metres);
        ``quality`` and ``observed`` (1 where the pixel was matched, 0 where its
        disparity was filled in from its neighbours).
    report : dict
        Whole-image relative bias, residual vertical parallax pooled over the tiles
        (median, p90, rms, n, rejected), the largest affine-model residual
        (``affine_residual_px``, see :class:`SatellitePair`), disparity range (the tile's for one tile; for
        several, the union relative to each tile's middle-height disparity), height
        interval, matched percentage (rectified pixels of the tile cores matched before
        gap filling; pixels off the reference image not counted), point count, ``"tiles"``:
        tile size, margin, count, failures and a per-tile record (core box, bias,
        parallax, affine residual, disparity range, matched percentage, points).

    Each tile searches the heights of the tie points inside it (:func:`search_heights`;
    the whole pair's when it holds fewer than ``MIN_TIE_POINTS``), never the RPC's blind
    height range; points lower than the lowest tie by more than ``SEARCH_MARGIN_M``
    are dropped.

    Raises
    ------
    InputError
        When the crops lie outside their RPC domain or do not overlap, the images are
        the same view, too few tie points bound the heights (and no ``dem``), or no tile
        could be processed.
    """
    if image_a.shape[:2] != (a.height, a.width) or image_b.shape[:2] != (b.height, b.width):
        raise ValueError("dense_cloud_rpc: image shapes do not match their cameras")
    overlap = check_pair(a, b)
    _, _, _, _, _, d2 = _epipolar_geometry(a, b)  # the whole pair's checks, with today's messages
    size = auto_tile_size(a.width, a.height) if tile_size is None else int(tile_size)
    cores, boxes = tile_grid(a.width, a.height, size, margin)
    area = a.width * a.height
    # 3000 SIFT features up to the single-tile size, as many per pixel beyond: tiles keep ties
    nfeatures = max(3000, int(3000 * area / SINGLE_TILE_MAX**2))
    t1, t2 = _tie_points(image_a, image_b, nfeatures=nfeatures)
    whole_shift, n_ties = _bias_from_ties(a, b, t1, t2, d2)  # None: too few tie points
    model = fit_bias_model(a, b, t1, t2, d2)
    ties = triangulate_ties(a, b, t1, t2, np.zeros(2) if whole_shift is None else whole_shift)
    if len(ties.height) < MIN_TIE_POINTS and dem is None:
        raise InputError(
            f"images {a.name} and {b.name}: {len(ties.height)} tie points agree with the RPCs "
            f"({ties.matched} SIFT matches): too few to bound the heights to search; "
            "give an elevation model with --dem"
        )
    floor = float(ties.height.min()) - SEARCH_MARGIN_M if len(ties.height) else -np.inf
    limit = search_heights(ties.height) if len(ties.height) >= MIN_TIE_POINTS else None
    pieces, records, failures, samples, rejected, tie_diffs, scale = [], [], [], [], 0, [], []
    for k, (core, box) in enumerate(zip(cores, boxes, strict=True)):
        if progress is not None:
            progress(f"tile {k + 1}/{len(cores)}")
        try:
            frame = _tile_frame(a, b, box, k, len(cores) == 1, whole_shift, margin)
            search, why = _tile_search(box, frame[2], ties, len(cores) == 1, a, dem, dem_tolerance)
            piece, pair, (n_matched, n_core) = _tile_points(
                a, b, image_a, image_b, core, box, frame, (t1, t2), whole_shift,
                search=search, engine=engine, floor=floor, model=model, limit=limit, checked=ties,
            )
        except InputError as exc:
            log.warning(
                "RPC pair %s-%s: tile %d of %d (core %s) skipped: %s",
                a.name, b.name, k, len(cores), core.tolist(), exc,
            )
            failures.append({"tile": k, "core": core.tolist(), "reason": str(exc)})
            continue
        pieces.append(piece)
        samples.append(pair.parallax_samples)
        tie_diffs.append(pair.tie_check)
        span = max(pair.disparity_range[1] - pair.disparity_range[0] - 4, 1)
        scale.append(abs(pair.heights[1] - pair.heights[0]) / span)
        rejected += pair.parallax["rejected"]
        records.append(
            {
                "tile": k,
                "core": core.tolist(),
                "bias_px": np.round(pair.shift, 3).tolist(),
                "bias_from": pair.bias_from,
                "bias_tie_points": pair.bias_ties,
                "vertical_parallax_px": pair.parallax,
                "search_heights_m": [round(pair.heights[0], 2), round(pair.heights[1], 2)],
                "search_from": why if tuple(pair.heights) == tuple(search) else
                f"{why}; widened to the pair's (the surface reached an end of {search[0]:.0f}..{search[1]:.0f} m)",
                "disparity_range": list(pair.disparity_range),
                "disparity_mid": round(pair.disparity_mid, 2),
                "affine_residual_px": round(pair.affine_residual_px, 4),
                "matched_percent": round(100.0 * n_matched / max(n_core, 1), 2),
                "overlap_samples": n_core,
                "matched_samples": n_matched,
                "points": int(len(piece[0])),
            }
        )
    if not pieces:
        reasons = "; ".join(sorted({f["reason"] for f in failures}))
        raise InputError(f"images {a.name} and {b.name}: no tile could be matched ({reasons})")
    self_check, warning = tie_self_check(np.concatenate(tie_diffs), float(np.median(scale)), f"{a.name} and {b.name}")
    lon, lat, h, conf, seen = (np.concatenate([p[i] for p in pieces]) for i in range(5))
    crs = utm_crs(float(np.nanmedian(lon)), float(np.nanmedian(lat)))
    east, north = pyproj.Transformer.from_crs(4326, crs, always_xy=True).transform(lon, lat)
    attributes = {"quality": conf.astype(np.float32), "observed": seen.astype(np.uint8)}
    cloud = PointCloud(np.column_stack([east, north, h]), attributes, crs)
    n_core = sum(r["overlap_samples"] for r in records)
    matched_percent = round(100.0 * sum(r["matched_samples"] for r in records) / max(n_core, 1), 2)
    report = {
        **overlap,
        "relative_bias_px": np.round(np.zeros(2) if whole_shift is None else whole_shift, 3).tolist(),
        "bias_model": None if model is None else model.to_dict(),
        "vertical_parallax_px": _parallax_summary(np.concatenate(samples), rejected),
        "affine_residual_px": round(max(r["affine_residual_px"] for r in records), 4),
        "disparity_range": _disparity_union(records),
        "height_interval_m": [min(r["search_heights_m"][0] for r in records),
                              max(r["search_heights_m"][1] for r in records)],
        "tie_points": {
            "sift_matches": ties.matched,
            "on_epipolar_curves": int(len(ties.height)),
            "epipolar_tolerance_px": TIE_EPIPOLAR_PX,
        },
        "tie_heights_m": [round(float(ties.height.min()), 2), round(float(ties.height.max()), 2)] if len(ties.height) else None,
        "lowest_height_kept_m": round(floor, 2) if np.isfinite(floor) else None,
        "matched_percent": matched_percent,
        "self_check": self_check,
        "self_check_warning": warning,
        "matching": {"engine": engine, "intensity_weight": SATELLITE_INTENSITY_WEIGHT,
                     "reason": "satellite pan images: half the frame images' intensity weight (see "
                     "recon3d.stereo.satellite.SATELLITE_INTENSITY_WEIGHT)"},
        "points": len(cloud),
        "heights": "ellipsoidal (WGS 84), as the RPCs give them",
        "tiles": {
            "tile_size_px": size,
            "margin_px": int(margin),
            "count": int(len(cores)),
            "failed": len(failures),
            "failures": failures,
            "per_tile": records,
        },
    }
    if len(cores) > 1:
        log.info(
            "RPC pair %s-%s: %d tiles of <= %d px (%d failed), vertical parallax %s, %d points",
            a.name, b.name, len(cores), size, len(failures), report["vertical_parallax_px"], len(cloud),
        )
    return cloud, report


def _disparity_union(records: list[dict]) -> list[int]:
    """The searched disparity range: the tile's for one tile; for several, the union of the
    tiles' ranges each taken relative to its middle-height disparity (tiles have their own
    rectified frames), so that its width is the parallax range of the whole scene."""
    if len(records) == 1:
        return list(records[0]["disparity_range"])
    lo = min(r["disparity_range"][0] - r["disparity_mid"] for r in records)
    hi = max(r["disparity_range"][1] - r["disparity_mid"] for r in records)
    return [int(np.floor(lo)), int(np.ceil(hi))]


def _tile_frame(a, b, box, k: int, whole: bool, whole_shift, margin: int):
    """The camera of one tile, that of the part of b's image that sees it, and that part's box.

    Returns
    -------
    sa, sb : RPCCamera
    bbox : (4,) int
        (col0, row0, col1, row1) of ``sb`` in b's crop.
    """
    if whole:
        return a, b, np.array([0, 0, b.width, b.height])
    sa = _sub_camera(a, box, f"{a.name}[tile {k}]")
    shift = np.zeros(2) if whole_shift is None else whole_shift
    bbox = _footprint_box(sa, b, (0, 0, sa.width, sa.height), shift, margin)
    return sa, _sub_camera(b, bbox, f"{b.name}[tile {k}]"), bbox


def _tile_search(box, bbox, ties: TiePoints, whole: bool, a, dem, dem_tolerance: float):
    """The heights one tile searches, and why: its tie points', else the whole pair's,
    narrowed to the DEM's range under the tile (+- ``dem_tolerance``) when there is one."""
    sel = np.ones(len(ties.height), bool) if whole else ties.inside(box, bbox)
    search, why = None, None
    if sel.sum() >= MIN_TIE_POINTS:
        search, why = search_heights(ties.height[sel]), f"{int(sel.sum())} tie points in the tile"
    elif len(ties.height) >= MIN_TIE_POINTS:
        search = search_heights(ties.height)
        why = f"the whole pair's {len(ties.height)} tie points (only {int(sel.sum())} in the tile)"
    if dem is not None:
        lo, hi = _dem_range(a, box, dem)
        lo, hi = lo - dem_tolerance, hi + dem_tolerance
        if search is not None and max(lo, search[0]) < min(hi, search[1]):
            search, why = (max(lo, search[0]), min(hi, search[1])), f"{why}, within the DEM's {lo:.0f}..{hi:.0f} m"
        else:
            search, why = (lo, hi), f"the DEM under the tile, {lo:.0f}..{hi:.0f} m (+-{dem_tolerance:g} m)"
    return search, why


def _dem_range(a: RPCCamera, box, dem) -> tuple[float, float]:
    """Lowest and highest DEM height under a tile of ``a`` (a 9 x 9 grid of its pixels,
    each localised at the DEM height found under it at the previous step)."""
    c0, r0, c1, r1 = (float(v) for v in box)
    rows, cols = (g.ravel() for g in np.meshgrid(np.linspace(r0, r1 - 1, 9), np.linspace(c0, c1 - 1, 9), indexing="ij"))
    to_dem = pyproj.Transformer.from_crs(4326, dem.crs, always_xy=True)
    h = np.full(rows.shape, float(np.nanmedian(dem.data)))
    for _ in range(3):
        lon, lat = a.localize(rows, cols, h)
        z = dem.sample(*to_dem.transform(lon, lat))
        h = np.where(np.isfinite(z), z, h)
    if not np.isfinite(z).any():
        raise InputError(f"{a.name}: the DEM does not cover the tile at pixels {[int(v) for v in box]}")
    return float(np.nanmin(z)), float(np.nanmax(z))


def _tile_points(a, b, image_a, image_b, core, box, frame, ties, whole_shift, *,
                 search, engine: str = "census", floor: float = -np.inf, model: BiasModel | None = None,
                 limit: tuple[float, float] | None = None, checked: TiePoints | None = None):
    """Rectify, match and intersect one tile; the points of its core.

    Parameters
    ----------
    core, box : (4,) int
        The tile's core and box (col0, row0, col1, row1) in ``a``'s crop.
    frame : (RPCCamera, RPCCamera, (4,) int)
        :func:`_tile_frame` of the tile.
    ties : ((m, 2) float, (m, 2) float)
        The whole pair's tie points (col, row) in ``a`` and ``b``.
    whole_shift : (2,) float or None
        The whole pair's bias, used when the tile has too few tie points (None: unknown).
    search : (float, float)
        Heights to search (m).
    engine : str
    floor : float
        Points lower than this (m) are dropped.
    model : BiasModel or None
        The pair's bias model: the tile's bias where its own ties are too few or
        disagree with it (None: ``whole_shift``).
    limit : (float, float) or None
        The heights of the whole pair, searched when the tile's disparities pile up at
        an end of ``search`` (see :func:`_widened`); ``pair.heights`` is what was searched.
    checked : TiePoints or None
        The pair's tie points: those in the core are compared with the dense
        disparities (``pair.tie_check``: (k,) absolute differences, px, where matched).

    Returns
    -------
    piece : tuple of five (n,) arrays
        lon, lat (degrees), ellipsoidal height (m), matching confidence and observed
        (True: matched, False: filled in) of the tile's core points whose match lies on
        b's data, in the matcher's (row-major rectified) order.
    pair : SatellitePair
    matched, overlap : int
        Rectified pixels of the core whose match falls on b's data (the overlap), and
        those of them matched rather than filled in.

    Raises
    ------
    InputError
        When the tile has no overlap, no texture or no match.
    """
    from recon3d.stereo.match import MatchParams, match

    sa, sb, bbox = frame
    whole = sa is a
    c0, r0, c1, r1 = (int(v) for v in box)
    tile_a = image_a[r0:r1, c0:c1]
    tile_b = image_b[bbox[1] : bbox[3], bbox[0] : bbox[2]]
    for name, img in ((sa.name, tile_a), (sb.name, tile_b)):
        v = img[np.isfinite(img)]
        if v.size < 0.1 * img.size or v.size == 0 or float(v.max() - v.min()) <= 0:
            raise InputError(f"{name}: no texture (no data or constant)")
    t1, t2 = ties
    sel = (
        (t1[:, 0] >= c0) & (t1[:, 0] < c1) & (t1[:, 1] >= r0) & (t1[:, 1] < r1)
        & (t2[:, 0] >= bbox[0]) & (t2[:, 0] < bbox[2]) & (t2[:, 1] >= bbox[1]) & (t2[:, 1] < bbox[3])
    )
    local_ties = (t1[sel] - [c0, r0], t2[sel] - bbox[:2])
    local_core = np.asarray(core) - [c0, r0, c0, r0]
    fallback = whole_shift if model is None or whole else model.at(0.5 * (c0 + c1), 0.5 * (r0 + r1))
    pair = rectify_rpc_pair(sa, sb, tile_a, tile_b, ties=local_ties, core=None if whole else local_core,
                            fallback_shift=fallback, heights=search)
    while True:
        lo, hi = pair.disparity_range
        params = MatchParams(min_disparity=lo, max_disparity=hi + 1, engine=engine,
                             intensity_weight=SATELLITE_INTENSITY_WEIGHT)
        result = match(pair.left, pair.right, params)
        wider = _widened(result.disparity, lo, hi, search, limit)
        if wider == search:
            break
        log.info("RPC pair %s-%s: the surface reaches the searched heights' end; %s -> %s m",
                 sa.name, sb.name, np.round(search, 1).tolist(), np.round(wider, 1).tolist())
        search = wider  # the rectification stands: only the disparities to search grow
        pair = dataclasses.replace(pair, heights=wider,
                                   disparity_range=_search_range(sa, sb, pair.A1, pair.A2, pair.shift, wider))
    pair.tie_check = _tie_check(pair, result, checked, core, box, bbox, a)
    y, x = np.nonzero(np.isfinite(result.disparity))
    d = result.disparity[y, x]
    matched = ~result.filled[y, x] if result.filled is not None else np.ones(len(d), bool)
    p1 = _apply(_invert(pair.A1), np.column_stack([x, y]).astype(float)) + [c0, r0]
    p2_image = _apply(_invert(pair.A2), np.column_stack([x - d, y]).astype(float)) + bbox[:2]
    # the overlap: core pixels whose match (found or filled in) falls on b's data
    inside = _in_core(p1, core, a.width, a.height) & _on_data(image_b, p2_image)
    counts = int(np.count_nonzero(matched & inside)), int(np.count_nonzero(inside))
    p1, p2 = p1[inside], p2_image[inside] - pair.shift
    conf, matched = result.confidence[y[inside], x[inside]], matched[inside]
    h = _intersect(a, b, p1, p2, *pair.heights)
    lon, lat = a.localize(p1[:, 1], p1[:, 0], h)
    ok = np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h) & (h >= floor)
    if not ok.any():
        raise InputError(f"{sa.name}: nothing matched")
    return (lon[ok], lat[ok], h[ok], conf[ok], matched[ok]), pair, counts


def _tie_check(pair: SatellitePair, result, ties: TiePoints | None, core, box, bbox, a: RPCCamera) -> np.ndarray:
    """(k,) |dense - tie| disparity (px) at the tile core's tie points where the pixel was matched.

    The tie points' disparities come from SIFT, independently of the dense matcher: a
    dense map that disagrees with them by pixels is wrong, whatever its own checks say.
    """
    if ties is None or len(ties.height) == 0:
        return np.zeros(0)
    c0, r0 = int(box[0]), int(box[1])
    sel = ties.inside(core, bbox) & _in_core(ties.left, core, a.width, a.height)
    q1 = _apply(pair.A1, ties.left[sel] - [c0, r0])
    q2 = _apply(pair.A2, ties.right[sel] - bbox[:2])
    col, row = np.rint(q1[:, 0]).astype(np.int64), np.rint(q1[:, 1]).astype(np.int64)
    h, w = result.disparity.shape
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    dense = np.full(len(q1), np.nan)
    dense[ok] = result.disparity[row[ok], col[ok]]
    if result.filled is not None:
        dense[ok] = np.where(result.filled[row[ok], col[ok]], np.nan, dense[ok])
    diff = np.abs(dense - (q1[:, 0] - q2[:, 0]))
    return diff[np.isfinite(diff)]


#: Self-check against the tie points: a median difference (px) above this between the
#: dense disparities and the tie points' stops the run; fewer than
#: ``TIE_CHECK_WITHIN_1PX`` percent within 1 px gives a warning.
TIE_CHECK_MAX_MEDIAN_PX = 2.0
TIE_CHECK_WITHIN_1PX = 80.0


def tie_self_check(diffs: np.ndarray, metres_per_px: float, names: str) -> tuple[dict, str | None]:
    """Summary of the dense-vs-tie disparity differences, and a warning (or None).

    Raises
    ------
    InputError
        When at least 20 tie points were matched and their median difference exceeds
        :data:`TIE_CHECK_MAX_MEDIAN_PX`: the dense surface contradicts the pair's own
        tie points (wrong rectification, bias or matching).
    """
    if diffs.size == 0:
        return {"tie_points": 0}, f"images {names}: no tie point fell on a matched pixel; the dense result is unchecked"
    med = float(np.median(diffs))
    check = {
        "tie_points": int(diffs.size),
        "median_px": round(med, 3),
        "p90_px": round(float(np.percentile(diffs, 90)), 3),
        "median_m": round(med * metres_per_px, 3),
        "within_1px_percent": round(100.0 * float(np.mean(diffs <= 1.0)), 1),
    }
    if diffs.size >= 20 and med > TIE_CHECK_MAX_MEDIAN_PX:
        raise InputError(
            f"images {names}: the dense disparities differ from the {diffs.size} tie points' by {med:.1f} px "
            f"(median, limit {TIE_CHECK_MAX_MEDIAN_PX} px, {check['median_m']:.1f} m): the matching contradicts the "
            "pair's own tie points"
        )
    if check["within_1px_percent"] < TIE_CHECK_WITHIN_1PX:
        return check, (f"images {names}: only {check['within_1px_percent']:.0f} % of {diffs.size} tie points lie within "
                       f"1 px of the dense disparities (expected >= {TIE_CHECK_WITHIN_1PX:.0f} %)")
    return check, None


#: Weight of the census engine's intensity term on satellite images (1 on frame images).
#: Panchromatic 11/12-bit images stretched to 0..255 carry several grey levels of noise
#: between the two dates' pixels, which the intensity term adds to every cost while the
#: census bits ignore it: on the synthetic mountain, town and desert pairs 0.5 matched
#: 88, 93 and 97 % of the overlap (1: 85, 91, 92 %; 0: 88, 93, 99 % but roofs 0.55 m
#: instead of 0.48 m), at the same NMAD.
SATELLITE_INTENSITY_WEIGHT = 0.5

#: Share of a tile's disparities within a pixel and a half of an end of the searched
#: range above which the surface is taken to reach beyond it.
AT_END_SHARE = 0.01


def _widened(disparity: np.ndarray, lo: int, hi: int, search, limit) -> tuple[float, float]:
    """The heights to search again: ``limit`` (the whole pair's) joined to ``search``
    when more than :data:`AT_END_SHARE` of the disparities pile up against an end of
    the range ``lo..hi`` (a valley or a peak the tile's tie points missed); ``search``
    itself when they do not."""
    d = disparity[np.isfinite(disparity)]
    if d.size == 0 or limit is None:
        return search
    at_lo, at_hi = np.mean(d <= lo + 1.5), np.mean(d >= hi - 1.5)
    if max(at_lo, at_hi) <= AT_END_SHARE:
        return search
    return (min(search[0], limit[0]), max(search[1], limit[1]))


def _on_data(image: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(k,) bool: pixels p (k, 2) (col, row) that fall on a finite pixel of ``image``."""
    col, row = np.rint(p[:, 0]).astype(np.int64), np.rint(p[:, 1]).astype(np.int64)
    h, w = image.shape[:2]
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    ok[ok] = np.isfinite(image[row[ok], col[ok]])
    return ok


def _invert(A: np.ndarray) -> np.ndarray:
    M = np.linalg.inv(A[:, :2])
    return np.column_stack([M, -M @ A[:, 2]])


def _intersect(a: RPCCamera, b: RPCCamera, p1: np.ndarray, p2: np.ndarray, h0: float, h1: float, steps: int = 2) -> np.ndarray:
    """Height at which a's pixel p1 projects onto b's pixel p2 (secant steps along the epipolar line)."""
    ha = np.full(len(p1), h0)
    hb = np.full(len(p1), h1)
    for _ in range(steps + 1):
        qa = _lift(a, b, p1, ha)
        qb = _lift(a, b, p1, hb)
        dq = qb - qa
        t = np.einsum("ij,ij->i", p2 - qa, dq) / np.maximum(np.einsum("ij,ij->i", dq, dq), 1e-12)
        h = ha + t * (hb - ha)
        ha, hb = h - 2.0, h + 2.0
    return h


def _lift(a: RPCCamera, b: RPCCamera, p1: np.ndarray, h: np.ndarray) -> np.ndarray:
    lon, lat = a.localize(p1[:, 1], p1[:, 0], h)
    r, c = b.project(lon, lat, h)
    return np.column_stack([c, r])


def absolute_shift(cloud: PointCloud, gcps: np.ndarray, *, search: float = 5.0, step: float = 0.5) -> tuple[np.ndarray, dict]:
    """Translation that brings the cloud onto ground control points (the RPCs' absolute bias).

    An RPC pair's absolute error is close to a constant shift on the ground. With 3-D
    control points only (no image measurements), the horizontal part is found by
    sliding the points over the cloud's surface (median height per 1 m column, a grid
    search within ``search`` metres) to the position where the height residuals agree
    best; the vertical part is then their median. Points on sloped or built ground
    carry the horizontal information; on flat ground only the height is recovered.

    Parameters
    ----------
    cloud : PointCloud
        Metric CRS.
    gcps : (m, 3) float
        Control points in the cloud's CRS.

    Returns
    -------
    shift : (3,) float
        To add to the cloud's coordinates.
    report : dict
    """
    from recon3d.core.raster import Raster, grid_for_bounds
    from recon3d.terrain.dsm import grid_points

    if len(gcps) < 3:
        raise InputError(f"{len(gcps)} ground control points; at least 3 are needed to estimate the bias")
    lo, hi = cloud.bounds
    transform, shape = grid_for_bounds(lo[0], lo[1], hi[0], hi[1], 1.0)
    surface = Raster(grid_points(cloud.xyz, transform, shape, reducer="mean"), transform)
    offsets = np.arange(-search, search + step / 2, step)
    best = (np.inf, 0.0, 0.0, 0.0)
    for dx in offsets:  # a small grid of shifts, each vectorised over the points
        for dy in offsets:
            dz = gcps[:, 2] - surface.sample(gcps[:, 0] - dx, gcps[:, 1] - dy)
            ok = np.isfinite(dz)
            if ok.sum() < 3:
                continue
            med = float(np.median(dz[ok]))
            spread = float(np.median(np.abs(dz[ok] - med)))
            if spread < best[0] - 1e-9:
                best = (spread, dx, dy, med)
    if not np.isfinite(best[0]):
        raise InputError("the ground control points do not fall on the reconstructed surface")
    shift = np.array(best[1:])
    report = {"shift_m": np.round(shift, 3).tolist(), "residual_mad_m": round(best[0], 3), "gcps": int(len(gcps))}
    log.info("absolute bias from %d GCPs: %s m", len(gcps), report["shift_m"])
    return shift, report
