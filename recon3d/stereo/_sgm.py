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
    rx = wx // 2
    h, w = b - a, padded.shape[1] - 2 * rx
    out = np.zeros((h, w), np.uint64)
    for y in prange(h):
        _census_row(padded, a + y, wy, wx, out[y])
    return out


@njit(cache=True)
def _census_row(padded, y, wy, wx, out):
    ry, rx = wy // 2, wx // 2
    w = out.shape[0]
    centre = padded[y + ry, rx : rx + w]
    bit = np.uint64(0)
    for dy in range(wy):
        for dx in range(wx):
            if dy == ry and dx == rx:
                continue
            other = padded[y + dy, dx : dx + w]
            for x in range(w):  # one neighbour for the whole row: SIMD
                if other[x] < centre[x]:
                    out[x] |= np.uint64(1) << bit
            bit += np.uint64(1)


@njit(cache=True, parallel=True)
def census_slanted(image, wy, wx, gx, gy):
    """Census bit strings (uint64) of a window sheared for a slanted surface.

    The neighbour at row offset ``dy`` and column offset ``dx`` is read at column
    ``x + dx * (1 - gx) - gy * dy`` (linear interpolation along the row, edge columns
    and rows repeated): the window of the other image seen on a surface whose disparity
    grows by ``gx`` per column and ``gy`` per row. Same bit order as :func:`census`.
    """
    h, w = image.shape
    ry, rx = wy // 2, wx // 2
    out = np.zeros((h, w), np.uint64)
    for y in prange(h):
        bit = np.uint64(0)
        for dy in range(-ry, ry + 1):
            yy = min(max(y + dy, 0), h - 1)
            for dx in range(-rx, rx + 1):
                if dy == 0 and dx == 0:
                    continue
                shift = np.float32(dx) * (np.float32(1.0) - gx) - gy * np.float32(dy)
                for x in range(w):
                    xf = min(max(np.float32(x) + shift, np.float32(0.0)), np.float32(w - 1))
                    x0 = int(xf)
                    f = xf - np.float32(x0)
                    x1 = min(x0 + 1, w - 1)
                    v = image[yy, x0] * (np.float32(1.0) - f) + image[yy, x1] * f
                    if v < image[y, x]:
                        out[y, x] |= np.uint64(1) << bit
                bit += np.uint64(1)
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
        # slices, not base + i indices: numba then knows them non-negative, and vectorises
        base = w - 1 - x
        bits = rev_bits[base : base + ndisp]
        r_lo = rev_min[base : base + ndisp]
        r_hi = rev_max[base : base + ndisp]
        left_bits = cl[x]
        lv = np.int32(l8[x])
        o = out[x]
        if not use_bt:
            for i in range(ndisp):
                o[i] = np.uint8(_popcount(left_bits ^ bits[i]))
        elif weight == 1.0:  # the default, in a loop simple enough for SIMD
            limit = min(trunc8, cap)
            for i in range(ndisp):
                bt = max(np.int32(r_lo[i]) - lv, lv - np.int32(r_hi[i]))
                bt = min(max(bt, np.int32(0)), limit)
                o[i] = np.uint8(np.int32(_popcount(left_bits ^ bits[i])) + bt)
        else:
            for i in range(ndisp):
                bt = max(np.int32(r_lo[i]) - lv, lv - np.int32(r_hi[i]), np.int32(0))
                bt = min(np.int32(np.rint(np.float32(min(bt, trunc8)) * weight)), np.int32(255))
                o[i] = np.uint8(np.int32(_popcount(left_bits ^ bits[i])) + min(bt, cap))


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
    # uint16 throughout (no value goes negative or past 65535): twice the SIMD lanes of int32
    pm, q1, jp, best16 = np.uint16(prev_min), np.uint16(p1), np.uint16(jump), np.uint16(best)
    for d in range(1, ndisp - 1):
        v = min(prev[d], np.uint16(min(prev[d - 1], prev[d + 1]) + q1), jp)
        v = np.uint16(np.uint16(v - pm) + np.uint16(c[d]))
        out[d] = v
        best16 = min(best16, v)
    best = np.int32(best16)
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
def _sweep(cost, guide, dy, dxs, p1, p2, p2_min, gscale, total):
    """``total`` = the path costs of the half of the directions that run down the rows
    (``dy`` = 1, with left-to-right along the row) or up them (-1, right-to-left).

    Rows one after the other; in each, the path along the row, then those from the
    previous row (column steps ``dxs``), summed and written once per pixel.
    """
    h, w, ndisp = cost.shape
    k = dxs.shape[0]
    prev = np.empty((k, w, ndisp), np.uint16)
    cur = np.empty((k, w, ndisp), np.uint16)
    prev_min = np.empty((k, w), np.int32)
    cur_min = np.empty((k, w), np.int32)
    along_prev = np.empty(ndisp, np.uint16)
    along = np.empty(ndisp, np.uint16)
    for step in range(h):
        y = step if dy > 0 else h - 1 - step
        g = guide[y]
        along_min = np.int32(0)
        for xs in range(w):
            x = xs if dy > 0 else w - 1 - xs
            c = cost[y, x]
            if xs == 0:
                along_min = _start(c, along)
            else:
                jump = along_min + _penalty(g[x], g[x - dy], p2, p2_min, gscale)
                along_min = _path_step(along_prev, along_min, c, p1, jump, along)
            for j in range(k):
                xq = x - dxs[j]
                if step == 0 or xq < 0 or xq >= w:
                    cur_min[j, x] = _start(c, cur[j, x])
                else:
                    pm = prev_min[j, xq]
                    jump = pm + _penalty(g[x], guide[y - dy, xq], p2, p2_min, gscale)
                    cur_min[j, x] = _path_step(prev[j, xq], pm, c, p1, jump, cur[j, x])
            out = total[y, x]
            if k == 3:
                a, b, e = cur[0, x], cur[1, x], cur[2, x]
                for d in range(ndisp):
                    out[d] = np.uint16(np.uint16(along[d] + a[d]) + np.uint16(b[d] + e[d]))
            else:
                a = cur[0, x]
                for d in range(ndisp):
                    out[d] = np.uint16(along[d] + a[d])
            along_prev, along = along, along_prev
        prev, cur = cur, prev
        prev_min, cur_min = cur_min, prev_min


@njit(cache=True, parallel=True)
def _both_sweeps(cost, guide, dxs, p1, p2, p2_min, gscale, down, up):
    for task in prange(2):
        if task == 0:
            _sweep(cost, guide, 1, dxs, p1, p2, p2_min, gscale, down)
        else:
            _sweep(cost, guide, -1, dxs, p1, p2, p2_min, gscale, up)


def aggregate(cost, guide, p1, p2, p2_min, gscale, paths, down, up):
    """SGM path costs summed over the scanline directions, in two halves.

    L(p, d) = C(p, d) + min(L(q, d), L(q, d +- 1) + P1, min_k L(q, k) + P2(p, q)) - min_k L(q, k)
    with q = p - r the previous pixel on the path; paths entering from outside the image
    start afresh (L = C). P2(p, q) = max(P2 / (1 + |I(p) - I(q)| / gscale), p2_min).
    Each path cost is at most max(C) + P2 <= 255 + P2: 8 paths fit in uint16 for P2 < 7900.
    The two halves run at once on two threads, without any synchronisation.

    Parameters
    ----------
    cost : (rows, cols, D) uint8
    guide : (rows, cols) float32
        Intensity (0..255) that lowers P2 across edges.
    paths : {4, 8}
    down, up : (rows, cols, D) uint16
        Output: the sums of the paths running down the rows (and left to right along
        them) and of those running up (and right to left); the total is their sum.
    """
    dxs = np.array([0, 1, -1] if paths == 8 else [0], np.int64)
    _both_sweeps(cost, guide, dxs, np.int32(p1), np.int32(p2), np.int32(p2_min), np.float32(gscale), down, up)


@njit(cache=True, parallel=True)
def select(down, up, dmin, subpixel, uniqueness):
    """Winner-takes-all over the aggregated costs ``down + up`` (see :func:`aggregate`).

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
    h, w, ndisp = down.shape
    disp = np.empty((h, w), np.float32)
    margin = np.empty((h, w), np.float32)
    right = np.empty((h, w), np.float32)
    for y in prange(h):
        t_row = np.empty((w, ndisp), np.uint16)
        _add_rows(down[y], up[y], t_row)
        _select_row(t_row, dmin, subpixel, uniqueness, disp[y], margin[y])
        _right_row(t_row, dmin, right[y])
    return disp, margin, right


@njit(cache=True)
def _add_rows(a, b, out):
    w, ndisp = a.shape
    for x in range(w):
        for d in range(ndisp):
            out[x, d] = np.uint16(a[x, d] + b[x, d])


@njit(cache=True)
def _min_of(t):
    """Smallest value of a uint16 (n,) array, 65535 when empty (a SIMD reduction)."""
    best = np.uint16(_TOP)
    for i in range(t.shape[0]):
        best = min(best, t[i])
    return np.int32(best)


@njit(cache=True)
def _select_row(t_row, dmin, subpixel, uniqueness, disp, margin):
    w, ndisp = t_row.shape
    for x in range(w):
        t = t_row[x]
        best = _min_of(t)
        bi = 0
        while np.int32(t[bi]) != best:  # the first minimum wins, as in argmin
            bi += 1
        bestf = np.float32(best)
        value = np.float32(bi + dmin)
        if subpixel and ndisp >= 3 and 0 < bi < ndisp - 1:
            cm, cp = np.float32(t[bi - 1]), np.float32(t[bi + 1])
            den = cm + cp - np.float32(2.0) * bestf
            if den > 0:
                offset = (cm - cp) / (np.float32(2.0) * den)
                value += min(max(offset, np.float32(-0.5)), np.float32(0.5))
        # second best outside the winner's +-1 neighbourhood
        second = min(_min_of(t[: max(bi - 1, 0)]), _min_of(t[bi + 2 :]))
        secondf = bestf if second == _TOP else np.float32(second)
        ratio = (secondf - bestf) / max(secondf, np.float32(1.0))
        margin[x] = min(max(ratio, np.float32(0.0)), np.float32(1.0))
        if uniqueness > 0 and not (secondf * np.float32(100.0) > bestf * np.float32(100.0 + uniqueness)):
            value = np.float32(np.nan)
        disp[x] = value


@njit(cache=True)
def _right_row(t_row, dmin, right):
    """Right disparity of one row: for each right column xr the smallest d among the
    minima of t_row(xr + d, d). Left pixels in order, each updating the right columns
    it reaches, kept reversed (entry w - 1 - xr) so that a pixel's run is contiguous."""
    w, ndisp = t_row.shape
    best = np.full(w, np.uint16(_TOP), np.uint16)
    arg = np.full(w, -1, np.int32)
    for x in range(w):
        i0 = max(0, x - dmin - (w - 1))
        i1 = min(ndisp, x - dmin + 1)
        if i1 <= i0:
            continue
        j0 = w - 1 - x + dmin + i0
        t = t_row[x, i0:i1]
        b = best[j0 : j0 + (i1 - i0)]
        a = arg[j0 : j0 + (i1 - i0)]
        for k in range(i1 - i0):
            if t[k] < b[k]:
                b[k] = t[k]
                a[k] = i0 + k
    for xr in range(w):
        i = arg[w - 1 - xr]
        right[xr] = np.float32(np.nan) if i < 0 else np.float32(dmin + i)


@njit(cache=True, parallel=True)
def weighted_median(disp, guide, todo, oy, ox, spatial, inv, out):
    """Edge-aware weighted median at the flat pixel indices ``todo``, into ``out``.

    Each pixel takes the weighted median of ``disp`` at the offsets (oy, ox) (clipped to
    the image), weights ``spatial * exp(inv * |guide(q) - guide(p)|^2)``, NaN values
    weighing nothing; it moves there only if that median is more than 1 px away.
    ``disp`` (H, W) float32, ``guide`` (H, W, C) float32, ``out`` (H, W) float32.
    """
    h, w = disp.shape
    n = oy.shape[0]
    for t in prange(todo.shape[0]):
        _median_at(disp, guide, todo[t] // w, todo[t] % w, oy, ox, spatial, inv, n, out)


@njit(cache=True)
def _median_at(disp, guide, r, c, oy, ox, spatial, inv, n, out):
    h, w = disp.shape
    values = np.empty(n, np.float32)
    weights = np.empty(n, np.float32)
    for k in range(n):
        rr = min(max(r + oy[k], 0), h - 1)
        cc = min(max(c + ox[k], 0), w - 1)
        v = disp[rr, cc]
        dist = np.float32(0.0)
        for ch in range(guide.shape[2]):
            diff = guide[rr, cc, ch] - guide[r, c, ch]
            dist += diff * diff
        wt = np.float32(np.exp(dist * inv)) * spatial[k]
        if not np.isfinite(v):
            wt = np.float32(0.0)
        # insertion sort by value, stable, NaN last
        j = k
        while j > 0 and (not np.isfinite(values[j - 1]) and np.isfinite(v) or values[j - 1] > v):
            values[j] = values[j - 1]
            weights[j] = weights[j - 1]
            j -= 1
        values[j] = v
        weights[j] = wt
    total = np.float32(0.0)
    for k in range(n):
        total += weights[k]
    half = np.float32(0.5) * total
    cum = np.float32(0.0)
    pick = 0
    for k in range(n):
        cum += weights[k]
        if cum < half:
            pick += 1
    pick = min(pick, n - 1)
    here = disp[r, c]
    median = values[pick]
    out[r, c] = median if np.abs(median - here) > 1.0 else here


@njit(cache=True, parallel=True)
def face_by_colour(disp, background, colour, min_step, min_contrast, side, descent, min_descent, likeness,
                   out, value):
    """The roof face in each occlusion hole, found by colour: into ``out`` (H, W) bool,
    its disparities into ``value`` (H, W) float32.

    A hole is a run of NaN in a row of ``disp`` between finite disparities, the right
    one at least ``min_step`` above the left one, the left one no higher than the
    hole's ``background`` fill + 1, and the surface beyond the right end falling away
    from it (by ``min_descent`` px over ``descent`` px: a ridge, not a flat roof's
    edge). Its reference colours are the means of ``colour`` (H, W, C) over the
    ``side`` matched pixels beyond each end. Where they differ by ``min_contrast`` or
    more (L1), the hole is split at the column that puts the left part nearest the
    left colour and the right part nearest the right colour (summed L1 distances), and
    the right part is the face when its mean distance to the right colour is at most
    ``likeness`` times the contrast. Its disparities ramp linearly to the right end's
    from the lower edge's: the right image sees the ground up to that edge, so the
    edge lands where the last matched ground pixel on the left does.
    """
    h, w = disp.shape
    nc = colour.shape[2]
    for y in prange(h):
        x = 0
        while x < w:
            if not np.isnan(disp[y, x]):
                x += 1
                continue
            start = x
            while x < w and np.isnan(disp[y, x]):
                x += 1
            il, ir = start - 1, x  # the hole is il + 1 .. ir - 1
            if il < 0 or ir + descent >= w:
                continue
            d_l, d_r = disp[y, il], disp[y, ir]
            if d_r - d_l < min_step or d_l > background[y, start] + 1.0:
                continue
            if np.isnan(disp[y, ir + descent]) or d_r - disp[y, ir + descent] < min_descent:
                continue
            _split_hole(disp, colour, y, il, ir, nc, side, min_contrast, likeness, out, value)


@njit(cache=True)
def _split_hole(disp, colour, y, il, ir, nc, side, min_contrast, likeness, out, value):
    w = disp.shape[1]
    bg = np.zeros(nc, np.float32)
    fg = np.zeros(nc, np.float32)
    nb = 0
    nf = 0
    for k in range(side):
        if il - k >= 0 and not np.isnan(disp[y, il - k]):
            nb += 1
            for c in range(nc):
                bg[c] += colour[y, il - k, c]
        if ir + k < w and not np.isnan(disp[y, ir + k]):
            nf += 1
            for c in range(nc):
                fg[c] += colour[y, ir + k, c]
    contrast = np.float32(0.0)
    for c in range(nc):
        bg[c] /= nb
        fg[c] /= nf
        contrast += abs(fg[c] - bg[c])
    if contrast < min_contrast:
        return
    # cost(s) = sum_{x < s} d_bg(x) + sum_{x >= s} d_fg(x): grow the right part leftwards
    best_s = ir
    best = np.float32(0.0)
    run = np.float32(0.0)
    near = np.float32(0.0)
    near_best = np.float32(0.0)
    for s in range(ir - 1, il, -1):
        dbg = np.float32(0.0)
        dfg = np.float32(0.0)
        for c in range(nc):
            dbg += abs(colour[y, s, c] - bg[c])
            dfg += abs(colour[y, s, c] - fg[c])
        run += dfg - dbg
        near += dfg
        if run < best:
            best, best_s, near_best = run, s, near
    if best_s == ir or near_best / np.float32(ir - best_s) > likeness * contrast:
        return
    d_r = disp[y, ir]
    d_e = min(disp[y, il] + np.float32(best_s - il), d_r)
    for s in range(best_s, ir):
        out[y, s] = True
        value[y, s] = d_e + (d_r - d_e) * np.float32(s - best_s) / np.float32(ir - best_s)
