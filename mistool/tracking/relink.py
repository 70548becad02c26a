"""Offline relinking: a whole sequence's names revisited once it is tracked.

The identity step (:class:`~mistool.tracking.IdentityTracker`) names instruments frame by
frame and never renames the past. With the whole motion table at hand, two of its errors
are plain to see, and undone here (:func:`relink`, called by :func:`mistool.api.refine`):

- **Fragments.** A tool entering the view head first, cut in two by an occluder, gets two
  names in its first frame; the piece's name lives a frame or two (and may later be
  handed to another tool coming back near it). A name's first run of at most
  :data:`FRAGMENT_MAX_FRAMES` frames that lies, in each of its frames, within
  :data:`FRAGMENT_REACH_PX` of a longer-lived name seen in all of them (at least
  :data:`FRAGMENT_HOST_MIN_FRAMES`), is that tool's when the tool shows no shaft there
  (its head entering the view), or shows a shaft and a head but none of the piece's parts,
  the piece lying on beyond its head along its shaft (:data:`BEYOND_HEAD_DEG`: jaws cut off
  past the wrist): the piece's rows take that name (a row of a part the tool already
  shows in that frame is dropped: one row per frame, instrument and part).
- **Broken lives.** A tool that leaves the view and comes back farther from where it left
  than the online search reaches gets a new name; a name given back to the wrong tool
  after a gap follows that tool. Each name is cut into tracklets, its runs of consecutive
  frames, also where it jumps (none of its boxes within :data:`JUMP_PX` of its boxes in
  the frame before: the name handed to a tool entering elsewhere in the very frame its
  own tool went on under another name); then one gated assignment
  (:func:`sparse_gated_assignment`) links tracklet ends to later tracklet starts by where
  the tool's shaft enters the view (it pivots about its trocar) and the time between them
  (:func:`link_cost`). Links the identity step made (one name across a gap) cost less and
  are kept unless the assignment finds a better one. Each chain of linked tracklets is one
  instrument.

- **Swapped heads.** Where the heads of two tools meet (jaws grasping, under an occluder),
  a split or hand-over may give each tool the other's wrist or jaws, and the identity
  step's head memory keeps the swap for tens of frames after they part. A head hangs on
  its own tool: its wrist continues its shaft's axis from the shaft's distal end, its
  jaws lie at its wrist (:func:`attachment_cost`). Per frame, two names' rows of one head
  part are swapped when the swap attaches both better by at least
  :data:`HEAD_SWAP_MARGIN` shaft widths (:func:`swap_heads`), only over runs of at least
  :data:`HEAD_SWAP_MIN_FRAMES` consecutive frames of that pair (a frame alone where heads
  touch is no evidence: box centres of merged heads lie between them), and the frames
  next to such a run where the swap gains less (:data:`HEAD_SWAP_KEEP_MARGIN`: the heads
  still close).
- **A wrist on another tool's shaft.** A tool's wrist cut off by an occluder, or taken
  with another tool's head by a split, goes under that tool's name while its own tool,
  seen with its shaft, shows no wrist. Per frame, a name's wrist row goes to another name
  showing a shaft and no wrist when it hangs on that shaft better by more than
  :data:`HEAD_MOVE_MARGIN` of its widths (:func:`move_heads`), only over runs of at least
  :data:`HEAD_SWAP_MIN_FRAMES` consecutive frames of that pair; the giving name's jaws go
  with it when they lie nearer the moved wrist than the giving shaft's distal end and the
  receiving name shows none.

Names are then renumbered ``"1"``, ``"2"``, ... in order of first appearance, as the
identity step numbers them (unchanged when nothing was relinked). Pure, table in and
table out: it needs no pixels, only each row's part box, so it runs on the raw rows of a
whole sequence (:func:`mistool.api.iter_track`'s chunks concatenated) as well as on a
finished table. The live path (:class:`mistool.Tracker` ``update``, the live viewer)
shows the identity step's names as they come; :meth:`mistool.Tracker.table` relinks.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from mistool.model import TrackTable

__all__ = [
    "FRAGMENT_MAX_FRAMES",
    "FRAGMENT_REACH_PX",
    "JUMP_PX",
    "LINK_GATE",
    "LINK_MAX_GAP_S",
    "box_gap",
    "HEAD_SWAP_KEEP_MARGIN",
    "HEAD_SWAP_MARGIN",
    "HEAD_SWAP_MIN_FRAMES",
    "HEAD_MOVE_MARGIN",
    "attachment_cost",
    "link_cost",
    "relink",
    "sparse_gated_assignment",
    "move_heads",
    "swap_heads",
]

#: A name whose first run of consecutive frames is at most this long may be a fragment
#: of another tool (a head an occluder cut off as the tool entered) ...
FRAGMENT_MAX_FRAMES = 3
#: ... when in each of those frames one of its part boxes lies within this many pixels of
#: one of that tool's (an occluder's width: the cut-off head lies beyond it) ...
FRAGMENT_REACH_PX = 80.0
#: ... and that tool is seen in all of them, for longer and for at least this many
#: frames (its head may itself come in pieces for a few frames, then go on under the name
#: of one of them: that one is linked on).
FRAGMENT_HOST_MIN_FRAMES = 3
#: Tracklets are linked across at most this many seconds unseen ...
LINK_MAX_GAP_S = 4.0
#: ... at a cost of at most this much (:func:`link_cost`).
LINK_GATE = 2.5
#: The distance between where the shaft left and where it comes back costs one per this
#: fraction of the image diagonal (as :attr:`~mistool.tracking.CostWeights.entry_scale_frac`).
LINK_SCALE_FRAC = 0.1
#: Each second unseen costs this much.
LINK_GAP_PER_S = 0.25
#: A link the identity step made (one name across the gap) costs this much less, and
#: never more than the gate: it is undone only for a better link.
LINK_SAME_NAME_BONUS = 0.5
#: A tracklet's end (start) is where its shaft enters the view in the last (first) frame
#: with a shaft among this many.
ANCHOR_FRAMES = 5
#: Two names' rows of one head part are swapped when that lowers the sum of their
#: :func:`attachment_cost` by more than this many shaft widths (the mean of the two) ...
HEAD_SWAP_MARGIN = 0.5
#: ... in each of at least this many consecutive frames; such a run goes on over the
#: frames next to it where the swap lowers the sum by more than
#: :data:`HEAD_SWAP_KEEP_MARGIN` shaft widths.
HEAD_SWAP_MIN_FRAMES = 3
HEAD_SWAP_KEEP_MARGIN = 0.25
#: A wrist's distance along its shaft's axis from the shaft's distal end counts this much
#: (the part of the shaft an occluder or the other tool hides shortens its box) ...
HEAD_ALONG_WEIGHT = 0.5
#: A name's wrist row goes to another name that shows a shaft but no wrist in that frame
#: when it hangs on that name's shaft better by more than this many of that shaft's
#: widths (:func:`attachment_cost`), in each of at least :data:`HEAD_SWAP_MIN_FRAMES`
#: consecutive frames (:func:`move_heads`).
HEAD_MOVE_MARGIN = 0.5


@dataclass
class _Tracklet:
    """One name's run of consecutive frames."""

    name: str
    rows: np.ndarray
    """Row indices into the table."""
    frames: np.ndarray
    """Its frames, sorted, consecutive."""
    host: _Tracklet | None = None
    """The tracklet it is a fragment of, when absorbed."""

    @property
    def first(self) -> int:
        return int(self.frames[0])

    @property
    def last(self) -> int:
        return int(self.frames[-1])


class _Rows:
    """The columns :func:`relink` reads, as arrays."""

    def __init__(self, table: TrackTable) -> None:
        self.frame = np.asarray(table["frame"]).astype(np.int64)
        self.name = np.asarray(table["instrument"]).astype(str)
        self.part = np.asarray(table["part"]).astype(str)
        self.xy = np.stack([np.asarray(table["cx_px"]), np.asarray(table["cy_px"])], 1).astype(
            np.float64
        )
        self.length = np.asarray(table["length_px"], dtype=np.float64)
        self.width = np.asarray(table["width_px"], dtype=np.float64)
        self.angle = np.asarray(table["angle_deg"], dtype=np.float64)
        self.area = np.asarray(table["area_px"], dtype=np.float64)
        self.corners = np.stack(
            [
                np.stack([np.asarray(table[f"x{k}_px"]), np.asarray(table[f"y{k}_px"])], 1)
                for k in (1, 2, 3, 4)
            ],
            1,
        ).astype(np.float64)
        finite = self.corners[np.isfinite(self.corners).all(axis=(1, 2))]
        # the view's extent: boxes of shafts entering the view reach its borders
        self.extent = finite.reshape(-1, 2).max(axis=0) if len(finite) else np.ones(2)


def _tracklets(rows: _Rows) -> list[_Tracklet]:
    """Every name cut into its runs of consecutive frames, and where it jumps
    (:func:`_jumps`), in order of first frame."""
    out: list[_Tracklet] = []
    order = np.lexsort((rows.frame, rows.name))
    names, frames = rows.name[order], rows.frame[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (names[1:] != names[:-1]) | (frames[1:] - frames[:-1] > 1)
    new[1:] |= _jumps(rows, order)
    for sel in np.split(order, np.flatnonzero(new)[1:]):
        out.append(_Tracklet(str(rows.name[sel[0]]), sel, np.unique(rows.frame[sel])))
    out.sort(key=lambda t: (t.first, t.name))
    return out


#: A name jumps where none of its part boxes in a frame lies within this many pixels of
#: one of its boxes in the frame before (a tool moves a few pixels a frame; the identity
#: step's name handed to another tool does not).
JUMP_PX = 40.0


def _jumps(rows: _Rows, order: np.ndarray) -> np.ndarray:
    """Per row of ``order`` (rows sorted by name, then frame) after the first: whether it
    is the first row of a name's frame whose part boxes (their axis-aligned bounds) all lie
    more than :data:`JUMP_PX` from each of the name's boxes in the frame before."""
    n = len(order)
    out = np.zeros(max(n - 1, 0), dtype=bool)
    if n < 2:
        return out
    names, frames = rows.name[order], rows.frame[order]
    c = rows.corners[order]
    lo = np.minimum(np.minimum(c[:, 0], c[:, 1]), np.minimum(c[:, 2], c[:, 3]))
    hi = np.maximum(np.maximum(c[:, 0], c[:, 1]), np.maximum(c[:, 2], c[:, 3]))
    start = np.ones(n, dtype=bool)
    start[1:] = (names[1:] != names[:-1]) | (frames[1:] != frames[:-1])
    group = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    slot = np.arange(n) - first[group]
    # consecutive groups: the same name, the next frame
    a_first, b_first = first[:-1], first[1:]
    follows = (names[b_first] == names[a_first]) & (frames[b_first] == frames[a_first] + 1)
    g = np.flatnonzero(follows)
    if len(g) == 0:
        return out
    # per group and part slot, the box's bounds (NaN: no such slot): x0, y0, x1, y1
    bounds = np.full((4, len(first), int(slot.max()) + 1), np.nan)
    for k, v in enumerate((lo[:, 0], lo[:, 1], hi[:, 0], hi[:, 1])):
        bounds[k, group, slot] = v
    a, b = bounds[:, g, :, None], bounds[:, g + 1, None, :]
    gx = np.maximum(np.maximum(a[0] - b[2], b[0] - a[2]), 0.0)
    gy = np.maximum(np.maximum(a[1] - b[3], b[1] - a[3]), 0.0)
    gap2 = (gx * gx + gy * gy).reshape(len(g), -1)  # NaN: no such part in that frame
    near = (gap2 <= JUMP_PX * JUMP_PX).any(axis=1)
    jump = ~near & np.isfinite(gap2).any(axis=1)
    out[first[g[jump] + 1] - 1] = True
    return out


def box_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Distance (px) between two convex quadrilaterals ``a``, ``b`` ((4, 2) corners in
    order): 0 when they overlap."""
    if _overlap(a, b):
        return 0.0
    return min(_point_quad_distance(a, b), _point_quad_distance(b, a))


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating axis test of two convex quadrilaterals."""
    for q in (a, b):
        edges = np.roll(q, -1, axis=0) - q
        normals = np.stack([-edges[:, 1], edges[:, 0]], 1)
        pa, pb = a @ normals.T, b @ normals.T
        if np.any((pa.max(0) < pb.min(0)) | (pb.max(0) < pa.min(0))):
            return False
    return True


def _point_quad_distance(points: np.ndarray, quad: np.ndarray) -> float:
    """Least distance from the (4, 2) ``points`` to the edges of ``quad``."""
    p0 = quad
    d = np.roll(quad, -1, axis=0) - quad
    rel = points[:, None, :] - p0[None, :, :]
    t = np.clip((rel * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    near = p0[None] + t[..., None] * d[None]
    return float(np.sqrt(((points[:, None, :] - near) ** 2).sum(-1)).min())


def _frame_gap(rows: _Rows, a: np.ndarray, b: np.ndarray) -> float:
    """Least distance (px) between any part box of rows ``a`` and any of rows ``b``."""
    return min(box_gap(rows.corners[i], rows.corners[j]) for i in a for j in b)


def _absorb_fragments(rows: _Rows, tracklets: list[_Tracklet]) -> None:
    """Mark each fragment's host (see the module docstring)."""
    first_run: dict[str, _Tracklet] = {}
    for t in tracklets:
        first_run.setdefault(t.name, t)
    firsts = np.array([t.first for t in tracklets])
    lasts = np.array([t.last for t in tracklets])
    sizes = np.array([len(t.frames) for t in tracklets])
    for t in tracklets:
        if first_run[t.name] is not t or len(t.frames) > FRAGMENT_MAX_FRAMES:
            continue
        # hosts: seen in all its frames (a tracklet's frames are consecutive), long-lived
        hosts = (firsts <= t.first) & (lasts >= t.last) & (sizes > len(t.frames))
        hosts &= sizes >= FRAGMENT_HOST_MIN_FRAMES
        best: tuple[float, _Tracklet] | None = None
        for k in np.flatnonzero(hosts):
            o = tracklets[k]
            during = o.rows[(rows.frame[o.rows] >= t.first) & (rows.frame[o.rows] <= t.last)]
            if (rows.part[during] == "shaft").any() and not _beyond_head(rows, t, during):
                continue  # a tool beside it, not its head cut off
            gap = max(
                _frame_gap(rows, t.rows[rows.frame[t.rows] == f], during[rows.frame[during] == f])
                for f in t.frames
            )
            if gap <= FRAGMENT_REACH_PX and (best is None or gap < best[0]):
                best = (gap, o)
        if best is not None:
            t.host = best[1]


#: A piece lies beyond a tool's head when the direction from the tool's head to it is
#: within this angle (deg) of the tool's shaft direction (distal).
BEYOND_HEAD_DEG = 30.0


def _beyond_head(rows: _Rows, t: _Tracklet, host: np.ndarray) -> bool:
    """Whether, in each of its frames, the piece ``t`` shows only parts the tool's rows
    ``host`` lack there and lies beyond the tool's head along its shaft (a head cut off
    by an occluder past the tool's wrist)."""
    for f in t.frames:
        mine = t.rows[rows.frame[t.rows] == f]
        theirs = host[rows.frame[host] == f]
        if np.isin(rows.part[mine], rows.part[theirs]).any():
            return False
        shaft = theirs[rows.part[theirs] == "shaft"]
        head = theirs[rows.part[theirs] != "shaft"]
        if len(shaft) == 0 or len(head) == 0:
            return False
        hc = np.average(rows.xy[head], axis=0, weights=np.maximum(rows.area[head], 1.0))
        distal = hc - rows.xy[shaft[0]]
        ahead = np.average(rows.xy[mine], axis=0, weights=np.maximum(rows.area[mine], 1.0)) - hc
        cos = float(distal @ ahead) / max(float(np.hypot(*distal) * np.hypot(*ahead)), 1e-9)
        if cos < math.cos(math.radians(BEYOND_HEAD_DEG)):
            return False
    return True


def _anchor(rows: _Rows, t: _Tracklet, frames: np.ndarray) -> np.ndarray:
    """(2,) px: where the tracklet's shaft enters the view in the first of ``frames``
    showing a shaft (its end away from the head; with no head in that frame, its end
    nearer the border), else its parts' centroid in ``frames[0]``."""
    for f in frames:
        sel = t.rows[rows.frame[t.rows] == f]
        shaft = sel[rows.part[sel] == "shaft"]
        if len(shaft) == 0:
            continue
        s = int(shaft[0])
        u = np.array([math.cos(math.radians(rows.angle[s])), math.sin(math.radians(rows.angle[s]))])
        ends = rows.xy[s] + np.outer([-0.5, 0.5], u) * rows.length[s]
        head = sel[rows.part[sel] != "shaft"]
        if len(head) and rows.area[head].sum() > 0:
            hc = np.average(rows.xy[head], axis=0, weights=rows.area[head])
            far = np.hypot(*(ends - hc).T)
            return ends[int(np.argmax(far))]
        border = np.minimum(ends, rows.extent - ends).min(axis=1)
        return ends[int(np.argmin(border))]
    sel = t.rows[rows.frame[t.rows] == frames[0]]
    weights = rows.area[sel] if rows.area[sel].sum() > 0 else None
    return np.average(rows.xy[sel], axis=0, weights=weights)


def link_cost(distance_px: float, gap_s: float, scale_px: float, same_name: bool) -> float:
    """Cost of linking a tracklet ending where its shaft entered the view to one starting
    ``distance_px`` away ``gap_s`` seconds later: the distance in ``scale_px`` units
    (:data:`LINK_SCALE_FRAC` of the image diagonal) plus :data:`LINK_GAP_PER_S` per second;
    a link the identity step made (``same_name``) :data:`LINK_SAME_NAME_BONUS` less and at
    most just under :data:`LINK_GATE`."""
    cost = distance_px / scale_px + LINK_GAP_PER_S * gap_s
    if same_name:
        cost = min(max(cost - LINK_SAME_NAME_BONUS, 0.0), 0.99 * LINK_GATE)
    return cost


def _links(rows: _Rows, tracklets: list[_Tracklet], fps: float) -> dict[int, int]:
    """Tracklet index -> the index of the tracklet it continues into (``tracklets`` in
    order of first frame)."""
    n = len(tracklets)
    if n < 2:
        return {}
    scale = LINK_SCALE_FRAC * float(np.hypot(*rows.extent))
    ends = [_anchor(rows, t, t.frames[::-1][:ANCHOR_FRAMES]) for t in tracklets]
    starts = [_anchor(rows, t, t.frames[:ANCHOR_FRAMES]) for t in tracklets]
    firsts = np.array([t.first for t in tracklets])
    max_gap = LINK_MAX_GAP_S * fps
    pairs: list[tuple[int, int, float]] = []
    for i, a in enumerate(tracklets):
        lo = int(np.searchsorted(firsts, a.last + 1, side="left"))
        hi = int(np.searchsorted(firsts, a.last + max_gap, side="right"))
        for j in range(lo, hi):
            b = tracklets[j]
            d = float(np.hypot(*(ends[i] - starts[j])))
            c = link_cost(d, (b.first - a.last) / fps, scale, a.name == b.name)
            if c <= LINK_GATE:
                pairs.append((i, j, c))
    return dict(sparse_gated_assignment(pairs, n, n, LINK_GATE))


def sparse_gated_assignment(
    pairs: list[tuple[int, int, float]], n: int, m: int, max_cost: float
) -> list[tuple[int, int]]:
    """:func:`~mistool.assignment.gated_assignment` of a sparse problem: the same pairs
    (up to ties) from the possible ``(row, col, cost)`` ``pairs`` alone (a whole
    sequence's tracklets: too many for a dense matrix, few candidates each).

    Solved by SciPy's sparse solver (``min_weight_full_bipartite_matching``, LAPJVsp) as
    one full matching: each row may also take its own "unmatched" column and each column
    its own "unmatched" row at ``max_cost``; those two pair up at no cost where their row
    and column could (every cost shifted by one: the solver needs positive weights).

    Args:
        pairs: ``(row, col, cost)`` with ``0 <= row < n``, ``0 <= col < m``, finite costs
            at most ``max_cost``; at most one per (row, col).
        n, m: rows and columns.
        max_cost: the gate (the cost of leaving a row or a column unmatched).

    Returns:
        The pairs ``(row, col)`` made, sorted by row.
    """
    if not pairs:
        return []
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import min_weight_full_bipartite_matching

    r = np.array([p[0] for p in pairs], dtype=np.int64)
    c = np.array([p[1] for p in pairs], dtype=np.int64)
    w = np.array([p[2] for p in pairs], dtype=np.float64)
    # left nodes: rows 0..n-1, then one "column unmatched" per column; right nodes:
    # columns 0..m-1, then one "row unmatched" per row
    left = np.concatenate([r, np.arange(n), n + np.arange(m), n + c])
    right = np.concatenate([c, m + np.arange(n), np.arange(m), m + r])
    weight = 1.0 + np.concatenate([w, np.full(n, max_cost), np.full(m, max_cost), np.zeros(len(w))])
    graph = coo_matrix((weight, (left, right)), shape=(n + m, m + n)).tocsr()
    rows, cols = min_weight_full_bipartite_matching(graph)
    return sorted((int(a), int(b)) for a, b in zip(rows, cols, strict=True) if a < n and b < m)


def _name_key(name: str) -> tuple[int, str]:
    """Sort key of a name: numbers in numeric order, before other names."""
    return (int(name), "") if name.isdigit() else (1 << 62, name)


def relink(table: TrackTable, fps: float) -> TrackTable:
    """A tracked sequence's names with fragments absorbed and broken lives relinked (see
    the module docstring).

    Args:
        table: a whole sequence's rows (``frame``, ``instrument``, ``part``, the part
            boxes: ``cx_px`` .. ``angle_deg``, ``area_px``, corners ``x1_px`` .. ``y4_px``),
            in any order; names from one identity step (merged masks).
        fps: frames per second (the link gate's time term).

    Returns:
        The table with instruments renamed (``"1"``, ``"2"``, ... in order of first
        appearance) and the rows of fragments' parts their tool already shows dropped; the
        very table passed in when nothing changed.
    """
    if table.num_rows == 0:
        return table
    rows = _Rows(table)
    tracklets = _tracklets(rows)
    _absorb_fragments(rows, tracklets)
    alive = [t for t in tracklets if t.host is None]
    succ = _links(rows, alive, fps)
    chain: dict[int, int] = {}
    for i in range(len(alive)):
        if i not in chain:
            chain[i] = i
        if i in succ:
            chain[succ[i]] = chain[i]
    label = np.empty(table.num_rows, dtype=np.int64)
    keep = np.ones(table.num_rows, dtype=bool)
    for i, t in enumerate(alive):
        label[t.rows] = chain[i]
    moved: set[tuple[int, int, str]] = set()
    for t in tracklets:
        if t.host is None:
            continue
        host = t.host
        label[t.rows] = label[host.rows[0]]
        for r in t.rows:  # one row per frame, instrument and part: the tool's own first
            f, part = int(rows.frame[r]), str(rows.part[r])
            own = host.rows[(rows.frame[host.rows] == f) & (rows.part[host.rows] == part)]
            key = (f, int(label[r]), part)
            keep[r] = len(own) == 0 and key not in moved
            moved.add(key)
    # chains numbered by first frame, ties in the identity step's order of its names
    heads = sorted(
        {chain[i] for i in range(len(alive))},
        key=lambda c: (alive[c].first, _name_key(alive[c].name)),
    )
    number = {c: str(k + 1) for k, c in enumerate(heads)}
    names = np.array([number[int(c)] for c in label], dtype=object)
    if keep.all() and np.array_equal(names.astype(str), rows.name):
        out = swap_heads(table, rows)
        return move_heads(out, rows if out is table else None)
    return move_heads(swap_heads(table.with_columns(instrument=names)[keep]))


def attachment_cost(head_xy: np.ndarray, anchor_xy: np.ndarray, axis: np.ndarray | None) -> float:
    """How badly a head part's box centre ``head_xy`` (2,) px hangs on ``anchor_xy``: with
    ``axis`` (a unit (2,) vector, the shaft's direction towards its distal end
    ``anchor_xy``), the distance from the shaft's axis line plus
    :data:`HEAD_ALONG_WEIGHT` times the distance along it from the distal end (a wrist);
    without, the distance between the centres (jaws to their wrist's centre). px."""
    u = None if axis is None else (float(axis[0]), float(axis[1]))
    return _attachment(
        float(head_xy[0]), float(head_xy[1]), (float(anchor_xy[0]), float(anchor_xy[1]), 0.0, u)
    )


_Anchor = tuple[float, float, float, "tuple[float, float] | None"]
"""Where a name's head part hangs in one frame: x, y px, its shaft's width px, the
shaft's unit direction towards its distal end (None: a point, the wrist's centre)."""


def _attachment(hx: float, hy: float, anchor: _Anchor) -> float:
    """:func:`attachment_cost` on plain floats."""
    dx, dy = hx - anchor[0], hy - anchor[1]
    u = anchor[3]
    if u is None:
        return math.hypot(dx, dy)
    return abs(dx * u[1] - dy * u[0]) + HEAD_ALONG_WEIGHT * abs(dx * u[0] + dy * u[1])


def _shaft_anchor(
    x: float, y: float, length: float, width: float, angle_deg: float, extent: np.ndarray
) -> _Anchor:
    """A shaft box's distal end (the end farther inside the view: a shaft comes from the
    border), its width and its direction towards that end."""
    a = math.radians(angle_deg)
    ux, uy = math.cos(a), math.sin(a)
    w, h = float(extent[0]), float(extent[1])
    ends = [(x + sg * 0.5 * length * ux, y + sg * 0.5 * length * uy, sg) for sg in (1.0, -1.0)]
    inside = [min(ex, w - ex, ey, h - ey) for ex, ey, _ in ends]
    ex, ey, sg = ends[1] if inside[1] > inside[0] else ends[0]
    return ex, ey, width, (sg * ux, sg * uy)


_Candidate = tuple[int, str, str, int, int, bool]
"""A swap found in one frame: ``(frame, name_a, name_b, row_a, row_b, strong)``, strong
when it gains more than :data:`HEAD_SWAP_MARGIN` (else :data:`HEAD_SWAP_KEEP_MARGIN`)."""

#: Part codes of :class:`_HeadRows`' keys.
_SHAFT, _WRIST, _CLASPER = 0, 1, 2


class _HeadRows:
    """The rows of the frames :func:`swap_heads` looks at, by (frame, name, part): one
    sorted integer key per row (``(frame * names + name) * 3 + part``, names numbered
    in :func:`_name_key` order), the last row of a key kept (as a dict filled in row
    order keeps it)."""

    def __init__(self, rows: _Rows, look: np.ndarray) -> None:
        self.rows = rows
        name = rows.name[look]
        unique = np.unique(name)
        self.names: list[str] = sorted(unique.tolist(), key=lambda n: (_name_key(n), n))
        rank = np.empty(len(unique), np.int64)
        rank[np.searchsorted(unique, self.names)] = np.arange(len(unique))
        code = np.full(len(look), -1, np.int64)
        part = rows.part[look]
        for c, p in ((_SHAFT, "shaft"), (_WRIST, "wrist"), (_CLASPER, "clasper")):
            code[part == p] = c
        kept = code >= 0
        self.m = len(self.names)
        key = (rows.frame[look] * self.m + rank[np.searchsorted(unique, name)]) * 3 + code
        order = np.flatnonzero(kept)[np.argsort(key[kept], kind="stable")]
        key, row = key[order], look[order]
        last = np.ones(len(key), dtype=bool)
        last[:-1] = key[1:] != key[:-1]
        self.key, self.row = key[last], row[last]

    @functools.cached_property
    def xy(self) -> tuple[list[float], list[float]]:
        """Every row's box centre x and y, as Python floats."""
        return self.rows.xy[:, 0].tolist(), self.rows.xy[:, 1].tolist()

    def find(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per key: its row (any where absent) and whether present."""
        at = np.minimum(np.searchsorted(self.key, keys), len(self.key) - 1)
        return self.row[at], self.key[at] == keys

    def by(self, frame: int) -> dict[tuple[str, str], int]:
        """One frame's ``(name, part) -> row``."""
        lo, hi = np.searchsorted(self.key, [frame * self.m * 3, (frame + 1) * self.m * 3])
        parts = ("shaft", "wrist", "clasper")
        return {
            (self.names[(k // 3) % self.m], parts[k % 3]): r
            for k, r in zip(self.key[lo:hi].tolist(), self.row[lo:hi].tolist(), strict=True)
        }

    def swap(self, frame: int, a: str, b: str, part: str, ra: int, rb: int) -> None:
        """``b``'s row of ``part`` in ``frame`` is now ``ra``, ``a``'s ``rb``."""
        c = _WRIST if part == "wrist" else _CLASPER
        base = frame * self.m
        ka = (base + self.names.index(a)) * 3 + c
        kb = (base + self.names.index(b)) * 3 + c
        at = np.searchsorted(self.key, [kb, ka])
        self.row[at] = (ra, rb)

    def candidates(self, part: str) -> list[_Candidate]:
        """The pairs of names whose rows of ``part`` attach better swapped (by
        :data:`HEAD_SWAP_KEEP_MARGIN` at least), each name in at most one pair per
        frame, in frame order: :func:`_pair_candidates` over the frames where exactly
        two names show ``part`` and a shaft, :func:`_frame_candidates` in the others."""
        c = _WRIST if part == "wrist" else _CLASPER
        base = self.key[self.key % 3 == c] // 3
        shaft, has = self.find(base * 3 + _SHAFT)
        base, shaft = base[has], shaft[has]
        head = self.find(base * 3 + c)[0]
        frame = base // self.m
        new = np.ones(len(frame), dtype=bool)
        new[1:] = frame[1:] != frame[:-1]
        starts = np.flatnonzero(new)
        count = np.diff(np.append(starts, len(frame)))
        i = starts[count == 2]  # the pair's first name in name order, then the second
        pairs = _PairRows(
            frame[i], base[i] % self.m, base[i + 1] % self.m,
            head[i], head[i + 1], shaft[i], shaft[i + 1],
        )  # fmt: skip
        if c == _CLASPER:  # a name's wrist (as swapped) anchors its jaws
            pairs.wrist_a, pairs.has_wrist_a = self.find(base[i] * 3 + _WRIST)
            pairs.wrist_b, pairs.has_wrist_b = self.find(base[i + 1] * 3 + _WRIST)
        out, odd = _pair_candidates(self, pairs, part)
        more = np.concatenate([frame[starts[count > 2]], odd]).astype(np.int64)
        for f in np.unique(more).tolist():
            out += _frame_candidates(self, f, self.by(f), part)
        out.sort(key=lambda cand: cand[0])  # (one source per frame: stable within it)
        return out


@dataclass
class _PairRows:
    """Per frame with exactly two names showing a head part and a shaft: the frame,
    the names' codes (in name order) and their rows of that part and of the shaft;
    for the jaws, each name's wrist row and whether it has one."""

    frame: np.ndarray
    a: np.ndarray
    b: np.ndarray
    head_a: np.ndarray
    head_b: np.ndarray
    shaft_a: np.ndarray
    shaft_b: np.ndarray
    wrist_a: np.ndarray | None = None
    has_wrist_a: np.ndarray | None = None
    wrist_b: np.ndarray | None = None
    has_wrist_b: np.ndarray | None = None


def _pair_candidates(
    heads: _HeadRows, pairs: _PairRows, part: str
) -> tuple[list[_Candidate], np.ndarray]:
    """:func:`_frame_candidates` of frames with two names, as column arithmetic: the
    same operations on the same floats, element by element (the cosines, sines and
    point distances by ``math``, as there); also the frames with a value that is not
    finite (left to :func:`_frame_candidates`: Python's ``min`` and numpy's differ on
    NaN)."""
    rows = heads.rows
    xy, length, width, angle = rows.xy, rows.length, rows.width, rows.angle

    def anchor(s: np.ndarray) -> tuple[np.ndarray, ...]:  # _shaft_anchor, by columns
        x, y, long = xy[s, 0], xy[s, 1], length[s]
        rad = list(map(math.radians, angle[s].tolist()))
        ux = np.fromiter(map(math.cos, rad), np.float64, len(rad))
        uy = np.fromiter(map(math.sin, rad), np.float64, len(rad))
        w, h = float(rows.extent[0]), float(rows.extent[1])
        px, py = x + 1.0 * 0.5 * long * ux, y + 1.0 * 0.5 * long * uy
        mx, my = x + -1.0 * 0.5 * long * ux, y + -1.0 * 0.5 * long * uy
        inside_p = np.minimum(np.minimum(np.minimum(px, w - px), py), h - py)
        inside_m = np.minimum(np.minimum(np.minimum(mx, w - mx), my), h - my)
        minus = inside_m > inside_p
        sg = np.where(minus, -1.0, 1.0)
        return np.where(minus, mx, px), np.where(minus, my, py), sg * ux, sg * uy

    ax, ay, aux, auy = anchor(pairs.shaft_a)
    bx, by, bux, buy = anchor(pairs.shaft_b)
    wa, wb = width[pairs.shaft_a], width[pairs.shaft_b]
    used = [ax, ay, aux, auy, bx, by, bux, buy, wa, wb]
    point_a = point_b = np.zeros(len(ax), dtype=bool)
    if pairs.wrist_a is not None and pairs.wrist_b is not None:
        point_a, point_b = pairs.has_wrist_a, pairs.has_wrist_b  # type: ignore[assignment]
        ax = np.where(point_a, xy[pairs.wrist_a, 0], ax)
        ay = np.where(point_a, xy[pairs.wrist_a, 1], ay)
        bx = np.where(point_b, xy[pairs.wrist_b, 0], bx)
        by = np.where(point_b, xy[pairs.wrist_b, 1], by)
        used += [ax, ay, bx, by]
    hax, hay = xy[pairs.head_a, 0], xy[pairs.head_a, 1]
    hbx, hby = xy[pairs.head_b, 0], xy[pairs.head_b, 1]
    used += [hax, hay, hbx, hby]

    def cost(hx: np.ndarray, hy: np.ndarray, to_a: bool) -> np.ndarray:  # _attachment
        x, y, ux, uy, point = (ax, ay, aux, auy, point_a) if to_a else (bx, by, bux, buy, point_b)
        dx, dy = hx - x, hy - y
        out = np.abs(dx * uy - dy * ux) + HEAD_ALONG_WEIGHT * np.abs(dx * ux + dy * uy)
        k = np.flatnonzero(point)
        if len(k):
            out[k] = np.fromiter(
                map(math.hypot, dx[k].tolist(), dy[k].tolist()), np.float64, len(k)
            )
        return out

    finite = np.logical_and.reduce([np.isfinite(v) for v in used])
    now = cost(hax, hay, True) + cost(hbx, hby, False)
    swapped = cost(hax, hay, False) + cost(hbx, hby, True)
    mean_width = 0.5 * (wa + wb)
    keep = finite & (swapped + HEAD_SWAP_KEEP_MARGIN * mean_width < now)
    strong = swapped + HEAD_SWAP_MARGIN * mean_width < now
    names = heads.names
    out: list[_Candidate] = [
        (f, names[a], names[b], ra, rb, s)
        for f, a, b, ra, rb, s in zip(
            pairs.frame[keep].tolist(), pairs.a[keep].tolist(), pairs.b[keep].tolist(),
            pairs.head_a[keep].tolist(), pairs.head_b[keep].tolist(), strong[keep].tolist(),
            strict=True,
        )
    ]  # fmt: skip
    return out, pairs.frame[~finite]


def _frame_candidates(
    heads: _HeadRows, f: int, by: dict[tuple[str, str], int], part: str
) -> list[_Candidate]:
    """One frame's (``(name, part) -> row``) pairs of names whose rows of ``part``
    attach better swapped (by :data:`HEAD_SWAP_KEEP_MARGIN` at least), each name in at
    most one pair."""
    rows, (x, y) = heads.rows, heads.xy
    out: list[_Candidate] = []
    names = sorted({n for n, p in by if p == part and (n, "shaft") in by}, key=_name_key)
    if len(names) < 2:
        return out
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


def _strong_frames(run: list[_Candidate]) -> int:
    """The most consecutive strong swaps in a run of consecutive frames."""
    best = now = 0
    for c in run:
        now = now + 1 if c[5] else 0
        best = max(best, now)
    return best


def swap_heads(table: TrackTable, rows: _Rows | None = None) -> TrackTable:
    """Head rows (wrist, then jaws: ``"clasper"``) swapped between two names where they
    hang on the other's shaft (or wrist) in at least :data:`HEAD_SWAP_MIN_FRAMES`
    consecutive frames, and in the frames next to them where they still do by
    :data:`HEAD_SWAP_KEEP_MARGIN` (see the module docstring); the very table when none
    is.

    Args:
        table: rows of a whole sequence (``frame``, ``instrument``, ``part``, the part
            boxes as :func:`relink` reads them), in any order.
        rows: the table's columns as :func:`relink` read them (None: read here).
    """
    if table.num_rows == 0:
        return table
    # A swap needs two rows of its head part in one frame: only such frames' rows are
    # looked at (the others' would give no candidate); none (one instrument): no swap.
    frame = np.asarray(table["frame"]).astype(np.int64)
    first = int(frame.min())
    busy = np.zeros(int(frame.max()) - first + 1, dtype=bool)
    part_of = np.asarray(table["part"])
    for part in ("wrist", "clasper"):
        busy |= np.bincount(frame[part_of == part] - first, minlength=len(busy)) >= 2
    if not busy.any():
        return table
    if rows is None:
        rows = _Rows(table)
    heads = _HeadRows(rows, np.flatnonzero(busy[frame - first]))
    names = rows.name.copy()
    swapped = False
    for part in ("wrist", "clasper"):  # the jaws' anchors are the wrists as swapped
        runs: dict[tuple[str, str], list[_Candidate]] = {}
        for c in heads.candidates(part):
            runs.setdefault((c[1], c[2]), []).append(c)
        for pair in runs.values():
            start = 0
            for j in range(1, len(pair) + 1):
                if j < len(pair) and pair[j][0] == pair[j - 1][0] + 1:
                    continue
                if _strong_frames(pair[start:j]) >= HEAD_SWAP_MIN_FRAMES:
                    for f, a, b, ra, rb, _ in pair[start:j]:
                        names[ra], names[rb] = b, a
                        heads.swap(f, a, b, part, ra, rb)
                    swapped = True
                start = j
    if not swapped:
        return table
    return table.with_columns(instrument=names.astype(object))


def _move_frames(frame: np.ndarray, name: np.ndarray, part: np.ndarray) -> np.ndarray:
    """The frames where one name shows a shaft and a wrist and another a shaft and no
    wrist (sorted): the only ones :func:`move_heads` can move a wrist in."""
    shaft, wrist = part == "shaft", part == "wrist"
    some = shaft | wrist
    unique, code = np.unique(name[some], return_inverse=True)
    m = len(unique)
    # one sorted key per (frame, name, shaft or wrist): a name's wrist right after its shaft
    key = np.unique(((frame[some] * m + code.reshape(-1)) << 1) | wrist[some])
    base, is_wrist = key >> 1, (key & 1).astype(bool)
    both = np.zeros(len(key), dtype=bool)
    both[:-1] = ~is_wrist[:-1] & is_wrist[1:] & (base[1:] == base[:-1])
    alone = ~is_wrist.copy()
    alone[:-1] &= ~both[:-1]
    mark = np.zeros(int(frame.max()) + 1, dtype=np.int8)
    mark[base[both] // m] |= 1
    mark[base[alone] // m] |= 2
    return np.flatnonzero(mark == 3)


def _wrist_moves(heads: _HeadRows, f: int, by: dict[tuple[str, str], int]) -> list[_Candidate]:
    """One frame's wrist rows that hang on another name's shaft better than on their own
    by more than :data:`HEAD_MOVE_MARGIN` of its widths, that name showing a shaft but no
    wrist: ``(frame, from, to, row, -1, True)``, each name giving and taking at most one
    (the largest gains first)."""
    rows, (x, y) = heads.rows, heads.xy
    anchors: dict[str, _Anchor] = {}
    for (n, p), r in by.items():
        if p == "shaft":
            anchors[n] = _shaft_anchor(
                x[r], y[r], float(rows.length[r]), float(rows.width[r]),
                float(rows.angle[r]), rows.extent,
            )  # fmt: skip
    takers = sorted((n for n in anchors if (n, "wrist") not in by), key=_name_key)
    found: list[tuple[float, str, str, int]] = []
    for a in sorted(anchors, key=_name_key):
        w = by.get((a, "wrist"))
        if w is None:
            continue
        own = _attachment(x[w], y[w], anchors[a])
        for b in takers:
            gain = own - _attachment(x[w], y[w], anchors[b])
            if gain > HEAD_MOVE_MARGIN * anchors[b][2]:
                found.append((gain, a, b, w))
    out: list[_Candidate] = []
    gave: set[str] = set()
    took: set[str] = set()
    for _, a, b, r in sorted(found, key=lambda c: -c[0]):  # (stable: ties in name order)
        if a not in gave and b not in took:
            out.append((f, a, b, r, -1, True))
            gave.add(a)
            took.add(b)
    return out


def move_heads(table: TrackTable, rows: _Rows | None = None) -> TrackTable:
    """Wrist rows given to the name whose shaft they hang on where that name shows no
    wrist, and the jaws with them (see :data:`HEAD_MOVE_MARGIN`); the very table when
    none is.

    A tool's wrist cut off by an occluder or taken with another tool's head by a split
    goes with that tool's name, whose own wrist is then missing (held-out seed 6 frames
    60-63 and 76-97, seed 14 frames 85-96: a name's wrist 200 px from its tool's, on the
    shaft of a name that shows none). Per frame, a name's wrist row goes to another
    name showing a shaft and no wrist when :func:`attachment_cost` to that name's shaft
    is lower by more than :data:`HEAD_MOVE_MARGIN` of that shaft's widths, over runs of
    at least :data:`HEAD_SWAP_MIN_FRAMES` consecutive frames of that pair; the giving
    name's jaws go too when the receiving name shows none and they lie nearer the moved
    wrist than the giving shaft's distal end. Rows move between names; none is added or
    dropped.

    Args:
        table: rows of a whole sequence (``frame``, ``instrument``, ``part``, the part
            boxes as :func:`relink` reads them), in any order.
        rows: the table's columns as :func:`relink` read them (None: read here).
    """
    if table.num_rows == 0:
        return table
    frame = np.asarray(table["frame"]).astype(np.int64)
    name = rows.name if rows is not None else np.asarray(table["instrument"]).astype(str)
    look = _move_frames(frame, name, np.asarray(table["part"]))
    if len(look) == 0:
        return table
    if rows is None:
        rows = _Rows(table)
    heads = _HeadRows(rows, np.flatnonzero(np.isin(frame, look)))
    by = {f: heads.by(f) for f in look.tolist()}
    runs: dict[tuple[str, str], list[_Candidate]] = {}
    for f in look.tolist():
        for c in _wrist_moves(heads, f, by[f]):
            runs.setdefault((c[1], c[2]), []).append(c)
    names = rows.name.copy()
    (x, y) = heads.xy
    moved = False
    for pair in runs.values():
        start = 0
        for j in range(1, len(pair) + 1):
            if j < len(pair) and pair[j][0] == pair[j - 1][0] + 1:
                continue
            if j - start >= HEAD_SWAP_MIN_FRAMES:
                for f, a, b, r, _, _ in pair[start:j]:
                    d = by[f]
                    if d.get((a, "wrist")) != r or (b, "wrist") in d:
                        continue  # (moved by another pair's run)
                    names[r] = b
                    del d[(a, "wrist")]
                    d[(b, "wrist")] = r
                    moved = True
                    jaws, s = d.get((a, "clasper")), d[(a, "shaft")]
                    if jaws is None or (b, "clasper") in d:
                        continue
                    end = _shaft_anchor(
                        x[s], y[s], float(rows.length[s]), float(rows.width[s]),
                        float(rows.angle[s]), rows.extent,
                    )  # fmt: skip
                    to_wrist = math.hypot(x[jaws] - x[r], y[jaws] - y[r])
                    if to_wrist < math.hypot(x[jaws] - end[0], y[jaws] - end[1]):
                        names[jaws] = b
                        del d[(a, "clasper")]
                        d[(b, "clasper")] = jaws
            start = j
    if not moved:
        return table
    return table.with_columns(instrument=names.astype(object))
