"""The refinement's pieces as they were before the eleventh session's changes (commit
b752e53), for ``tests/test_refine_speed.py`` to compare the faster ones with bit for
bit: the noise scale and the trocar with ``np.median`` and ``np.linalg.norm``, the
trocar's solve with its unused condition number, the head swaps found frame by frame
from one dict per frame."""

from __future__ import annotations

import numpy as np

from mistool.model import TrackTable
from mistool.pose.trocar import Trocar
from mistool.tracking.relink import (
    HEAD_SWAP_KEEP_MARGIN,
    HEAD_SWAP_MARGIN,
    HEAD_SWAP_MIN_FRAMES,
    _Anchor,
    _attachment,
    _Candidate,
    _name_key,
    _Rows,
    _shaft_anchor,
    _strong_frames,
)


def noise_scale(y: np.ndarray, floor: float) -> float:
    y = y[np.isfinite(y)]
    if len(y) < 4:
        return floor
    d2 = y[2:] - 2.0 * y[1:-1] + y[:-2]
    return max(1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / np.sqrt(6.0), floor)


def distances_to_lines(point: np.ndarray, p: np.ndarray, a: np.ndarray) -> np.ndarray:
    d = point - p
    along = np.einsum("ij,ij->i", d, a)
    return np.linalg.norm(d - along[:, None] * a, axis=1)


def _solve(p: np.ndarray, a: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    m = np.eye(3)[None] - a[:, :, None] * a[:, None, :]
    wm = w[:, None, None] * m
    A = wm.sum(axis=0)
    b = np.einsum("nij,nj->i", wm, p)
    evals = np.linalg.eigvalsh(A)
    cond = float(evals[0] / max(evals[-1], 1e-12))
    return np.linalg.solve(A + 1e-9 * np.eye(3), b), cond


def lmeds_start(p: np.ndarray, a: np.ndarray, pairs: int = 60) -> np.ndarray | None:
    rng = np.random.default_rng(0)
    n = len(p)
    i = rng.integers(0, n, pairs)
    j = rng.integers(0, n, pairs)
    best, best_med = None, np.inf
    for k in range(pairs):
        a1, a2 = a[i[k]], a[j[k]]
        c = float(a1 @ a2)
        if abs(c) > np.cos(np.radians(2.0)):
            continue
        d = p[j[k]] - p[i[k]]
        s = (d @ a1 - c * (d @ a2)) / (1.0 - c * c)
        t = (c * (d @ a1) - d @ a2) / (1.0 - c * c)
        x = 0.5 * (p[i[k]] + s * a1 + p[j[k]] + t * a2)
        med = float(np.median(distances_to_lines(x, p, a)))
        if med < best_med:
            best, best_med = x, med
    return best


def intersect_lines(
    p: np.ndarray, a: np.ndarray, min_lines: int = 5, min_spread_deg: float = 2.0, iters: int = 10
) -> Trocar | None:
    ok = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(a), axis=1)
    p, a = p[ok], a[ok]
    if len(p) < min_lines:
        return None
    point = lmeds_start(p, a)
    if point is None:
        return None
    scale = None
    for _ in range(iters):
        r = distances_to_lines(point, p, a)
        mad = 1.4826 * float(np.median(r))
        scale = max(mad, 0.5) if scale is None else max(min(mad, scale), 0.5)
        u = r / (4.0 * scale)
        w = np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)
        if np.count_nonzero(w) < min_lines:
            return None
        point, _ = _solve(p, a, w)
    r = distances_to_lines(point, p, a)
    inl = w > 0
    mean_dir = a[inl].mean(axis=0)
    mean_dir /= np.linalg.norm(mean_dir)
    cosang = np.clip(a[inl] @ mean_dir, -1.0, 1.0)
    spread = float(np.degrees(np.sqrt(np.mean(np.arccos(cosang) ** 2))))
    if spread < min_spread_deg or int(inl.sum()) < min_lines:
        return None
    full = np.zeros(len(ok), dtype=bool)
    full[np.flatnonzero(ok)[inl]] = True
    m = np.eye(3)[None] - a[inl, :, None] * a[inl, None, :]
    A = m.sum(axis=0)
    dof = max(int(inl.sum()) * 2 - 3, 1)
    var = float(np.sum(r[inl] ** 2)) / dof
    cov = var * np.linalg.inv(A + 1e-9 * np.eye(3))
    return Trocar(point, full, float(np.sqrt(np.mean(r[inl] ** 2))), spread, cov)


def _swap_candidates(
    rows: _Rows, frames: list[dict[tuple[str, str], int]], part: str
) -> list[_Candidate]:
    x, y = rows.xy[:, 0].tolist(), rows.xy[:, 1].tolist()
    out: list[_Candidate] = []
    for f, by in enumerate(frames):
        names = sorted({n for n, p in by if p == part and (n, "shaft") in by}, key=_name_key)
        if len(names) < 2:
            continue
        anchors: dict[str, _Anchor] = {}
        for n in names:
            r = by[(n, "shaft")]
            anchors[n] = _shaft_anchor(
                x[r], y[r], float(rows.length[r]), float(rows.width[r]),
                float(rows.angle[r]), rows.extent,
            )  # fmt: skip
            w = by.get((n, "wrist"))
            if part == "clasper" and w is not None:
                anchors[n] = (x[w], y[w], anchors[n][2], None)
        paired: set[str] = set()
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                if a in paired or b in paired:
                    continue
                ra, rb = by[(a, part)], by[(b, part)]
                pa, pb = anchors[a], anchors[b]
                now = _attachment(x[ra], y[ra], pa) + _attachment(x[rb], y[rb], pb)
                swapped = _attachment(x[ra], y[ra], pb) + _attachment(x[rb], y[rb], pa)
                width = 0.5 * (pa[2] + pb[2])
                if swapped + HEAD_SWAP_KEEP_MARGIN * width < now:
                    strong = swapped + HEAD_SWAP_MARGIN * width < now
                    out.append((f, a, b, ra, rb, strong))
                    paired |= {a, b}
    return out


def swap_heads(table: TrackTable) -> TrackTable:
    if table.num_rows == 0:
        return table
    frame = np.asarray(table["frame"]).astype(np.int64)
    first = int(frame.min())
    busy = np.zeros(int(frame.max()) - first + 1, dtype=bool)
    part_of = np.asarray(table["part"])
    for part in ("wrist", "clasper"):
        busy |= np.bincount(frame[part_of == part] - first, minlength=len(busy)) >= 2
    if not busy.any():
        return table
    rows = _Rows(table)
    frames: list[dict[tuple[str, str], int]] = [{} for _ in range(len(busy))]
    look = np.flatnonzero(busy[frame - first])
    for r, f, n, p in zip(
        look.tolist(),
        rows.frame[look].tolist(),
        rows.name[look].tolist(),
        rows.part[look].tolist(),
        strict=True,
    ):
        frames[f - first][(n, p)] = r
    names = rows.name.copy()
    swapped = False
    for part in ("wrist", "clasper"):
        runs: dict[tuple[str, str], list[_Candidate]] = {}
        for c in _swap_candidates(rows, frames, part):
            runs.setdefault((c[1], c[2]), []).append(c)
        for pair in runs.values():
            start = 0
            for j in range(1, len(pair) + 1):
                if j < len(pair) and pair[j][0] == pair[j - 1][0] + 1:
                    continue
                if _strong_frames(pair[start:j]) >= HEAD_SWAP_MIN_FRAMES:
                    for f, a, b, ra, rb, _ in pair[start:j]:
                        names[ra], names[rb] = b, a
                        by = frames[f]
                        by[(b, part)], by[(a, part)] = ra, rb
                    swapped = True
                start = j
    if not swapped:
        return table
    return table.with_columns(instrument=names.astype(object))
