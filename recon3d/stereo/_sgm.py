"""Compiled kernels of the census engine (numba): cost volume, SGM aggregation, selection.

Volumes are (rows, cols, disparities), disparity innermost, so that every inner loop
runs over contiguous memory and compiles to SIMD code. Each ``prange`` iteration writes
its own rows or pixels only and all arithmetic is integer or plain IEEE float32 (no
``fastmath``): the bytes out do not depend on the number of threads. Compiled once and
cached on disk (``cache=True``), in numba's cache folder beside this file or in
``NUMBA_CACHE_DIR``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange, types
from numba.extending import intrinsic

_TOP = 65535  # uint16 maximum: "no candidate"


@intrinsic
def _popcount(typingctx, x):
    """Number of set bits of a uint64 (LLVM ``ctpop``: one POPCNT instruction)."""
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return sig, codegen


@njit(cache=True, parallel=True)
def census(padded, a, b, wy, wx):
    """Census bit strings (uint64) of rows a..b of the unpadded image.

    ``padded`` is the image with ``wy // 2`` rows and ``wx // 2`` columns of border;
    bit k is set where the k-th window neighbour (row-major, centre skipped) is darker
    than the centre.
    """
    ry, rx = wy // 2, wx // 2
    h, w = b - a, padded.shape[1] - 2 * rx
    out = np.zeros((h, w), np.uint64)
    for y in prange(h):
        for x in range(w):
            centre = padded[a + y + ry, x + rx]
            bits = np.uint64(0)
            bit = np.uint64(0)
            for dy in range(wy):
                for dx in range(wx):
                    if dy == ry and dx == rx:
                        continue
                    if padded[a + y + dy, x + dx] < centre:
                        bits |= np.uint64(1) << bit
                    bit += np.uint64(1)
            out[y, x] = bits
    return out


@njit(cache=True, parallel=True)
def cost_volume(cl, cr, l8, rmin, rmax, dmin, use_bt, trunc8, weight, cap, out):
    """Fill ``out`` (rows, cols, D) uint8 with census Hamming distance + truncated BT cost.

    Disparity index i is ``dmin + i``; right columns ``x - d`` outside the image take
    the edge column. The BT term is ``min(max(rmin - l, l - rmax, 0), trunc8)``, times
    ``weight`` (rounded half to even) when it is not 1, capped at ``cap``.
    """
    for y in prange(out.shape[0]):
        _cost_row(cl[y], cr[y], l8[y], rmin[y], rmax[y], dmin, use_bt, trunc8, weight, cap, out[y])


@njit(cache=True)
def _reversed_padded(row, first, length):
    """``out[j] = row[clip(first - j, 0, len(row) - 1)]`` for j < length: the right row
    read backwards, so that successive disparities of one left pixel are contiguous."""
    out = np.empty(length, row.dtype)
    last = row.shape[0] - 1
    for j in range(length):
        out[j] = row[min(max(first - j, 0), last)]
    return out


@njit(cache=True)
def _cost_row(cl, cr, l8, rmin, rmax, dmin, use_bt, trunc8, weight, cap, out):
    w, ndisp = out.shape
    # column x - dmin - i of the right row is entry (w - 1 - x) + i of the reversed rows
    first, length = w - 1 - dmin, w + ndisp
    rev_bits = _reversed_padded(cr, first, length)
    rev_min = _reversed_padded(rmin, first, length)
    rev_max = _reversed_padded(rmax, first, length)
    for x in range(w):
        base = w - 1 - x
        left_bits = cl[x]
        lv = np.int32(l8[x])
        o = out[x]
        for i in range(ndisp):
            o[i] = np.uint8(_popcount(left_bits ^ rev_bits[base + i]))
        if not use_bt:
            continue
        for i in range(ndisp):
            bt = max(np.int32(rev_min[base + i]) - lv, lv - np.int32(rev_max[base + i]), np.int32(0))
            bt = min(bt, trunc8)
            if weight != 1.0:
                bt = min(np.int32(np.rint(np.float32(bt) * weight)), np.int32(255))
            o[i] = np.uint8(np.int32(o[i]) + min(bt, cap))


@njit(cache=True, parallel=True)
def penalise_outside(cost, first, last, penalty):
    """Raise, in place, the cost of disparity indices outside ``first..last`` of each
    pixel by ``penalty`` (saturating at 255). All (rows, cols) but ``cost``."""
    h, w, ndisp = cost.shape
    for y in prange(h):
        for x in range(w):
            p = np.int32(penalty[y, x])
            if p == 0:
                continue
            for i in range(ndisp):
                if i < first[y, x] or i > last[y, x]:
                    cost[y, x, i] = np.uint8(min(np.int32(cost[y, x, i]) + p, 255))


@njit(cache=True)
def _penalty(g_here, g_before, p2, p2_min, gscale):
    """Adaptive P2 between two neighbours on a path (float32 arithmetic, truncated)."""
    if gscale <= 0:
        return np.int32(p2)
    step = np.abs(g_here - g_before)
    pen = np.float32(p2) / (np.float32(1.0) + step / np.float32(gscale))
    pen = max(pen, np.float32(p2_min))
    return np.int32(pen)


@njit(cache=True)
def _path_step(prev, prev_min, c, p1, jump, out):
    """One SGM step: ``out`` = L(p, .) from the previous path cost ``prev`` (its minimum
    ``prev_min``), the matching cost ``c`` and the big-jump cost ``prev_min + P2``.

    Returns min(out). All (D,) arrays; uint16 in and out.
    """
    ndisp = c.shape[0]
    best = np.int32(_TOP)
    if ndisp == 1:
        v = min(np.int32(prev[0]), jump) - prev_min + np.int32(c[0])
        out[0] = np.uint16(v)
        return v
    v = min(np.int32(prev[0]), np.int32(prev[1]) + p1, jump) - prev_min + np.int32(c[0])
    out[0] = np.uint16(v)
    best = min(best, v)
    for d in range(1, ndisp - 1):
        v = min(np.int32(prev[d]), min(np.int32(prev[d - 1]), np.int32(prev[d + 1])) + p1, jump)
        v = v - prev_min + np.int32(c[d])
        out[d] = np.uint16(v)
        best = min(best, v)
    last = ndisp - 1
    v = min(np.int32(prev[last]), np.int32(prev[last - 1]) + p1, jump) - prev_min + np.int32(c[last])
    out[last] = np.uint16(v)
    return min(best, v)


@njit(cache=True)
def _start(c, out):
    """A path entering the image: L = C. Returns min(C)."""
    best = np.int32(_TOP)
    for d in range(c.shape[0]):
        out[d] = np.uint16(c[d])
        best = min(best, np.int32(c[d]))
    return best


@njit(cache=True)
def _horizontal_row(cost, guide, p1, p2, p2_min, gscale, row):
    """``row`` (cols, D) = the left-to-right plus the right-to-left path costs of one row."""
    w, ndisp = cost.shape
    prev = np.empty(ndisp, np.uint16)
    cur = np.empty(ndisp, np.uint16)
    for direction in range(2):
        m = np.int32(0)
        for step in range(w):
            x = step if direction == 0 else w - 1 - step
            if step == 0:
                m = _start(cost[x], cur)
            else:
                q = x - 1 if direction == 0 else x + 1
                jump = m + _penalty(guide[x], guide[q], p2, p2_min, gscale)
                m = _path_step(prev, m, cost[x], p1, jump, cur)
            out = row[x]
            if direction == 0:
                for d in range(ndisp):
                    out[d] = cur[d]
            else:
                for d in range(ndisp):
                    out[d] += cur[d]
            prev, cur = cur, prev


@njit(cache=True, parallel=True)
def _horizontal(cost, guide, p1, p2, p2_min, gscale, total):
    """``total`` = the left-to-right plus the right-to-left path costs (assigns)."""
    for y in prange(cost.shape[0]):
        _horizontal_row(cost[y], guide[y], p1, p2, p2_min, gscale, total[y])


@njit(cache=True, parallel=True)
def _vertical_row(cost, guide, y, dy, dxs, p1, p2, p2_min, gscale, prev, prev_min, cur, cur_min, total):
    """One row of the sweeps along rows (direction ``dy``, column steps ``dxs``): path
    costs of row y from those of row y - dy (``prev``: (len(dxs), cols, D)), added to
    ``total``. The first row of the sweep starts every path."""
    h, w, ndisp = cost.shape
    first = (y == 0) if dy > 0 else (y == h - 1)
    for x in prange(w):
        c = cost[y, x]
        out = total[y, x]
        for j in range(dxs.shape[0]):
            xq = x - dxs[j]
            if first or xq < 0 or xq >= w:
                cur_min[j, x] = _start(c, cur[j, x])
            else:
                pm = prev_min[j, xq]
                jump = pm + _penalty(guide[y, x], guide[y - dy, xq], p2, p2_min, gscale)
                cur_min[j, x] = _path_step(prev[j, xq], pm, c, p1, jump, cur[j, x])
        if dxs.shape[0] == 3:  # one read-modify-write of the total for the three paths
            a, b, e = cur[0, x], cur[1, x], cur[2, x]
            for d in range(ndisp):
                out[d] += a[d] + b[d] + e[d]
        else:
            for j in range(dxs.shape[0]):
                a = cur[j, x]
                for d in range(ndisp):
                    out[d] += a[d]


@njit(cache=True)
def _vertical(cost, guide, dy, dxs, p1, p2, p2_min, gscale, total):
    h, w, ndisp = cost.shape
    k = dxs.shape[0]
    prev = np.empty((k, w, ndisp), np.uint16)
    cur = np.empty((k, w, ndisp), np.uint16)
    prev_min = np.empty((k, w), np.int32)
    cur_min = np.empty((k, w), np.int32)
    for step in range(h):
        y = step if dy > 0 else h - 1 - step
        _vertical_row(cost, guide, y, dy, dxs, p1, p2, p2_min, gscale, prev, prev_min, cur, cur_min, total)
        prev, cur = cur, prev
        prev_min, cur_min = cur_min, prev_min


def aggregate(cost, guide, p1, p2, p2_min, gscale, paths, total):
    """Sum over scanline directions of the SGM path costs, into ``total`` (assigned).

    L(p, d) = C(p, d) + min(L(q, d), L(q, d +- 1) + P1, min_k L(q, k) + P2(p, q)) - min_k L(q, k)
    with q = p - r the previous pixel on the path; paths entering from outside the image
    start afresh (L = C). P2(p, q) = max(P2 / (1 + |I(p) - I(q)| / gscale), p2_min).
    Each path cost is at most max(C) + P2 <= 255 + P2: 8 paths fit in uint16 for P2 < 7900.

    Parameters
    ----------
    cost : (rows, cols, D) uint8
    guide : (rows, cols) float32
        Intensity (0..255) that lowers P2 across edges.
    paths : {4, 8}
    total : (rows, cols, D) uint16
        Output.
    """
    args = (np.int32(p1), np.int32(p2), np.int32(p2_min), np.float32(gscale))
    _horizontal(cost, guide, *args[:3], args[3], total)
    dxs = np.array([0, 1, -1] if paths == 8 else [0], np.int64)
    for dy in (1, -1):
        _vertical(cost, guide, dy, dxs, *args, total)


@njit(cache=True, parallel=True)
def select(total, dmin, subpixel, uniqueness):
    """Winner-takes-all over the aggregated costs, per pixel.

    Returns
    -------
    disp : (rows, cols) float32
        ``dmin`` + index of the first minimum, plus the parabola offset (clipped to
        +-0.5) when ``subpixel``; NaN where the uniqueness test (percent, 0 = off) fails.
    margin : (rows, cols) float32
        (second best - best) / second best in [0, 1], the second best taken outside
        the winner's +-1 neighbourhood (the best itself when there is none).
    right : (rows, cols) float32
        Right-image disparity (whole pixels): argmin over d of total(y, xr + d, d),
        the smallest d among equals; NaN where no left pixel maps to xr.
    """
    h, w, ndisp = total.shape
    disp = np.empty((h, w), np.float32)
    margin = np.empty((h, w), np.float32)
    right = np.empty((h, w), np.float32)
    for y in prange(h):
        _select_row(total[y], dmin, subpixel, uniqueness, disp[y], margin[y])
        _right_row(total[y], dmin, right[y])
    return disp, margin, right


@njit(cache=True)
def _select_row(t_row, dmin, subpixel, uniqueness, disp, margin):
    w, ndisp = t_row.shape
    for x in range(w):
        t = t_row[x]
        best, bi = np.int32(t[0]), 0
        for i in range(1, ndisp):
            if np.int32(t[i]) < best:
                best, bi = np.int32(t[i]), i
        bestf = np.float32(best)
        value = np.float32(bi + dmin)
        if subpixel and ndisp >= 3 and 0 < bi < ndisp - 1:
            cm, cp = np.float32(t[bi - 1]), np.float32(t[bi + 1])
            den = cm + cp - np.float32(2.0) * bestf
            if den > 0:
                offset = (cm - cp) / (np.float32(2.0) * den)
                value += min(max(offset, np.float32(-0.5)), np.float32(0.5))
        second = np.int32(_TOP)
        for i in range(ndisp):
            if (i < bi - 1 or i > bi + 1) and np.int32(t[i]) < second:
                second = np.int32(t[i])
        secondf = bestf if second == _TOP else np.float32(second)
        ratio = (secondf - bestf) / max(secondf, np.float32(1.0))
        margin[x] = min(max(ratio, np.float32(0.0)), np.float32(1.0))
        if uniqueness > 0 and not (secondf * np.float32(100.0) > bestf * np.float32(100.0 + uniqueness)):
            value = np.float32(np.nan)
        disp[x] = value


@njit(cache=True)
def _right_row(t_row, dmin, right):
    w, ndisp = t_row.shape
    for xr in range(w):
        best, arg = np.int32(_TOP), np.float32(np.nan)
        for i in range(ndisp):
            x = xr + dmin + i
            if 0 <= x < w and np.int32(t_row[x, i]) < best:
                best, arg = np.int32(t_row[x, i]), np.float32(dmin + i)
        right[xr] = arg
