"""Footprints given by the user, aligned with the data.

:func:`align_footprints` estimates the map-to-data shift of each footprint (up to
``footprint_shift``) against the building evidence of the nDSM, and reports the
footprints that have no data or no building under them.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import rasterio.features
import shapely
from affine import Affine

from recon3d.buildings import outline as outline_mod
from recon3d.core.raster import Raster

log = logging.getLogger(__name__)

__all__ = ["align_footprints"]


def align_footprints(
    polygons: list[shapely.Polygon],
    evidence: Raster,
    max_shift: float,
    *,
    per_footprint: bool = True,
    min_gain: float = 0.05,
) -> tuple[list[shapely.Polygon], np.ndarray, np.ndarray]:
    """Shift given footprints onto the buildings seen in the data.

    The footprints are sampled on a grid of half a cell; for every shift on a grid of
    half a cell within ``max_shift`` (a disc), each footprint scores the sum of
    (2 evidence - 1) under its shifted samples (cross-correlation of the rasterised
    footprints with the building mask, non-building cells counting against). The best
    common shift (refined to sub-step by a parabola) moves every footprint; with
    ``per_footprint``, a footprint whose own best shift within ``max_shift`` raises the
    share of its samples on building cells by more than ``min_gain`` takes it instead
    (maps digitised from orthophotos shift each building by its own lean).

    Parameters
    ----------
    polygons : list of shapely.Polygon
        Footprints in the evidence's CRS; invalid ones are repaired (largest part).
    evidence : Raster
        1 on building cells, 0 elsewhere, NaN without data (:func:`building_evidence`).
    max_shift : float
        Largest shift (CRS units).
    per_footprint : bool
    min_gain : float

    Returns
    -------
    shifted : list of shapely.Polygon
        The footprints moved (an empty polygon stays empty).
    shift : (n, 2) float
        Shift applied to each footprint (x, y), CRS units.
    support : (n,) float
        Share of each shifted footprint's samples with data that fall on building cells;
        NaN when the footprint has no data under it (outside the cloud, or a hole), a low
        value when no building stands there (demolished, or a wrong footprint).
    """
    n = len(polygons)
    shifts = np.zeros((n, 2))
    support = np.full(n, np.nan)
    if n == 0:
        return [], shifts, support
    step = evidence.resolution / 2
    polys = [outline_mod._valid_polygon(p) for p in polygons]
    fid, px, py = _footprint_samples(polys, evidence, step)
    r = int(math.floor(max_shift / step + 1e-9))
    grid = np.arange(-r, r + 1) * step
    sx, sy = np.meshgrid(grid, grid)
    disc = np.hypot(sx, sy) <= max_shift + 1e-9
    cand = np.column_stack([sx[disc], sy[disc]])
    scores = np.zeros((len(cand), n))  # sum of (2 e - 1) per footprint and shift
    hits = np.zeros((len(cand), n))  # building samples
    valid = np.zeros((len(cand), n))  # samples with data
    for k, (dx, dy) in enumerate(cand):
        e = evidence.sample(px + dx, py + dy, bilinear=False) if len(px) else np.zeros(0)
        ok = np.isfinite(e)
        scores[k] = np.bincount(fid[ok], weights=2 * e[ok] - 1, minlength=n)
        hits[k] = np.bincount(fid[ok], weights=e[ok], minlength=n)
        valid[k] = np.bincount(fid[ok], minlength=n)
    total = scores.sum(axis=1)
    best = int(np.argmax(total))
    zero = int(np.flatnonzero((cand[:, 0] == 0) & (cand[:, 1] == 0))[0])
    if total[best] <= total[zero]:
        best = zero
    shift = cand[best] + _parabolic(cand, total, best, step)
    if np.hypot(*shift) > max_shift:
        shift *= max_shift / np.hypot(*shift)
    shifts[:] = shift
    chosen = np.full(n, best)
    if per_footprint:
        with np.errstate(invalid="ignore", divide="ignore"):
            share = hits / valid
        own = np.argmax(scores, axis=0)
        gain = share[own, np.arange(n)] - share[best, np.arange(n)]
        better = np.nan_to_num(gain) > min_gain
        chosen[better] = own[better]
        shifts[better] = cand[own[better]]
    with np.errstate(invalid="ignore", divide="ignore"):
        support = hits[chosen, np.arange(n)] / valid[chosen, np.arange(n)]
    support[valid[chosen, np.arange(n)] == 0] = np.nan
    shifted = []
    for p, (dx, dy) in zip(polys, shifts, strict=True):
        shifted.append(shapely.affinity.translate(p, dx, dy) if p is not None else shapely.Polygon())
    log.info(
        "footprints shifted by (%.2f, %.2f); %d moved on their own; %d without data, %d without building",
        shift[0], shift[1], int((chosen != best).sum()), int(np.isnan(support).sum()),
        int((np.nan_to_num(support, nan=1.0) < 0.5).sum()),
    )
    return shifted, shifts, support


def _footprint_samples(
    polys: list[shapely.Polygon | None], grid: Raster, step: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample points (footprint index, x, y) on a grid of ``step`` inside each footprint."""
    west, south, east, north = grid.bounds
    pad = 2 * step
    cols = int(math.ceil((east - west + 2 * pad) / step))
    rows = int(math.ceil((north - south + 2 * pad) / step))
    transform = Affine(step, 0.0, west - pad, 0.0, -step, north + pad)
    shapes = [(p, i + 1) for i, p in enumerate(polys) if p is not None and not p.is_empty]
    if not shapes:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    fids, xs, ys = [], [], []
    # rasterise one footprint at a time: overlapping footprints each keep all their samples
    for p, v in shapes:
        minx, miny, maxx, maxy = p.bounds
        c0 = max(int((minx - transform.c) / step) - 1, 0)
        r0 = max(int((transform.f - maxy) / step) - 1, 0)
        c1 = min(int((maxx - transform.c) / step) + 2, cols)
        r1 = min(int((transform.f - miny) / step) + 2, rows)
        if c1 <= c0 or r1 <= r0:
            continue
        sub = transform @ Affine.translation(c0, r0)
        m = rasterio.features.rasterize([(p, 1)], out_shape=(r1 - r0, c1 - c0), transform=sub, fill=0, dtype="uint8")
        rr, cc = np.nonzero(m)
        if len(rr):
            x, y = sub.c + (cc + 0.5) * step, sub.f - (rr + 0.5) * step
        else:  # thinner than a sample step: one sample inside it
            x, y = (np.array([v]) for v in p.representative_point().coords[0])
        fids.append(np.full(len(x), v - 1))
        xs.append(x)
        ys.append(y)
    if not fids:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    return np.concatenate(fids).astype(np.int64), np.concatenate(xs), np.concatenate(ys)


def _parabolic(cand: np.ndarray, total: np.ndarray, best: int, step: float) -> np.ndarray:
    """Sub-step offset of a peak from parabolas through its neighbours along x and y."""
    out = np.zeros(2)
    for axis in (0, 1):
        offsets = []
        for sign in (-1, 1):
            target = cand[best].copy()
            target[axis] += sign * step
            k = np.flatnonzero(np.all(np.isclose(cand, target), axis=1))
            offsets.append(total[k[0]] if len(k) else None)
        lo, hi = offsets
        if lo is None or hi is None:
            continue
        denom = lo - 2 * total[best] + hi
        if denom < 0:
            out[axis] = float(np.clip(0.5 * (lo - hi) / denom * step, -step / 2, step / 2))
    return out
