"""Heads handed back to their own tool after one frame's instances are named.

In merged masks a head (wrist, jaws) touching another tool in the mask, or cut off by an
occluder and lying against another tool's shaft, is grouped with that tool
(:func:`~mistool.tracking.observe_frame` sees no boundary between them). Geometry alone
often cannot tell (the jaws lie at the other shaft's end too); where each tool's head was
a few frames ago can. :func:`hand_over_heads` gives a named instance's head pixels that
lie where another named tool's head is expected, and nearer to it than to where their
own tool's head is expected, to that tool, when that tool does not show the part where
it is expected. Pure (no tracker state).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import cv2
import numpy as np

from mistool.kernels import split as kernels
from mistool.model import PARTS, InstanceObservation, PartObservation, RotatedBox
from mistool.tracking.instances import make_instance, part_observation, unit_vector

__all__ = ["HEAD_CLAIM_PX", "box_distance", "hand_over_heads"]

#: A head pixel is claimed by a tool's expected head box when it lies within this many
#: pixels of it (the box moved on the tool's velocity: a wrist turns, jaws open).
HEAD_CLAIM_PX = 8.0
#: Head parts handed over (the shaft is never: its pixels are the split's).
HEAD_PARTS = ("wrist", "clasper")


def box_distance(xy: np.ndarray, box: RotatedBox) -> np.ndarray:
    """(N,) distance (px) of points ``xy`` (N, 2) to a rotated box (0 inside): along and
    across its axes, beyond its half length and width (compiled:
    :func:`mistool.kernels.split.box_distances`, the float operations of the numpy
    ``|(xy - c) @ u| - length / 2`` ... ``np.hypot`` it replaces)."""
    u0, u1 = _unit(box.angle_deg)
    out = np.empty(len(xy), np.float64)
    kernels.box_distances(
        np.ascontiguousarray(xy, np.float64), box.cx, box.cy, u0, u1,
        0.5 * box.length, 0.5 * box.width, out,
    )  # fmt: skip
    return out


def _unit(angle_deg: float) -> tuple[float, float]:
    """:func:`~mistool.tracking.instances.unit_vector` as two floats."""
    t = math.radians(angle_deg)
    return math.cos(t), math.sin(t)


#: A tool whose head is expected at least this share under where another's same part
#: is expected receives none of it (its head went under the other's).
HEAD_UNDER_FRAC = 0.5


def _covered(a: RotatedBox, b: RotatedBox, n: int = 5) -> float:
    """The share of box ``a`` lying inside box ``b`` (on an n x n grid of points)."""
    u = unit_vector(a.angle_deg)
    v = np.array([-u[1], u[0]])
    s, t = _grid(n)
    pts = np.array([a.cx, a.cy]) + (s * a.length)[:, None] * u + (t * a.width)[:, None] * v
    return float((box_distance(pts, b) <= 0.0).mean())


@functools.cache
def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid over [-0.5, 0.5]^2, raveled (x, y) (computed once per n)."""
    s, t = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(-0.5, 0.5, n))
    return s.ravel(), t.ravel()


def _pixels(inst: InstanceObservation, part: str) -> np.ndarray:
    """(N, 2) x, y of the part's pixels (float), row by row (``np.nonzero``'s order, by
    OpenCV's ``findNonZero``: ~2x faster)."""
    obs = inst.parts[part]
    nz = cv2.findNonZero(obs.mask.view(np.uint8))
    if nz is None:
        return np.zeros((0, 2))
    return nz.reshape(-1, 2).astype(np.float64) + obs.offset


def _with_part(
    inst: InstanceObservation, part: str, xy: np.ndarray, min_area: int
) -> InstanceObservation | None:
    """``inst`` with part ``part`` made of the pixels ``xy`` (dropped when too few);
    None when nothing is left."""
    parts = {p: o for p, o in inst.parts.items() if p != part}
    if len(xy) >= min_area:
        ij = xy.astype(np.int64)
        xs, ys = ij[:, 0], ij[:, 1]  # (a column's min and max: numpy's over axis 0 of
        x0, y0 = int(xs.min()), int(ys.min())  # (N, 2) is ~10x slower)
        x1, y1 = int(xs.max()) + 1, int(ys.max()) + 1
        m = np.zeros((y1 - y0, x1 - x0), np.uint8)
        m[ij[:, 1] - y0, ij[:, 0] - x0] = 255
        obs = part_observation(part, m, int(x0), int(y0), min_area)
        if obs is not None:
            parts[part] = obs
    if not parts:
        return None
    ordered: dict[str, PartObservation] = {p: parts[p] for p in PARTS if p in parts}
    return make_instance(inst.label, ordered, inst.image_shape)


def _shows(inst: InstanceObservation, part: str, box: RotatedBox, min_area: int) -> bool:
    """Whether the instance shows ``part`` where ``box`` expects it: at least
    ``min_area`` of its pixels within :data:`HEAD_CLAIM_PX` of the box (each pixel's
    :func:`box_distance`; compiled, only the pixels near the box looked at, counting
    stopped at ``min_area``: :func:`mistool.kernels.split.shown_near`)."""
    if part not in inst.parts:
        return False
    obs = inst.parts[part]
    u0, u1 = _unit(box.angle_deg)
    mask = np.ascontiguousarray(obs.mask).view(np.uint8)
    return bool(
        kernels.shown_near(
            mask, int(obs.offset[0]), int(obs.offset[1]), box.cx, box.cy, u0, u1,
            0.5 * box.length, 0.5 * box.width, HEAD_CLAIM_PX, min_area,
        )
    )  # fmt: skip


def hand_over_heads(
    instances: Sequence[InstanceObservation | None],
    expected: Sequence[dict[str, RotatedBox]],
    min_area: int,
) -> list[InstanceObservation | None]:
    """One frame's named instances with head pixels handed back to their own tool.

    Args:
        instances: per named tool, its instance this frame (None: not seen).
        expected: per tool (same order), where its head parts are expected this frame
            (part -> box; parts with no recent sighting left out).
        min_area: fewest pixels a part keeps, and a hand-over moves.

    A tool receives a head part when its instance does not show it where expected
    (fewer than ``min_area`` pixels within :data:`HEAD_CLAIM_PX` of the box): another
    instance's pixels of that part within that reach of the box, and nearer to it than
    to where the other's own head is expected, are moved to it (at least ``min_area``;
    none when the tool's box lies at least :data:`HEAD_UNDER_FRAC` inside where the
    other's is expected: its head went under the other's),
    and its own pixels of that part lying where the other's is expected go the other
    way. A hand-over that would leave either instance empty is not made; a tool with no
    instance receives nothing.

    Returns:
        The instances, those changed replaced (same order).
    """
    out = list(instances)
    for r, mine in enumerate(out):
        if mine is None:
            continue
        for part in HEAD_PARTS:
            want = expected[r].get(part)
            if want is None or _shows(mine, part, want, min_area):
                continue
            for d, donor in enumerate(out):
                if d == r or donor is None or part not in donor.parts:
                    continue
                own = expected[d].get(part)
                if own is not None and _covered(want, own) >= HEAD_UNDER_FRAC:
                    continue  # expected under the other's head: hidden by it
                if _claimed(donor, part, want, own) < min_area:
                    continue  # (counted without the pixel lists: the usual answer)
                xy = _pixels(donor, part)
                to_me = box_distance(xy, want)
                to_own = box_distance(xy, own) if own is not None else np.full(len(xy), np.inf)
                move = (to_me <= HEAD_CLAIM_PX) & (to_me < to_own)
                if int(move.sum()) < min_area:
                    continue
                kept, back = _own_and_theirs(mine, part, own)
                got = _with_part(mine, part, np.concatenate([kept, xy[move]]), min_area)
                left = _with_part(donor, part, np.concatenate([xy[~move], back]), min_area)
                if got is None or left is None:
                    continue
                out[r], out[d] = got, left
                mine = got
                break
    return out


def _claimed(inst: InstanceObservation, part: str, want: RotatedBox, own: RotatedBox | None) -> int:
    """How many of the instance's pixels of ``part`` :func:`hand_over_heads` would move
    to the tool expecting it at ``want``: within :data:`HEAD_CLAIM_PX` of ``want`` and
    nearer to it than to ``own`` (their :func:`box_distance`; compiled, one pass over the
    mask without its pixel list: :func:`mistool.kernels.split.claimed`)."""
    obs = inst.parts[part]
    u0, u1 = _unit(want.angle_deg)
    o = own if own is not None else want
    o0, o1 = _unit(o.angle_deg)
    mask = np.ascontiguousarray(obs.mask).view(np.uint8)
    return int(
        kernels.claimed(
            mask, int(obs.offset[0]), int(obs.offset[1]), want.cx, want.cy, u0, u1,
            0.5 * want.length, 0.5 * want.width, own is not None, o.cx, o.cy, o0, o1,
            0.5 * o.length, 0.5 * o.width, HEAD_CLAIM_PX,
        )
    )  # fmt: skip


def _own_and_theirs(
    inst: InstanceObservation, part: str, theirs: RotatedBox | None
) -> tuple[np.ndarray, np.ndarray]:
    """The instance's pixels of ``part`` split into those it keeps and those lying where
    another tool expects that part (``theirs``: within :data:`HEAD_CLAIM_PX`): a swap."""
    if part not in inst.parts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    xy = _pixels(inst, part)
    if theirs is None:
        return xy, xy[:0]
    back = box_distance(xy, theirs) <= HEAD_CLAIM_PX
    return xy[~back], xy[back]
