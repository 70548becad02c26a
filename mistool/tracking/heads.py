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
#: is expected receives none of it (its head went under the other's). The share is
#: counted on a 5 x 5 grid of the box (:func:`_covered`): 0.68 is 17 of the 25 points,
#: so a head expected three fifths under the other's (15 points) still takes the
#: pixels lying beside it (crowded scenes: 36 of the 108 sequences up, 6 down, at 0.5
#: -> 0.68; 0.76 and above lose a two-tool crossing, docs/tracking.md).
HEAD_UNDER_FRAC = 0.68


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
    inst: InstanceObservation,
    part: str,
    canvas: np.ndarray,
    bounds: np.ndarray,
    k: int,
    min_area: int,
) -> InstanceObservation | None:
    """``inst`` with part ``part`` made of the pixels painted on ``canvas`` (at
    ``bounds[0], bounds[1]``; their count and bounds ``bounds[k : k + 5]``, see
    :func:`mistool.kernels.split.hand_over_pixels`), dropped when too few; None when
    nothing is left."""
    parts = {p: o for p, o in inst.parts.items() if p != part}
    count, x0, y0, x1, y1 = bounds[k : k + 5].tolist()
    if count >= min_area:
        cx0, cy0 = bounds[:2].tolist()
        m = canvas[y0 - cy0 : y1 - cy0, x0 - cx0 : x1 - cx0].copy()  # (C order)
        obs = part_observation(part, m, x0, y0, min_area)
        if obs is not None:
            parts[part] = obs
    if not parts:
        return None
    ordered: dict[str, PartObservation] = {p: parts[p] for p in PARTS if p in parts}
    return make_instance(inst.label, ordered, inst.image_shape)


_NO_PIXELS = np.zeros((0, 0), np.uint8)


def _handed_over(
    mine: InstanceObservation,
    donor: InstanceObservation,
    part: str,
    want: RotatedBox,
    own: RotatedBox | None,
    min_area: int,
) -> tuple[InstanceObservation | None, InstanceObservation | None]:
    """The receiving tool's and the donor's instances after the hand-over of ``part``
    (see :func:`hand_over_heads`; ``want``: where the receiver expects it, ``own``:
    where the donor does): the donor's pixels within :data:`HEAD_CLAIM_PX` of ``want``
    and nearer to it than to ``own`` go to the receiver, the receiver's within that
    reach of ``own`` go to the donor (compiled, the new masks painted without the pixel
    lists: :func:`mistool.kernels.split.hand_over_pixels`). None for one left with
    nothing."""
    d = donor.parts[part]
    dmask = np.ascontiguousarray(d.mask).view(np.uint8)
    dx0, dy0 = int(d.offset[0]), int(d.offset[1])
    x0, y0, x1, y1 = dx0, dy0, dx0 + dmask.shape[1], dy0 + dmask.shape[0]
    m = mine.parts.get(part)
    mmask, mx0, my0 = _NO_PIXELS, 0, 0
    if m is not None:
        mmask = np.ascontiguousarray(m.mask).view(np.uint8)
        mx0, my0 = int(m.offset[0]), int(m.offset[1])
        x0, y0 = min(x0, mx0), min(y0, my0)
        x1, y1 = max(x1, mx0 + mmask.shape[1]), max(y1, my0 + mmask.shape[0])
    got = np.zeros((y1 - y0, x1 - x0), np.uint8)
    left = np.zeros((y1 - y0, x1 - x0), np.uint8)
    bounds = np.zeros(12, np.int64)
    bounds[0], bounds[1] = x0, y0
    u0, u1 = _unit(want.angle_deg)
    o = own if own is not None else want
    o0, o1 = _unit(o.angle_deg)
    kernels.hand_over_pixels(
        mmask, mx0, my0, dmask, dx0, dy0, want.cx, want.cy, u0, u1, 0.5 * want.length,
        0.5 * want.width, own is not None, o.cx, o.cy, o0, o1, 0.5 * o.length,
        0.5 * o.width, HEAD_CLAIM_PX, got, left, bounds,
    )  # fmt: skip
    return (
        _with_part(mine, part, got, bounds, 2, min_area),
        _with_part(donor, part, left, bounds, 7, min_area),
    )


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
                    continue  # (counted without painting the new masks: the usual answer)
                got, left = _handed_over(mine, donor, part, want, own, min_area)
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
