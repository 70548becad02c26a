"""The compiled pose kernels' pieces as they were before the tenth session's changes
(commit 3dccf97; the line fit's RANSAC and sort, the jaw ends' picks and the contour
tracing as they were before the eleventh session's, at commit 5bd7ced), compiled here
with the same numba options, for ``tests/test_pose_speed.py`` to compare the faster
kernels with bit for bit."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from mistool.kernels import contours as kc
from mistool.kernels import pose as kp

_jit = njit(cache=True, nogil=True, error_model="numpy")


@_jit
def jaw_axis(
    mask: np.ndarray,
    ox: int,
    oy: int,
    cx: int,
    cy: int,
    rad: float,
    ux: float,
    uy: float,
    width: float,
    end: np.ndarray,
) -> bool:
    h, w = mask.shape
    x0, y0 = max(int(math.floor(cx - rad)), 0), max(int(math.floor(cy - rad)), 0)
    x1, y1 = min(int(math.ceil(cx + rad)) + 1, w), min(int(math.ceil(cy + rad)) + 1, h)
    r2 = rad * rad
    xs = np.empty(max((x1 - x0) * (y1 - y0), 0), np.int64)
    ys = np.empty_like(xs)
    flat = mask.view(np.uint8).ravel()
    cnt = sx = sy = 0
    for y in range(y0, y1):  # row-major, as np.nonzero
        rem = r2 - (y - cy) * (y - cy)
        if rem < 0:
            continue
        dxm = int(math.sqrt(rem))  # the row's pixels in the disc: |x - cx| <= dxm, exactly
        while dxm * dxm > rem:
            dxm -= 1
        while (dxm + 1) * (dxm + 1) <= rem:
            dxm += 1
        base = y * w
        for x in range(max(cx - dxm, x0), min(cx + dxm + 1, x1)):
            # written always, kept when the pixel is set: no branch on the mask
            v = np.int64(flat[base + x])
            xs[cnt], ys[cnt] = x, y
            cnt += v
            sx += x * v
            sy += y * v
    if cnt < 3:
        return False
    mx, my = (sx + cnt * ox) / cnt, (sy + cnt * oy) / cnt
    c00 = c01 = c11 = 0.0
    for k in range(cnt):
        dx, dy = float(xs[k] + ox) - mx, float(ys[k] + oy) - my
        c00 += dx * dx
        c01 += dx * dy
        c11 += dy * dy
    phi = 0.5 * math.atan2(2.0 * c01, c00 - c11)
    e0, e1 = math.cos(phi), math.sin(phi)
    if e0 * ux + e1 * uy < 0:
        e0, e1 = -e0, -e1
    along = -math.inf
    lo, hi = math.inf, -math.inf
    for k in range(cnt):
        dx, dy = float(xs[k] + ox) - mx, float(ys[k] + oy) - my
        along = max(along, dx * e0 + dy * e1)
        across = dx * -e1 + dy * e0
        lo, hi = min(lo, across), max(hi, across)
    end[0], end[1] = mx + (along + 0.5) * e0, my + (along + 0.5) * e1
    end[2], end[3] = e0, e1
    end[4] = min(0.5 * (hi - lo) + 0.5, width)
    return True


@_jit
def iou_count(
    rend: np.ndarray, mask: np.ndarray, ox: int, oy: int, x0: int, y0: int, st: int
) -> float:
    hc, wc = rend.shape
    mh, mw = mask.shape
    rflat = rend.ravel()
    n_rend = 0
    for i in range(np.uint64(hc * wc)):
        n_rend += rflat[i]
    ia, ja = max(0, -(-(oy - y0) // st)), max(0, -(-(ox - x0) // st))
    ib, jb = min(hc, -(-(oy + mh - y0) // st)), min(wc, -(-(ox + mw - x0) // st))
    m8 = mask.view(np.uint8).ravel()
    inter = n_obs = 0
    for i in range(ia, ib):  # the mask's samples within the canvas
        m0 = np.uint64((y0 + st * i - oy) * mw + x0 + st * ja - ox)
        r0 = np.uint64(i * wc + ja)
        row_obs = row_inter = 0
        if st == 1:
            for j in range(np.uint64(jb - ja)):
                row_obs += m8[m0 + j]
                row_inter += m8[m0 + j] & rflat[r0 + j]
        else:
            for j in range(np.uint64(jb - ja)):
                row_obs += m8[m0 + 2 * j]
                row_inter += m8[m0 + 2 * j] & rflat[r0 + j]
        n_obs += row_obs
        inter += row_inter
    union = n_rend + n_obs - inter
    return inter / union if union else math.nan


@_jit
def _irls_step(
    x: np.ndarray, y: np.ndarray, r: np.ndarray, line: np.ndarray, scale: float, thresh: float
) -> float:
    n = len(x)
    f = 1.0 / (2.5 * scale)
    m00 = m01 = m02 = m11 = m12 = sw = 0.0
    for t in range(n):
        u = r[t] * f
        w = max(1.0 - u * u, 0.0)
        w *= w
        xw = x[t] * w
        yw = y[t] * w
        m00 += xw * x[t]
        m01 += xw * y[t]
        m02 += xw
        m11 += yw * y[t]
        m12 += yw
        sw += w
    if sw < 6:
        return -1.0
    kp._tls(m00, m01, m02, m11, m12, sw, line)
    core = np.empty(n)
    k = 0
    lim = 2.5 * scale
    for t in range(n):
        r[t] = line[0] * x[t] + line[1] * y[t] + line[2]
        ra = abs(r[t])
        if ra < lim:
            core[k] = ra
            k += 1
    if k:
        scale = min(max(1.4826 * kp._select(core[:k], k // 2), 0.3), thresh)
    return scale


@_jit
def fit_line(
    px: np.ndarray,
    py: np.ndarray,
    along: np.ndarray,
    thresh: float,
    iters: int,
    line: np.ndarray,
    inliers: np.ndarray,
) -> int:
    n = len(px)
    if n < 8:
        return -1
    sx = sy = 0.0
    for t in range(n):
        sx += px[t]
        sy += py[t]
    ox, oy = sx * (1.0 / n), sy * (1.0 / n)
    x = np.empty(n)
    y = np.empty(n)
    for t in range(n):
        x[t] = px[t] - ox
        y[t] = py[t] - oy
    h = np.empty(3)
    if ransac(x, y, along, thresh, iters, h) < 6:
        return -1
    m00 = m01 = m02 = m11 = m12 = sw = 0.0
    for t in range(n):
        if abs(h[0] * x[t] + h[1] * y[t] + h[2]) < thresh:
            m00 += x[t] * x[t]
            m01 += x[t] * y[t]
            m02 += x[t]
            m11 += y[t] * y[t]
            m12 += y[t]
            sw += 1.0
    kp._tls(m00, m01, m02, m11, m12, sw, line)
    r = np.empty(n)
    for t in range(n):
        r[t] = line[0] * x[t] + line[1] * y[t] + line[2]
    scale = thresh
    for _ in range(2):
        step = _irls_step(x, y, r, line, scale, thresh)
        if step < 0:
            break
        scale = step
    lim = max(2.5 * scale, 0.75)
    k = 0
    ss = 0.0
    for t in range(n):
        if abs(r[t]) < lim:
            inliers[k] = t
            ss += r[t] * r[t]
            k += 1
    line[3] = math.sqrt(ss / k) if k else math.inf
    line[2] -= line[0] * ox + line[1] * oy
    return k


@_jit
def argsort(v: np.ndarray) -> np.ndarray:
    n = len(v)
    idx = np.empty(n, np.int64)
    key = np.empty(n)
    tmp = np.empty(n, np.int64)
    tkey = np.empty(n)
    bounds = np.empty(n + 1, np.int64)
    n_runs = 0
    i = 0
    while i < n:  # the runs: ascending as they are, strictly descending reversed
        j = i + 1
        if j < n and v[j] < v[i]:
            while j < n and v[j] < v[j - 1]:
                j += 1
            for k in range(j - i):
                idx[i + k] = j - 1 - k
                key[i + k] = v[j - 1 - k]
        else:
            while j < n and v[j] >= v[j - 1]:
                j += 1
            for k in range(i, j):
                idx[k] = k
                key[k] = v[k]
        bounds[n_runs] = i
        n_runs += 1
        i = j
    bounds[n_runs] = n
    while n_runs > 1:  # merge neighbouring runs pairwise
        m = 0
        for r in range(0, n_runs, 2):
            lo, mid = bounds[r], bounds[r + 1]
            hi = bounds[r + 2] if r + 2 <= n_runs else mid
            a, b, k = lo, mid, lo
            while a < mid and b < hi:
                if key[b] < key[a]:
                    tmp[k], tkey[k] = idx[b], key[b]
                    b += 1
                else:
                    tmp[k], tkey[k] = idx[a], key[a]
                    a += 1
                k += 1
            while a < mid:
                tmp[k], tkey[k] = idx[a], key[a]
                a += 1
                k += 1
            while b < hi:
                tmp[k], tkey[k] = idx[b], key[b]
                b += 1
                k += 1
            bounds[m] = lo
            m += 1
        bounds[m] = n
        n_runs = m
        idx, tmp = tmp, idx
        key, tkey = tkey, key
    return idx


@_jit
def ransac(
    x: np.ndarray, y: np.ndarray, along: np.ndarray, thresh: float, iters: int, h: np.ndarray
) -> int:
    n = len(x)
    order = argsort(along)
    half = n // 2
    best = math.inf
    res = np.empty(n)
    found = False
    for k in range(iters):
        i = order[int(kp._DRAWS[0, k] * half)]
        j = order[n - half + int(kp._DRAWS[1, k] * half)]
        h0, h1 = y[i] - y[j], x[j] - x[i]
        ln = math.sqrt(h0 * h0 + h1 * h1)
        if not ln > 1e-9:  # NaN falls through: its residuals say no line
            if not math.isnan(ln):
                continue
        h0, h1 = h0 / ln, h1 / ln
        c = -(h0 * x[i] + h1 * y[i])
        for t in range(n):
            res[t] = min(abs(h0 * x[t] + h1 * y[t] + c), thresh)
        cost = kp._sum8(res)
        if math.isnan(cost):  # a NaN line or point: no line
            return -1
        if cost < best:
            best = cost
            h[0], h[1], h[2] = h0, h1, c
            found = True
    if not found:
        return -1
    count = 0
    for t in range(n):
        count += abs(h[0] * x[t] + h[1] * y[t] + h[2]) < thresh
    return count


@_jit
def jaw_picks(
    ci: np.ndarray, ox: float, oy: float, ju: float, jv: float, width: float, picks: np.ndarray
) -> int:
    n = len(ci)
    if n < 2:
        return 0
    d = np.empty(n)
    for i in range(n):
        dx = (ci[i, 0] + ox) - ju
        dy = (ci[i, 1] + oy) - jv
        d[i] = math.sqrt(dx * dx + dy * dy)
    win = int(max(2, min(n // 4, np.rint(width))))
    dmax = d.max()
    cand = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if d[i] < 0.5 * dmax:
            continue
        top = True  # d[i] is the maximum of its window (the outline is closed)
        for j in range(i - win, i + win + 1):
            jj = j + n if j < 0 else (j - n if j >= n else j)
            if d[jj] > d[i]:
                top = False
                break
        if top:
            cand[k] = i
            k += 1
    cand = cand[:k]
    order = argsort(-d[cand])  # farthest first; equal distances in outline order
    n_picks = 0
    for o in order:
        i = cand[o]
        xi, yi = ci[i, 0] + ox, ci[i, 1] + oy
        far = True
        for p in range(n_picks):
            far &= math.hypot(xi - (ci[picks[p], 0] + ox), yi - (ci[picks[p], 1] + oy)) > width
        if far:
            picks[n_picks] = i
            n_picks += 1
            if n_picks == 2:
                break
    return n_picks


@_jit
def trace(
    flat: np.ndarray, h: int, w: int, x0: int, y0: int, points: np.ndarray, start: int
) -> int:
    cap = points.shape[0] - start
    if cap < 1:
        return -2
    x, y = x0, y0
    s = 4
    n = 0
    first_step = True
    x1 = y1 = 0  # the second pixel
    while True:
        if 0 < x < w - 1 and 0 < y < h - 1:  # all eight neighbours in the crop
            k = y * w + x
            code = (
                np.uint64(flat[k + 1])
                | np.uint64(flat[k + 1 - w]) << np.uint64(1)
                | np.uint64(flat[k - w]) << np.uint64(2)
                | np.uint64(flat[k - 1 - w]) << np.uint64(3)
                | np.uint64(flat[k - 1]) << np.uint64(4)
                | np.uint64(flat[k - 1 + w]) << np.uint64(5)
                | np.uint64(flat[k + w]) << np.uint64(6)
                | np.uint64(flat[k + 1 + w]) << np.uint64(7)
            )
        else:
            code = (
                kc._pixel(flat, h, w, x + 1, y)
                | kc._pixel(flat, h, w, x + 1, y - 1) << np.uint64(1)
                | kc._pixel(flat, h, w, x, y - 1) << np.uint64(2)
                | kc._pixel(flat, h, w, x - 1, y - 1) << np.uint64(3)
                | kc._pixel(flat, h, w, x - 1, y) << np.uint64(4)
                | kc._pixel(flat, h, w, x - 1, y + 1) << np.uint64(5)
                | kc._pixel(flat, h, w, x, y + 1) << np.uint64(6)
                | kc._pixel(flat, h, w, x + 1, y + 1) << np.uint64(7)
            )
        if first_step:  # the start pixel (west of it: background)
            first_step = False
            s = 4
            while True:
                s = (s - 1) & 7
                if (code >> np.uint64(s)) & np.uint64(1) or s == 4:
                    break
            if s == 4:  # a single pixel
                points[start, 0], points[start, 1] = x0, y0
                return 1
            x1, y1 = x0 + kc._DX[s], y0 + kc._DY[s]
        s = np.int64(kc._NEXT[code * np.uint64(8) + np.uint64(s)])
        if n == cap:
            return -2
        points[start + n, 0], points[start + n, 1] = x, y
        n += 1
        xn, yn = x + kc._DX[s], y + kc._DY[s]
        if xn == x0 and yn == y0 and x == x1 and y == y1:
            return n
        x, y = xn, yn
        s = (s + 4) & 7


# -- the twelfth session's pieces as they were before it (commit 37a36fc) ---------------


@_jit
def tip_depth(
    rx: float,
    ry: float,
    rz: float,
    jx: float,
    jy: float,
    jz: float,
    ax: float,
    ay: float,
    az: float,
    l_nom: float,
    has_len: bool,
    bend: float,
    sigma: float,
) -> float:
    """``kernels.pose._tip_depth`` (the bend's arc cosine at every grid point);
    ``bend``, ``sigma``: its ``par`` entries."""
    s_j = rx * jx + ry * jy + rz * jz
    span = 3.0 * (l_nom if has_len else 16.0)
    lo = max(s_j - span, 1.0)
    step = s_j + span - lo
    jj = jx * jx + jy * jy + jz * jz
    ra = rx * ax + ry * ay + rz * az
    ja = jx * ax + jy * ay + jz * az
    grid = kp._UNIT_GRID
    n = len(grid)
    cost = np.empty(n)
    best = 0
    for k in range(n):
        s = lo + step * grid[k]
        ln = math.sqrt(max((s - 2.0 * s_j) * s + jj, 0.0))
        cosb = min(max((s * ra - ja) / max(ln, 1e-9), -1.0), 1.0)
        c = math.acos(cosb) / bend
        c = c * c
        if has_len:
            e = (ln - l_nom) / (sigma * l_nom)
            c += e * e
        cost[k] = c
        if c < cost[best]:
            best = k
    sk = lo + step * grid[best]
    if 0 < best < n - 1:  # parabolic refinement
        c0, c1, c2 = cost[best - 1], cost[best], cost[best + 1]
        den = c0 - 2.0 * c1 + c2
        off = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        sk += min(max(off, -1.0), 1.0) * ((lo + step * grid[1]) - (lo + step * grid[0]))
    return sk


@_jit
def near_others(lab: np.ndarray, gap_rows: np.ndarray, near: np.ndarray) -> None:
    """``kernels.pose._near_others``: ``cv2.dilate(lab == OTHER, disk) > 0`` over the
    whole window."""
    hh, ww = lab.shape
    g = (len(gap_rows) - 1) // 2
    pre = np.zeros((hh, ww + 1), np.int64)
    for y in range(hh):
        acc = 0
        for x in range(ww):
            acc += lab[y, x] == 2
            pre[y, x + 1] = acc
    for y in range(hh):
        for x in range(ww):
            hit = False
            for i in range(2 * g + 1):
                yy = y + i - g
                if 0 <= yy < hh:
                    r = gap_rows[i]
                    if pre[yy, min(x + r, ww - 1) + 1] > pre[yy, max(x - r, 0)]:
                        hit = True
                        break
            near[y, x] = hit
