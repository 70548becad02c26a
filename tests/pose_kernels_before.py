"""The compiled pose kernels' pieces as they were before the tenth session's changes
(commit 3dccf97), compiled here with the same numba options, for
``tests/test_pose_speed.py`` to compare the faster kernels with bit for bit."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

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
    if kp._ransac(x, y, along, thresh, iters, h) < 6:
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
