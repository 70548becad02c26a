"""Identity across frames: :class:`IdentityTracker` names instruments consistently.

With ``config.instruments`` (own label values) the name is the instance's label. In
merged masks each frame runs one pipeline, as trackers such as ByteTrack or norfair do::

    predict every live track (its motion model)  ->  cost matrix (:func:`track_cost`)
    -> one gated assignment  ->  crossing handler (tracks hidden in a matched blob; the
    blob split between them)  ->  entry handler (a blob with more shafts entering the
    view than tracks in it, split on those shafts)  ->  update tracks, new names

A track is in one :class:`TrackState`. Names are ``"1"``, ``"2"``, ... in order of first
appearance.

- Crossing: when two instruments touch they form one instance. The instance keeps the
  name of the best match; the other track, whose predicted position lies inside that
  instance, is kept alive (``HIDDEN``), and both *coast* on their predicted motion (their
  state is not polluted by the merged blob's centroid) until they separate, when position
  and shaft direction tell them apart again. :meth:`IdentityTracker.resolve` also splits
  the blob between them (:func:`~mistool.tracking.split.split_instance`).
- A piece of an instrument taken for another (a head an occluder cut off, seen for a
  few frames, never with a shaft, never at the image border unless it appeared with
  that instrument) is forgotten when it is found inside that instrument's blob
  (``ABSORBED``), so the blob keeps its name.
- Touching since they appeared (``resolve`` only): a blob whose shaft pixels enter the
  view at more places on the image border than instruments known in it is split on
  those shafts; each known instrument takes the piece entering nearest to where its own
  shaft last entered, the others get new names.
- Leaving and coming back: a track unseen for more than :data:`LOST_AFTER_FRAMES` frames
  is ``LOST``; for up to ``max_gap_s`` seconds a new instance near where it was last seen
  (within :attr:`CostWeights.lost_scale_frac` of the image diagonal, growing with time,
  or its shaft entering the view near where the track's last did, and similar in shaft
  direction) gets its old name back; after that gap it is forgotten.

Identity needs only the instances (boxes, areas, centroids and the part pixel crops,
which a split uses), never the label image: the per-frame work can run elsewhere.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from mistool.assignment import gated_assignment
from mistool.config import Config
from mistool.model import InstanceObservation, PartObservation, RotatedBox
from mistool.tracking.heads import HEAD_CLAIM_PX, HEAD_PARTS, hand_over_heads
from mistool.tracking.instances import angle_diff_deg, unit_vector
from mistool.tracking.motion import ConstantVelocity
from mistool.tracking.split import (
    HEAD_LENGTH_WIDTHS,
    BlobPixels,
    HeadAnchor,
    SplitFit,
    border_entries,
    border_runs,
    fit_split,
    reference_boxes,
    shaft_support,
    split_on_entries,
    split_with_heads,
)

__all__ = [
    "CostWeights",
    "IdentityTracker",
    "Track",
    "TrackState",
    "distinct_lanes",
    "shaft_entry",
    "track_cost",
]

#: A track unseen for more than this many frames is lost: it is looked for near where
#: it was last seen (its prediction goes no further than this many frames).
LOST_AFTER_FRAMES = 5
#: A matched instance holds another (unmatched) track too when its area grew by this
#: factor over its track's, or its track is already coasting in a blob, and the other
#: track's prediction lies in its bounds ...
BLOB_GROWTH = 1.3
#: ... widened by this fraction of their size on each side.
BLOB_MARGIN_FRAC = 0.15
#: ... and the other track was seen within this many frames (or a quarter of the
#: tracker's memory, if longer).
HIDDEN_MAX_GAP_FRAMES = 3
#: Splitting a crossing blob: the first motion hypothesis moves each track's last boxes
#: seen apart by at most this many frames of its velocity (slowing to a stop when the
#: tools met); the second all the way (keeping on).
SPLIT_STOP_FRAMES = 5
#: The second hypothesis is fitted only when the first fails or its score (RMS distance
#: of a shaft's pixels to its axis, half-widths; a full rectangle gives 0.58) is above
#: this.
SPLIT_GOOD_SCORE = 0.65
#: Splitting a blob that holds tools with no expected shaft: shaft pixels farther than
#: this (squared shaft half-widths) from every fitted axis are theirs (left out of the
#: fit; a lone such tool takes them).
SPLIT_OTHERS_D2 = 9.0
#: A piece of a blob split between at least this many tools measures its tool's motion
#: across its shaft, but along it no faster than the tool went before: the cuts between
#: three or four tools move from frame to frame, and a piece's centroid slid along its
#: shaft by up to 140 px a frame (the velocity then carried the tool's expected shaft out
#: of the blob). Two tools crossing are cut across their shafts: their pieces' motion
#: is measured as is.
CROWDED_SPLIT_TRACKS = 3
#: ... and keeps its velocity when one of its head parts lies farther than this many
#: shaft widths from where its tool's same part is expected (:meth:`Track.expected_heads`):
#: the head changed hands between the pieces, the tool did not move (a four-tool split
#: of fresh seed 55, frames 141-149).
HEAD_JUMP_WIDTHS = 1.0
#: A head part seen this many frames ago or fewer is expected where it was, moved on the
#: track's velocity (for at most :data:`SPLIT_STOP_FRAMES`), when heads are handed back
#: to their own tool (:func:`~mistool.tracking.heads.hand_over_heads`).
HEAD_MEMORY_FRAMES = 10
#: A reference head part longer than this many of its shaft's widths is no part of its
#: tool's shape (:func:`_one_tools_heads`) when another track's head, remembered
#: within :data:`HEAD_MEMORY_FRAMES` frames of the reference, lies in its box: the box
#: spans that tool's head too (held-out seed 19 frame 50: a 215 x 40 px jaws box, 2.9
#: widths, over both tools' jaws). Without another head in it, such a box is kept: a
#: wrist alone reaches too short there (seed 2 and two-tool seed 2 fell with a cap of 2
#: widths on every long box).
HEAD_OVER_OTHER_WIDTHS = 2.0
#: A reference head part with two 8-connected label components of at least this many px
#: each is no part of its tool's shape (:func:`_one_tools_heads`): another tool's wrist
#: or jaws touching this tool's instance while it was seen apart (twox seed 1 frames
#: 122-127 and 520-545, fresh seed 55 frame 102: each component one tool's, by a
#: distinct-label render). Smaller pieces are kept: a wrist or jaws cut by an occluder
#: or another tool's shaft, or a jaws' two open blades (500-1,500 px each in the same
#: renders at 300-400 px, where the rule cost two-tool seed 2 and twox seed 1).
#: A piece of a blob split between at least :data:`CROWDED_SPLIT_TRACKS` tools with
#: such a head part does not renew its tool's remembered head (:attr:`Track.heads`):
#: the last box before it stands (+0.02 on the 108 crowd sets; in two-tool crossings
#: the same rule cost cross2500 and twox seed 3 ~0.5 each).
HEAD_PIECE_PX = 500
_EIGHT_CONNECTED = np.ones((3, 3), bool)
#: A track seen for at most this many frames, never with a shaft, found hidden in the
#: blob of an older track that could not be split, was a piece of it (absorbed); at the
#: image border only if both were first seen in the same frame (see :func:`_fragment_of`).
FRAGMENT_MAX_SEEN = 3
#: A tool whose shape is a redone entry split's piece (:attr:`Track.boxes_entering`) may
#: still be entering the view while it crosses another: its shape is renewed from a
#: piece of a two-tool crossing split with one shaft entering and a head part whose
#: shaft box is longer than its shape's by this factor (4-e17-occ-s4-150 frames 39-60:
#: tool 2's 256 px shape from frame 39 stayed frozen while its shaft went ~150 px deeper,
#: and its expected wrist took tool 1's in frames 48-60).
ENTERING_GROWTH = 1.2
#: A redone entry split's piece (:meth:`IdentityTracker._heads_given_away`) with fewer
#: head pixels than this is no reference shape: its tool keeps the shape it had. The
#: redo is taken for a few pixels of a head (they are the tool's), but a shape with a
#: sliver of head, or none, then stands through the crossing that follows (dev seed 65
#: frame 72: tool 4's piece held 57 px of its wrist, a 20 x 6 px box, and 22 frames of
#: crossing later the split gave tool 4's wrist to tool 2; dev seed 79 frame 113: the
#: other tool's piece, its head taken back by the redo, held none).
REDONE_SHAPE_HEAD_PX = 180


class TrackState(enum.Enum):
    """Where a track stands after the last frame."""

    TRACKED = "tracked"
    """Seen apart from others in its last frame."""
    COASTING = "coasting"
    """In a blob shared with another instrument, the blob carrying its name: it moves on
    its predicted motion (the blob's centroid is not its own)."""
    HIDDEN = "hidden"
    """In a blob carrying another instrument's name (coasting too)."""
    LOST = "lost"
    """Unseen for more than :data:`LOST_AFTER_FRAMES` frames (not in a blob)."""
    ABSORBED = "absorbed"
    """A piece of another instrument taken for one (a head cut off by an occluder, seen
    for at most :data:`FRAGMENT_MAX_SEEN` frames, never with a shaft), found inside that
    instrument's blob: forgotten."""

    @property
    def coasting(self) -> bool:
        """Inside a shared blob (``COASTING`` or ``HIDDEN``)."""
        return self is _COASTING or self is _HIDDEN


# The states as module names: ``TrackState.TRACKED`` is looked up through the enum's
# metaclass (~0.2 us, ~10x a module name's), a few times per track and frame.
_TRACKED, _COASTING, _HIDDEN, _LOST, _ABSORBED = (
    TrackState.TRACKED,
    TrackState.COASTING,
    TrackState.HIDDEN,
    TrackState.LOST,
    TrackState.ABSORBED,
)


@dataclass(frozen=True)
class CostWeights:
    """The terms of :func:`track_cost` and the assignment's gate."""

    max_cost: float = 3.0
    """Gate: a match costs at most this much (the distance term is in units of the
    instrument's size, sqrt(area))."""
    angle: float = 1.5
    """Weight of the shaft direction difference, per 90 deg (times the elongation)."""
    area: float = 0.3
    """Weight of |log(area ratio)|."""
    gap: float = 0.02
    """Extra cost per frame unseen, so recently seen instruments are preferred."""
    hidden_penalty: float = 0.5
    """Extra cost for a track hidden in another's blob to take that blob's name."""
    lost_search_growth: float = 0.25
    """A lost track is searched for within a distance that grows by this many of its
    sizes per second unseen ..."""
    lost_scale_frac: float = 0.1
    """... starting from at most this fraction of the image diagonal (an instrument comes
    back near where it left, through its trocar; a large one is no wider gate)."""
    entry_scale_frac: float = 0.1
    """Where shafts enter the view: a track takes an instance whose shaft enters the view
    far from where its own last entered at a cost of :attr:`entry` (and, splitting a
    blob on its shafts' entries, of one) per this fraction of the image diagonal (a
    shaft pivots about its trocar: its entry point moves slowly)."""
    entry: float = 0.5
    """Weight of that entry-point distance in :func:`track_cost`."""


@dataclass
class Track:
    """An instrument the tracker has seen (mutable state)."""

    name: str
    """The instrument's name."""
    motion: ConstantVelocity
    """Where the instrument itself is believed to be (its pixels' centroid), px."""
    last_frame: int
    """Last frame it was updated (seen, or coasting in a blob)."""
    area: float
    """Its pixel count when last seen apart."""
    angle: float | None
    """Shaft (or largest part) direction, deg in [0, 180)."""
    elongation: float
    """(length - width) / length of that box, 0..1."""
    state: TrackState = TrackState.TRACKED
    """See :class:`TrackState`."""
    size: float = 0.0
    """Largest sqrt(area) seen, px: the instrument's scale."""
    boxes_frame: int = 0
    """The frame of :attr:`boxes`."""
    shaftless: int = 0
    """Frames in a row it was seen apart from others without a shaft."""
    seen: int = 1
    """Frames it was updated in."""
    entry: np.ndarray | None = None
    """(2,) px where its shaft last entered the view alone."""
    at_border: bool = False
    """Whether it was ever seen touching the image border (entering the view)."""
    heads: dict[str, tuple[RotatedBox, int]] = field(default_factory=dict)
    """Per head part, its last box seen under this name and that frame."""
    in_blob: bool = False
    """Whether it was last updated inside a blob shared with others (a split's piece,
    or coasting)."""
    first_frame: int = 0
    """The frame it was first seen in."""
    boxes_entering: bool = False
    """Whether :attr:`boxes` are a redone entry split's piece with one shaft entering the
    view (:meth:`IdentityTracker._heads_given_away`): the tool may still be coming in,
    and its shape is renewed from a crossing piece showing its shaft grown (see
    :data:`ENTERING_GROWTH`)."""
    _boxes: dict[str, RotatedBox] | None = field(default=None, repr=False)
    _boxes_from: tuple[InstanceObservation, list[tuple[np.ndarray, int]]] | None = field(
        default=None, repr=False
    )

    @property
    def boxes(self) -> dict[str, RotatedBox] | None:
        """Last part boxes seen apart from others (with a shaft), at :attr:`boxes_frame`:
        the instance's :func:`~mistool.tracking.split.reference_boxes`, made at their
        first read (:meth:`set_boxes_from`: a track is updated every frame, its boxes
        read only when it is split from a blob; the tracker makes them with
        :meth:`make_boxes`, which knows the other tracks' heads)."""
        source = self._boxes_from
        if source is not None:
            self._boxes, self._boxes_from = _one_tools_heads(_shape_of(*source)), None
        return self._boxes

    @boxes.setter
    def boxes(self, value: dict[str, RotatedBox] | None) -> None:
        self._boxes, self._boxes_from = value, None

    @property
    def has_boxes(self) -> bool:
        """Whether :attr:`boxes` is not None (without making them)."""
        return self._boxes_from is not None or self._boxes is not None

    @property
    def boxes_pending(self) -> bool:
        """Whether :attr:`boxes` are still to be made (:meth:`make_boxes`)."""
        return self._boxes_from is not None

    def make_boxes(self, other_heads: Sequence[tuple[float, float]]) -> None:
        """Make :attr:`boxes` now, with the centres of the other tracks' heads remembered
        near :attr:`boxes_frame` (:func:`_one_tools_heads`)."""
        source = self._boxes_from
        if source is not None:
            boxes = _one_tools_heads(_shape_of(*source), other_heads)
            self._boxes, self._boxes_from = boxes, None

    def set_boxes_from(
        self, inst: InstanceObservation, runs: list[tuple[np.ndarray, int]], frame: int
    ) -> None:
        """:attr:`boxes` are ``reference_boxes(inst, runs)`` (made when first read),
        seen at ``frame``."""
        self._boxes, self._boxes_from = None, (inst, runs)
        self.boxes_frame = frame
        self.boxes_entering = False

    def expected_heads(self, frame: int) -> dict[str, RotatedBox]:
        """Where its head parts seen at most :data:`HEAD_MEMORY_FRAMES` ago are expected
        at ``frame``: moved on its velocity for at most :data:`SPLIT_STOP_FRAMES`."""
        out = {}
        vx, vy = self.motion.vx, self.motion.vy
        for p, (b, seen) in self.heads.items():
            gap = frame - seen
            if 0 < gap <= HEAD_MEMORY_FRAMES:
                n = min(gap, SPLIT_STOP_FRAMES)
                out[p] = RotatedBox(b.cx + vx * n, b.cy + vy * n, b.length, b.width, b.angle_deg)
        return out

    def predict_steps(self, frame: int) -> int:
        """Frames of motion to predict at ``frame``: the gap, at most
        :data:`LOST_AFTER_FRAMES` when lost (looked for near where it was last)."""
        gap = frame - self.last_frame
        return LOST_AFTER_FRAMES if self.state is _LOST else gap

    def predict(self, frame: int) -> np.ndarray:
        """(2,) px: the expected centroid at ``frame``."""
        return self.motion.predict(self.predict_steps(frame))

    def predict_xy(self, frame: int) -> tuple[float, float]:
        """:meth:`predict` as two floats (the same values)."""
        return self.motion.predict_xy(self.predict_steps(frame))


def _shape_of(
    inst: InstanceObservation, runs: list[tuple[np.ndarray, int]]
) -> dict[str, RotatedBox]:
    """The instance's :func:`~mistool.tracking.split.reference_boxes` without its head
    parts of two label components of at least :data:`HEAD_PIECE_PX` each (two tools'
    wrists or jaws), when another head part is left (as :func:`_without_long_heads`)."""
    boxes = reference_boxes(inst, runs)
    if "shaft" not in boxes or len(boxes) < 3:
        return boxes  # (no head part, or one: nothing to leave out)
    out = {p: b for p, b in boxes.items() if p == "shaft" or not _two_pieces(inst.parts[p])}
    return boxes if len(out) == len(boxes) or len(out) < 2 else out


def _two_pieces(part: PartObservation) -> bool:
    """Whether the part's pixels hold two 8-connected components of at least
    :data:`HEAD_PIECE_PX` each."""
    if part.area_px < 2 * HEAD_PIECE_PX:
        return False
    # (SciPy's labelling, one thread: OpenCV's connectedComponents wakes its thread pool,
    # ~0.1 ms of CPU a frame on crowded sequences for ~0.4 calls a frame)
    from scipy import ndimage

    labels, count = ndimage.label(part.mask, structure=_EIGHT_CONNECTED)
    if count < 2:
        return False  # (one component: the usual part; its count not needed)
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    return int(np.count_nonzero(sizes >= HEAD_PIECE_PX)) >= 2


def _one_tools_heads(
    boxes: dict[str, RotatedBox], other_heads: Sequence[tuple[float, float]] = ()
) -> dict[str, RotatedBox]:
    """A reference shape without its head parts longer than :data:`HEAD_LENGTH_WIDTHS`
    of its shaft's widths (the farthest a split lets a head reach beyond its shaft),
    when another head part is left: such a box spans two tools' heads (jaws touching
    another tool's, grouped with this tool's instance by ``observe_frame`` while it was
    seen apart), and would give the tool that whole reach in every split (the head
    segments of :func:`~mistool.tracking.split.fit_split`), taking the other tools'
    heads with it; the part left bounds the reach to its own extent. (With no head part
    left, the split would reach as far and lose the shaft's distal side: kept.) Then,
    on what is left and on the same terms, without its head parts longer than
    :data:`HEAD_OVER_OTHER_WIDTHS` with one of ``other_heads`` (the centres of other
    tracks' heads remembered near the reference's frame) in their box."""
    shaft = boxes.get("shaft")
    if shaft is None:
        return boxes
    boxes = _without_long_heads(boxes, HEAD_LENGTH_WIDTHS * shaft.width, lambda b: True)
    if not other_heads:
        return boxes
    return _without_long_heads(
        boxes,
        HEAD_OVER_OTHER_WIDTHS * shaft.width,
        lambda b: any(_holds(b, x, y) for x, y in other_heads),
    )


def _without_long_heads(
    boxes: dict[str, RotatedBox], reach: float, dropped: Callable[[RotatedBox], bool]
) -> dict[str, RotatedBox]:
    """``boxes`` without the head parts longer than ``reach`` for which ``dropped`` holds,
    when that leaves another head part (two boxes or more), else ``boxes`` as they are."""
    out = {
        p: b
        for p, b in boxes.items()
        if p == "shaft" or max(b.length, b.width) <= reach or not dropped(b)
    }
    return boxes if len(out) == len(boxes) or len(out) < 2 else out


def _holds(box: RotatedBox, x: float, y: float) -> bool:
    """Whether the point (x, y) lies in the rotated box (its edges included)."""
    t = math.radians(box.angle_deg)
    c, s = math.cos(t), math.sin(t)
    dx, dy = x - box.cx, y - box.cy
    return abs(dx * c + dy * s) <= 0.5 * box.length and abs(dy * c - dx * s) <= 0.5 * box.width


def _head_jumped(t: Track, inst: InstanceObservation, frame: int) -> bool:
    """One of the instance's head parts lies farther than :data:`HEAD_JUMP_WIDTHS` shaft
    widths (its shaft's, else the expected part's width) from where ``t``'s same part is
    expected at ``frame``."""
    expected = t.expected_heads(frame)
    shaft = inst.parts.get("shaft")
    for p in HEAD_PARTS:
        part = inst.parts.get(p)
        e = expected.get(p)
        if part is not None and e is not None:
            reach = HEAD_JUMP_WIDTHS * (shaft.box.width if shaft is not None else e.width)
            if math.hypot(part.box.cx - e.cx, part.box.cy - e.cy) > reach:
                return True
    return False


def _area_of(part: PartObservation) -> int:
    """A part's pixel count (the key that picks an instance's largest part)."""
    return part.area_px


def _head_area(inst: InstanceObservation) -> int:
    """An instance's head pixels (all its head parts)."""
    return sum(inst.parts[p].area_px for p in HEAD_PARTS if p in inst.parts)


def _appearance(inst: InstanceObservation) -> tuple[float | None, float]:
    """(direction deg or None, elongation) of the shaft, or the largest part."""
    part = inst.parts.get("shaft") or max(inst.parts.values(), key=_area_of)
    box = part.box
    if box.length <= 0:
        return None, 0.0
    return box.angle_deg, (box.length - box.width) / box.length


def shaft_entry(inst: InstanceObservation) -> np.ndarray | None:
    """(2,) px where the instance's one shaft enters the view, or None (no shaft at the
    border, or several: a blob)."""
    return _one_entry(border_runs(inst))


def _one_entry(runs: list[tuple[np.ndarray, int]]) -> np.ndarray | None:
    """The middle of the one border run, or None (none, or several: a blob)."""
    return runs[0][0][1] if len(runs) == 1 else None


def track_cost(
    t: Track,
    inst: InstanceObservation,
    frame: int,
    weights: CostWeights,
    fps: float,
    entry: np.ndarray | None = None,
) -> float:
    """Cost of giving instance ``inst`` the name of track ``t`` at ``frame`` (pure).

    Distance from the track's prediction in units of its size (a lost track's size
    bounded by :attr:`CostWeights.lost_scale_frac` of the image diagonal and growing
    with time unseen; for a lost track, the distance between where the instance's shaft
    enters the view and where the track's last did, when shorter and within
    :attr:`CostWeights.entry_scale_frac` of the diagonal), plus direction and area
    terms, a per-frame-unseen term, and a penalty for a track hidden in another's blob,
    and the distance between where the instance's shaft enters the view (``entry``,
    :func:`shaft_entry`) and where the track's last did.
    """
    return _pair_cost(_TrackTerms(t, frame), _InstanceTerms(inst, entry), frame, weights, fps)


class _TrackTerms:
    """What :func:`track_cost` reads of a track at one frame, computed once per frame
    (plain floats: the same values as the numpy arrays they come from)."""

    __slots__ = ("angle", "area", "elongation", "entry", "gap", "last_frame", "lost",
                 "px", "py", "size", "state", "track")  # fmt: skip

    def __init__(self, t: Track, frame: int) -> None:
        self.track = t
        self.state = t.state
        self.lost = t.state is _LOST
        self.gap = frame - t.last_frame
        self.size = t.size
        self.area = t.area
        self.angle = t.angle
        self.elongation = t.elongation
        self.px, self.py = t.predict_xy(frame)
        self.entry = None if t.entry is None else t.entry.tolist()


class _InstanceTerms:
    """What :func:`track_cost` reads of an instance (and its shaft's ``entry``),
    computed once per frame."""

    __slots__ = ("angle", "area", "cx", "cy", "diag", "elongation", "entry", "has_shaft",
                 "inst", "root")  # fmt: skip

    def __init__(self, inst: InstanceObservation, entry: np.ndarray | None) -> None:
        self.inst = inst
        self.cx, self.cy = inst.centroid_px
        self.area = inst.area_px
        self.root = math.sqrt(inst.area_px)
        self.angle, self.elongation = _appearance(inst)
        self.has_shaft = "shaft" in inst.parts
        shape = inst.image_shape
        self.diag = None if shape is None else math.hypot(*shape)
        self.entry = None if entry is None else entry.tolist()


def _pair_cost(
    t: _TrackTerms, i: _InstanceTerms, frame: int, weights: CostWeights, fps: float
) -> float:
    """:func:`track_cost` of precomputed terms (the same operations in the same order:
    the same bits)."""
    # (plain floats, numpy's values; np.hypot: the C library's, which math.hypot is not)
    dist = float(np.hypot(i.cx - t.px, i.cy - t.py))
    moved = 0.0
    if i.entry is not None and t.entry is not None and i.diag is not None:
        moved = float(np.hypot(i.entry[0] - t.entry[0], i.entry[1] - t.entry[1]))
    return _cost_of(t, i, weights, fps, dist, moved)


def _cost_of(
    t: _TrackTerms, i: _InstanceTerms, weights: CostWeights, fps: float, dist: float, moved: float
) -> float:
    """:func:`_pair_cost` given its distances: ``dist`` from the track's prediction to
    the instance's centroid, ``moved`` between their shafts' entries (0.0 unless both
    have one and the image's shape is known)."""
    gap = t.gap
    lost = t.lost
    # scale: the instrument's full size, also when it was last seen only partly
    scale = max(t.size, i.root, 10.0)
    if lost:  # unseen: the search area grows with time
        if i.diag is not None:  # from where it left, whatever its size
            scale = min(scale, weights.lost_scale_frac * i.diag)
        scale *= 1.0 + weights.lost_search_growth * (gap - LOST_AFTER_FRAMES) / fps
    # (the image's diagonal when both shafts enter the view: ``moved`` is measured)
    diag = i.diag if i.entry is not None and t.entry is not None else None
    if diag is not None and lost and moved <= weights.entry_scale_frac * diag:
        # a tool comes back through its trocar: its shaft enters where it left (its
        # centroid, predicted on from its exit, lies outside the view)
        dist = min(dist, moved)
    cost = dist / scale
    angle, elong = i.angle, i.elongation
    # an instrument coming back shows its head first: its direction is no shaft's
    if angle is not None and t.angle is not None and not (lost and not i.has_shaft):
        w = min(elong, t.elongation)
        cost += weights.angle * w * angle_diff_deg(angle, t.angle) / 90.0
    if t.state is _TRACKED:  # not a blob's area, nor an exit's partial one
        cost += weights.area * abs(math.log(max(i.area, 1) / max(t.area, 1.0)))
    cost += weights.gap * (gap - 1)
    if t.state is _HIDDEN:  # a shared blob keeps its name: no flapping
        cost += weights.hidden_penalty
    if diag is not None:
        cost += weights.entry * moved / (weights.entry_scale_frac * diag)
    return cost


def _more_shafts(n_entries: int, n_group: int, known: bool) -> bool:
    """Whether a blob with ``n_entries`` shafts entering the view and ``n_group`` tracks
    in it is split on its entries: at least two entries, not fewer than the tracks, and
    more when the tracks already account for the blob (``known``: no hidden track, or
    the crossing handler split it)."""
    if n_entries < max(2, n_group):
        return False
    return not (n_entries == n_group and known)


#: Entering shafts fitted on their lanes are one shaft whose border contact a hole cut
#: in two when two of them differ by less than this (deg) and enter closer than their
#: widths together ...
LANE_SAME_DEG = 40.0
#: ... and a lane entering at less than this sine to the border (its width less than
#: this share of its run) runs along the border: no shaft's.
LANE_MIN_SIN = 0.5


def _run_lengths(runs: list[tuple[np.ndarray, int]]) -> dict[tuple[float, float], int]:
    """Border runs' lengths (px) by their middle point."""
    return {(float(e[1][0]), float(e[1][1])): n for e, n in runs}


def distinct_lanes(
    lanes: list[tuple[np.ndarray, np.ndarray, float]], runs: list[tuple[np.ndarray, int]]
) -> bool:
    """Whether shafts entering the view, fitted on their own lanes
    (:func:`~mistool.tracking.split.border_entries` ``lanes``; ``runs``: the border runs
    they come from), are as many shafts: none along the border, no two alike side by
    side."""
    length = _run_lengths(runs)
    for k, (p, d, w) in enumerate(lanes):
        if w < LANE_MIN_SIN * length.get((float(p[0]), float(p[1])), 0.0):
            return False
        for p2, d2, w2 in lanes[k + 1 :]:
            alike = abs(float(d @ d2)) >= math.cos(math.radians(LANE_SAME_DEG))
            if alike and float(np.hypot(*(p - p2))) < w + w2:
                return False
    return True


#: A track last seen in a blob takes no head-only instance farther than this many of its
#: sizes from its prediction (but where its shaft enters the view).
FAR_HEAD_SIZES = 0.5


def _far_head(t: Track, inst: InstanceObservation, frame: int, entry_reach: float) -> bool:
    """Whether ``inst`` is a head alone (no shaft) that a track last seen in a blob
    cannot be: farther than half the track's size from where it is expected, unless at
    the image border within ``entry_reach`` px of where its shaft entered the view (its
    shaft left the view there). That track is still in its blob; a tool entering head
    first elsewhere is another."""
    if not (t.in_blob or t.state.coasting) or "shaft" in inst.parts:
        return False
    return _far_head_terms(_TrackTerms(t, frame), _InstanceTerms(inst, None), entry_reach)


def _far_head_terms(t: _TrackTerms, i: _InstanceTerms, entry_reach: float) -> bool:
    """:func:`_far_head` of precomputed terms."""
    track = t.track
    if not (track.in_blob or t.state.coasting) or i.has_shaft:
        return False
    cx, cy = i.cx, i.cy
    near = None if t.entry is None else float(np.hypot(cx - t.entry[0], cy - t.entry[1]))
    return _far_head_of(t, i, entry_reach, float(np.hypot(cx - t.px, cy - t.py)), near)


def _far_head_of(
    t: _TrackTerms, i: _InstanceTerms, entry_reach: float, dist: float, near: float | None
) -> bool:
    """:func:`_far_head_terms` given its distances from the instance's centroid: to the
    track's prediction (``dist``) and to where its shaft last entered (``near``; None:
    it has no entry)."""
    if not (t.track.in_blob or t.state.coasting) or i.has_shaft:
        return False
    if dist <= FAR_HEAD_SIZES * t.size:
        return False
    near_entry = near is not None and near <= entry_reach
    return not (near_entry and _touches_border(i.inst))


#: A track seen apart in the last frame takes no instance inside the view (not touching
#: the image border) of less than this share of its area: a piece cut off a tool (by an
#: occluder, or a split) is no tool's whole; the tool itself is elsewhere, e.g. in a blob
#: with another. (A tool leaving the view shrinks at the border.)
SHRUNK_AREA_FRAC = 0.1


def _shrunk(t: Track, inst: InstanceObservation, frame: int) -> bool:
    """Whether ``inst`` is too small to be the whole of track ``t``, seen apart in the
    frame before (:data:`SHRUNK_AREA_FRAC`), and lies inside the view."""
    return (
        t.state is _TRACKED
        and frame - t.last_frame == 1
        and inst.area_px < SHRUNK_AREA_FRAC * t.area
        and not _touches_border(inst)
    )


def _fragment_of(t: Track, host: Track | None) -> bool:
    """Whether track ``t``, hidden in ``host``'s blob that could not be split, was only a
    piece of it: seen for at most :data:`FRAGMENT_MAX_SEEN` frames, never with a shaft,
    while the host has been seen longer; and never at the image border (a tool entering
    head first there, into another's blob, is a tool), unless both were first seen in
    the same frame: a tool's head entering in two pieces (jaws apart, then one blob).
    Held-out seed 6 frame 24: such a piece at the border stayed hidden in its tool's blob
    for 30 frames, the tool coasting all along (no shape, no entry), until a split of
    three tools gave the names out wrongly."""
    return (
        host is not None
        and not t.has_boxes
        and (not t.at_border or t.first_frame == host.first_frame)
        and t.seen <= FRAGMENT_MAX_SEEN
        and host.seen > t.seen
    )


def _some_longer(runs: Sequence[list[tuple[np.ndarray, int]]], n: int) -> bool:
    """Whether some instance's list of border runs is longer than ``n``."""
    for r in runs:
        if len(r) > n:
            return True
    return False


def _touches_border(inst: InstanceObservation) -> bool:
    """Whether the instance's bounds reach the image border."""
    if inst.image_shape is None:
        return True
    x, y, w, h = inst.bbox_xywh
    hh, ww = inst.image_shape
    return x <= 0 or y <= 0 or x + w >= ww or y + h >= hh


def _heads_within_reach(
    insts: Sequence[InstanceObservation | None], tracks: list[Track], frame: int
) -> bool:
    """Whether :func:`~mistool.tracking.heads.hand_over_heads` may move any pixel: some
    track's head part expected at ``frame`` (:meth:`Track.expected_heads`) lies within
    :data:`~mistool.tracking.heads.HEAD_CLAIM_PX` of another instance's crop of that
    part. A hand-over moves only pixels within that reach of where the receiving tool
    expects the part; the test looks at the crops' bounds against the box's own bounds
    grown by the reach and a pixel (the window
    :func:`mistool.kernels.split.shown_near` scans), without the pixels, nor the boxes
    :meth:`Track.expected_heads` makes. False: it would return the instances
    unchanged."""
    for r, t in enumerate(tracks):
        if not t.heads:
            continue
        vx, vy = t.motion.vx, t.motion.vy
        for p, (b, seen) in t.heads.items():
            gap = frame - seen
            if not 0 < gap <= HEAD_MEMORY_FRAMES:
                continue
            n = min(gap, SPLIT_STOP_FRAMES)
            cx, cy = b.cx + vx * n, b.cy + vy * n
            a = math.radians(b.angle_deg)
            u0, u1 = abs(math.cos(a)), abs(math.sin(a))
            hl, hw = 0.5 * b.length, 0.5 * b.width
            ex = hl * u0 + hw * u1 + HEAD_CLAIM_PX + 1.0
            ey = hl * u1 + hw * u0 + HEAD_CLAIM_PX + 1.0
            for d, donor in enumerate(insts):
                obs = donor.parts.get(p) if d != r and donor is not None else None
                if obs is None:
                    continue
                x0, y0 = obs.offset
                h, w = obs.mask.shape
                if not (  # (NaN: within reach)
                    x0 > cx + ex + 1.0
                    or x0 + w < cx - ex - 1.0
                    or y0 > cy + ey + 1.0
                    or y0 + h < cy - ey - 1.0
                ):
                    return True
    return False


def _inside(
    p: np.ndarray | tuple[float, float], bbox: tuple[int, int, int, int], margin: float
) -> bool:
    x, y, w, h = bbox
    mx, my = margin * w, margin * h
    return bool(x - mx <= p[0] <= x + w + mx and y - my <= p[1] <= y + h + my)


#: :func:`_instance_terms`: (instance, cx, cy, area, sqrt(area), direction or None,
#: elongation, has a shaft, image diagonal or None, (x, y, image diagonal) where its one
#: shaft enters the view or None).
_InstanceRow = tuple[
    InstanceObservation, float, float, int, float, "float | None", float, bool,
    "float | None", "tuple[float, float, float] | None",
]  # fmt: skip
#: :meth:`IdentityTracker._costs`' terms of a track: (track, state, lost, frames since
#: its update, last in a blob or coasting, where its shaft last entered or None).
_TrackRow = tuple[Track, TrackState, bool, int, bool, "list[float] | None"]


def _instance_terms(inst: InstanceObservation, runs: list[tuple[np.ndarray, int]]) -> _InstanceRow:
    """What the assignment's costs read of an instance (``runs``: its border runs), as
    :class:`_InstanceTerms` (the same values) in a plain tuple (:data:`_InstanceRow`);
    its entry only with the image's shape (the costs measure it only then)."""
    cx, cy = inst.centroid_px
    area = inst.area_px
    parts = inst.parts
    shaft = parts.get("shaft")
    box = (shaft or max(parts.values(), key=_area_of)).box  # (:func:`_appearance`)
    angle, elong = (None, 0.0) if box.length <= 0 else (
        box.angle_deg, (box.length - box.width) / box.length
    )  # fmt: skip
    shape = inst.image_shape
    diag = None if shape is None else math.hypot(*shape)
    entry = None
    if len(runs) == 1 and diag is not None:  # (:func:`_one_entry`)
        ex, ey = runs[0][0][1].tolist()
        entry = (ex, ey, diag)
    return (inst, cx, cy, area, math.sqrt(area), angle, elong, shaft is not None, diag, entry)


class _Frame:
    """One frame's work in progress (see :meth:`IdentityTracker._step`; a plain slotted
    class: a dataclass's five default factories cost ~2 us a frame)."""

    __slots__ = ("blob_of", "index", "instances", "live", "owner", "piece_tracks", "pieces",
                 "split_tracks")  # fmt: skip

    def __init__(self, index: int, instances: list[InstanceObservation], live: list[Track]) -> None:
        self.index = index
        self.instances = instances
        self.live = live
        self.owner: dict[int, int] = {}
        """instance -> live track matched to it."""
        self.blob_of: dict[int, list[int]] = {}
        """instance -> live tracks hidden in it (crossing)."""
        self.pieces: dict[int, list[InstanceObservation]] = {}
        """instance -> the pieces it was split into."""
        self.split_tracks: dict[int, list[Track]] = {}
        """instance split by the crossing handler -> the track of each piece (the blob's
        other tracks coast)."""
        self.piece_tracks: dict[int, list[Track]] = {}
        """instance split on border entries -> the track of each piece."""


class IdentityTracker:
    """Names instruments consistently across frames (see the module docstring).

    ``assign`` / ``resolve`` must be called in frame order (the tracker keeps state); it
    is not thread-safe.

    Args:
        config: fps, ``min_area_px``, and whether instruments have their own labels.
        max_gap_s: how long (s) an unseen instrument is remembered.
        weights: the cost terms and gate.
    """

    def __init__(
        self, config: Config, *, max_gap_s: float = 2.0, weights: CostWeights | None = None
    ) -> None:
        self._config = config
        self._weights = weights or CostWeights()
        self._max_gap = max(1, int(round(max_gap_s * config.fps)))
        self._tracks: list[Track] = []
        self._next = 1
        self._last_frame: int | None = None
        # border runs of this frame's instances (and pieces), by id: computed once
        self._runs: dict[int, tuple[InstanceObservation, list[tuple[np.ndarray, int]]]] = {}

    @property
    def names(self) -> tuple[str, ...]:
        """Every name handed out so far, in order of first appearance."""
        return tuple(t.name for t in self._tracks)

    @property
    def tracks(self) -> tuple[Track, ...]:
        """Every track so far (read-only use), in order of first appearance."""
        return tuple(self._tracks)

    def assign(self, frame_index: int, instances: list[InstanceObservation]) -> list[str]:
        """Names for one frame's instances.

        Args:
            frame_index: the frame's 0-based index; increasing between calls.
            instances: :func:`~mistool.tracking.observe_frame`'s result for that frame.

        Returns:
            One instrument name per instance, same order, all different. An instance that
            holds two crossing instruments gets one name (see :meth:`resolve`).
        """
        return self._step(frame_index, instances, split=False)[1]

    def resolve(
        self,
        frame_index: int,
        instances: list[InstanceObservation],
        runs: Sequence[list[tuple[np.ndarray, int]]] | None = None,
    ) -> tuple[list[InstanceObservation], list[str]]:
        """Like :meth:`assign`, but an instance holding several known instruments (two
        crossing or grasping each other in merged masks) is split between them.

        The split (:func:`~mistool.tracking.split_instance`) assigns the blob's pixels to
        the instruments' expected part boxes (their last boxes seen apart, moved by their
        velocity), the shaft axes refined on the blob's own pixels; it is used only when
        it is well supported, else the blob keeps one name as in :meth:`assign`.

        Args:
            frame_index: the frame's 0-based index; increasing between calls.
            instances: :func:`~mistool.tracking.observe_frame`'s result for that frame.
            runs: optionally, :func:`~mistool.tracking.split.border_runs` of each
                instance, computed elsewhere (a worker process): the same result, less
                work here.

        Returns:
            ``(instances, names)``: the instances (split ones replaced by their pieces,
            which have ``label`` None and new part boxes) and one name per instance. When
            nothing was split, ``instances`` is the very list passed in (so a caller can
            test ``is`` and redo per-instance work only for split frames).
        """
        return self._step(frame_index, instances, split=True, runs=runs)

    # the pipeline ---------------------------------------------------------------------
    def _step(
        self,
        frame_index: int,
        instances: list[InstanceObservation],
        *,
        split: bool,
        runs: Sequence[list[tuple[np.ndarray, int]]] | None = None,
    ) -> tuple[list[InstanceObservation], list[str]]:
        if self._config.instruments and all(i.label is not None for i in instances):
            return instances, [str(i.label) for i in instances]
        if self._last_frame is not None and frame_index <= self._last_frame:
            raise ValueError(
                f"IdentityTracker: frame {frame_index} after frame "
                f"{self._last_frame}; frames must come in increasing order"
            )
        self._last_frame = frame_index
        self._runs = {}
        if runs is not None:  # border runs computed elsewhere: the same, cached
            self._runs = {id(i): (i, r) for i, r in zip(instances, runs, strict=True)}
        fr = _Frame(frame_index, instances, self._predict_live(frame_index))
        self._match(fr)
        if len(fr.owner) < len(fr.live):  # (every live track matched: none hidden)
            self._find_hidden(fr)
        if split:
            if fr.blob_of:
                self._split_crossings(fr)
            # (the usual frame: no instance with two shafts entering, nothing to split)
            if runs is None or _some_longer(runs, 1):
                self._split_entries(fr)
        return self._update_all(fr)

    def _predict_live(self, frame: int) -> list[Track]:
        """The tracks still remembered at ``frame``, their states brought up to date."""
        live = []
        max_gap = self._max_gap
        for t in self._tracks:
            gap = frame - t.last_frame
            state = t.state
            if gap <= max_gap and state is not _ABSORBED:
                if state is _TRACKED and gap > LOST_AFTER_FRAMES:
                    t.state = _LOST
                live.append(t)
        return live

    def _cost(
        self, t: Track, inst: InstanceObservation, frame: int, entry: np.ndarray | None = None
    ) -> float:
        return track_cost(t, inst, frame, self._weights, self._config.fps, entry)

    def _match(self, fr: _Frame) -> None:
        """One gated assignment of live tracks to instances."""
        cost = self._costs(fr)
        if len(cost) == 1 and len(cost[0]) == 1:
            # one track, one instance (the usual frame with one tool): the pair is made
            # exactly when it passes the gate (:func:`gated_assignment`'s answer)
            x = cost[0][0]
            fr.owner = {0: 0} if math.isfinite(x) and x <= self._weights.max_cost else {}
            return
        fr.owner = {b: a for a, b in gated_assignment(cost, self._weights.max_cost)}

    def _costs(self, fr: _Frame) -> list[list[float]]:
        """The assignment's costs, a row per live track (:func:`_pair_cost`; ``inf``: an
        impossible pair, :func:`_far_head_of` or :func:`_shrunk`). Every pair's
        distances come from one ``np.hypot`` call over the frame's pairs (the same
        values as one call per pair: numpy's loop calls the C library's ``hypot`` on
        each element). Each track's and instance's terms are read once into a plain
        tuple (:func:`_instance_terms`), and :func:`_cost_of` is written out in the loop
        (:func:`_cost_rows`): the same operations in the same order, the same bits,
        without an object and a call per pair and term (they cost about what the
        arithmetic does)."""
        frame = fr.index
        insts = [_instance_terms(inst, self._runs_of(inst)) for inst in fr.instances]
        # which distances each pair needs: to the prediction; between the shafts'
        # entries (both known, and the image's shape); from the instance to the track's
        # entry only for the far-head test (a track last in a blob, a shaftless instance)
        tracks: list[_TrackRow] = []
        xs: list[float] = []
        ys: list[float] = []
        for t in fr.live:
            state = t.state
            lost = state is _LOST
            gap = frame - t.last_frame
            m = t.motion
            steps = LOST_AFTER_FRAMES if lost else gap  # (Track.predict_xy)
            px, py = m.x + m.vx * steps, m.y + m.vy * steps
            blobby = t.in_blob or state is _COASTING or state is _HIDDEN
            te = None if t.entry is None else t.entry.tolist()
            tracks.append((t, state, lost, gap, blobby, te))
            for i in insts:
                xs.append(i[1] - px)
                ys.append(i[2] - py)
                if te is not None:
                    if blobby and not i[7]:
                        xs.append(i[1] - te[0])
                        ys.append(i[2] - te[1])
                    ie = i[9]
                    if ie is not None:
                        xs.append(ie[0] - te[0])
                        ys.append(ie[1] - te[1])
        if not xs:
            return [[] for _ in tracks]
        hyp = np.hypot(np.array(xs, np.float64), np.array(ys, np.float64)).tolist()
        return self._cost_rows(tracks, insts, hyp)

    def _cost_rows(
        self, tracks: list[_TrackRow], insts: list[_InstanceRow], hyp: list[float]
    ) -> list[list[float]]:
        """:meth:`_costs`' rows from the terms and every pair's distances (``hyp``, in
        the order :meth:`_costs` lists them): :func:`_far_head_of`, :func:`_shrunk` and
        :func:`_cost_of` written out."""
        weights, fps = self._weights, self._config.fps
        w_angle, w_area, w_gap = weights.angle, weights.area, weights.gap
        w_entry, entry_frac = weights.entry, weights.entry_scale_frac
        lost_frac, lost_growth = weights.lost_scale_frac, weights.lost_search_growth
        cost = []
        k = 0
        for t, state, lost, gap, blobby, te in tracks:
            size, t_angle, t_elong, t_area = t.size, t.angle, t.elongation, t.area
            tracked = state is _TRACKED
            # (:func:`_shrunk`: a track seen apart in the frame before)
            shrink = SHRUNK_AREA_FRAC * t_area if tracked and gap == 1 else None
            row = []
            for inst, _, _, area, root, angle, elong, has_shaft, i_diag, ie in insts:
                dist = hyp[k]
                k += 1
                near = None
                moved = 0.0
                diag = None  # (the image's diagonal when both shafts enter the view)
                far_head = blobby and not has_shaft
                if te is not None:
                    if far_head:
                        near = hyp[k]
                        k += 1
                    if ie is not None:
                        moved = hyp[k]
                        k += 1
                        diag = ie[2]
                if (  # (:func:`_far_head_of`)
                    far_head
                    and dist > FAR_HEAD_SIZES * size
                    and not (
                        near is not None
                        and near <= self._entry_reach(inst)
                        and _touches_border(inst)
                    )
                ) or (shrink is not None and area < shrink and not _touches_border(inst)):
                    row.append(math.inf)
                    continue
                # :func:`_cost_of`, written out
                scale = max(size, root, 10.0)
                if lost:
                    if i_diag is not None:
                        scale = min(scale, lost_frac * i_diag)
                    scale *= 1.0 + lost_growth * (gap - LOST_AFTER_FRAMES) / fps
                if diag is not None and lost and moved <= entry_frac * diag:
                    dist = min(dist, moved)
                c = dist / scale
                if angle is not None and t_angle is not None and not (lost and not has_shaft):
                    d = abs(angle - t_angle) % 180.0  # (angle_diff_deg)
                    c += w_angle * min(elong, t_elong) * min(d, 180.0 - d) / 90.0
                if tracked:
                    c += w_area * abs(math.log(max(area, 1) / max(t_area, 1.0)))
                c += w_gap * (gap - 1)
                if state is _HIDDEN:
                    c += weights.hidden_penalty
                if diag is not None:
                    c += w_entry * moved / (entry_frac * diag)
                row.append(c)
            cost.append(row)
        return cost

    def _entry_reach(self, inst: InstanceObservation) -> float:
        """How far (px) from where a shaft last entered the view it may enter now
        (:attr:`CostWeights.entry_scale_frac` of the image diagonal)."""
        shape = inst.image_shape or (1000, 1000)
        return self._weights.entry_scale_frac * math.hypot(*shape)

    def _find_hidden(self, fr: _Frame) -> None:
        """Unmatched recent tracks whose prediction lies in a matched, grown blob."""
        recent = max(HIDDEN_MAX_GAP_FRAMES, self._max_gap // 4)
        matched = set(fr.owner.values())
        for a, t in enumerate(fr.live):
            if a in matched or fr.index - t.last_frame > recent:
                continue
            pred = t.predict_xy(fr.index)
            for b, a2 in sorted(fr.owner.items(), key=lambda kv: kv[1]):
                host = fr.live[a2]
                grown = fr.instances[b].area_px > BLOB_GROWTH * host.area or host.state.coasting
                if grown and _inside(pred, fr.instances[b].bbox_xywh, BLOB_MARGIN_FRAC):
                    fr.blob_of.setdefault(b, []).append(a)
                    break

    def _expected_boxes(
        self, t: Track, frame: int, steps: int | None
    ) -> dict[str, RotatedBox] | None:
        """The track's last part boxes seen apart from others, moved to ``frame`` by at
        most ``steps`` frames of its velocity (None: all the way); the shaft is lengthened
        by what the rest of the constant-velocity motion would add along it. None when
        there are none, or the track was last seen apart without a shaft for more than
        :data:`LOST_AFTER_FRAMES` frames in a row (its shaft left the view: they are
        stale)."""
        boxes = self._reference_of(t)
        if boxes is None or t.shaftless > LOST_AFTER_FRAMES:
            return None
        gap = frame - t.boxes_frame
        move = gap if steps is None else min(gap, steps)
        vx, vy = t.motion.vx, t.motion.vy
        dx, dy = vx * move, vy * move  # (plain floats: numpy's values, faster)
        s = boxes["shaft"]
        if gap == move and abs(vx) < 1e300 and abs(vy) < 1e300:
            # moved all the way: the extension is 2 |v . u| * 0, +0.0 for a finite v
            # (its dot product, ~2.5 us, not needed)
            length = s.length + 0.0
        else:  # (numpy's dot product, as before: its summation may differ from floats')
            extra = 2.0 * abs(float(t.motion.velocity @ unit_vector(s.angle_deg))) * (gap - move)
            length = s.length + extra
        # (each box made once, the shaft's with its extension)
        return {
            p: RotatedBox(
                b.cx + dx, b.cy + dy, length if p == "shaft" else b.length, b.width, b.angle_deg
            )
            for p, b in boxes.items()
        }

    def _reference_of(self, t: Track) -> dict[str, RotatedBox] | None:
        """The track's :attr:`Track.boxes`, made with the other tracks' heads
        (:meth:`Track.make_boxes`) when still to be made."""
        if t.boxes_pending:
            t.make_boxes(self._other_heads(t, t.boxes_frame))
        return t.boxes

    def _other_heads(self, t: Track, frame: int) -> list[tuple[float, float]]:
        """Centres of the head boxes the other tracks remember (:attr:`Track.heads`)
        from within :data:`HEAD_MEMORY_FRAMES` frames of ``frame``."""
        return [
            (b.cx, b.cy)
            for o in self._tracks
            if o is not t
            for b, seen in o.heads.values()
            if abs(seen - frame) <= HEAD_MEMORY_FRAMES
        ]

    def _split_crossings(self, fr: _Frame) -> None:
        """Crossing handler: each blob holding hidden tracks split between its tracks.

        Two motion hypotheses (:data:`SPLIT_STOP_FRAMES`) share the blob's pixels; only
        their axes are fitted (cheap), the second only when the first fails or fits
        poorly (:data:`SPLIT_GOOD_SCORE`), and only the best-scoring fit is measured (its
        pieces' boxes), the other only if that one yields no pieces. When that fails and
        some tracks have no shaft in the blob (none expected, or no shaft pixels where
        it is expected: a tool entering head first), it is redone with those taking only
        head pixels (:func:`~mistool.tracking.split.split_with_heads`)."""
        for b, hidden in fr.blob_of.items():
            group = [fr.live[fr.owner[b]]] + [fr.live[a] for a in hidden]
            pixels = BlobPixels(fr.instances[b])
            got = self._split_blob(fr.index, group, pixels, set())
            if got is None:
                heads = self._shaftless(fr.index, group, pixels)
                if heads and len(heads) < len(group):
                    got = self._split_blob(fr.index, group, pixels, heads)
            if got is not None:
                fr.pieces[b], fr.split_tracks[b] = got

    def _shaftless(self, frame: int, group: list[Track], pixels: BlobPixels) -> set[int]:
        """Indices of the tracks in ``group`` with no shaft in the blob: none expected,
        or fewer than ``min_area_px`` shaft pixels where it is expected."""
        out = set()
        for k, t in enumerate(group):
            e = self._expected_boxes(t, frame, SPLIT_STOP_FRAMES)
            if e is None or shaft_support(pixels, e["shaft"]) < self._config.min_area_px:
                out.add(k)
        return out

    def _split_blob(
        self, frame: int, group: list[Track], pixels: BlobPixels, heads: set[int]
    ) -> tuple[list[InstanceObservation], list[Track]] | None:
        """The blob split between the tracks of ``group`` (those in ``heads`` taking only
        head pixels): the pieces and their tracks, or None."""
        min_area = max(self._config.min_area_px, 1)
        shafted = [t for k, t in enumerate(group) if k not in heads]
        fits: list[SplitFit] = []
        for steps in (SPLIT_STOP_FRAMES, None):
            expected = [self._expected_boxes(t, frame, steps) for t in shafted]
            if any(e is None for e in expected):
                break
            fit = fit_split(
                pixels,
                [e for e in expected if e],
                min_area,
                min_tracks=1 if heads else 2,
                keep_d2=SPLIT_OTHERS_D2 if heads else None,
            )
            if fit is not None:
                fits.append(fit)
                if fit.score <= SPLIT_GOOD_SCORE:
                    break  # the second hypothesis only when the first is poor
        anchors = [self._head_anchor(group[k], frame) for k in sorted(heads)]
        for fit in sorted(fits, key=lambda f: f.score):
            got = split_with_heads(pixels, fit, min_area, anchors)
            if got is not None:
                pieces, head_pieces = got
                tracks = list(shafted)
                for k, piece in zip(sorted(heads), head_pieces, strict=True):
                    if piece is not None:
                        pieces.append(piece)
                        tracks.append(group[k])
                return pieces, tracks
        return None

    def _head_anchor(self, t: Track, frame: int) -> HeadAnchor:
        """Where a track with no shaft in a blob expects its head."""
        e = self._expected_boxes(t, frame, SPLIT_STOP_FRAMES) or {}
        boxes = {p: b for p, b in e.items() if p != "shaft"}
        return HeadAnchor(boxes, t.predict(frame), max(0.5 * math.sqrt(t.area), 5.0))

    def _split_entries(self, fr: _Frame) -> None:
        """Entry handler: a blob with more shafts entering from the border than tracks
        known in it (instruments touching since they came into view), split on those
        shafts; the known tracks take the pieces, the others are new."""
        if all(len(self._runs_of(inst)) < 2 for inst in fr.instances):
            return  # (no blob with two shafts entering: the usual frame)
        used = set(fr.owner.values()) | {
            a for b, hidden in fr.blob_of.items() if b in fr.pieces for a in hidden
        }
        # tracks believed hidden in a blob that was not split may be found elsewhere
        spare = [a for a in range(len(fr.live)) if a not in used]
        for b, inst in enumerate(fr.instances):
            group = ([fr.owner[b]] + fr.blob_of.get(b, [])) if b in fr.owner else []
            known = b not in fr.blob_of or b in fr.pieces
            runs = self._runs_of(inst)
            if not _more_shafts(len(runs), len(group), known):
                continue  # (entries <= runs: the cheap count first)
            entries = border_entries(inst, runs)
            if not _more_shafts(len(entries), len(group), known):
                continue
            # (a blob the crossing handler split, holding one more tool entering: redone)
            got = self._entry_split(inst, runs, entries)
            if got is None:
                continue
            cands = group + [a for a in spare if a not in group]
            pairs = self._match_entries(fr, inst, entries, got, cands, len(group))
            taken = {cands[r] for r, _ in pairs}
            spare = [a for a in spare if a not in taken and a not in group]
            for b2 in [b2 for b2 in fr.blob_of if b2 != b]:
                fr.blob_of[b2] = [a for a in fr.blob_of[b2] if a not in taken]
                if not fr.blob_of[b2]:
                    del fr.blob_of[b2]
            by_piece = {c: fr.live[cands[r]] for r, c in pairs}
            redone = None
            if len(by_piece) == len(got):  # no new tool: the crossing split may do better
                order = [by_piece[c] for c in range(len(got))]
                redone = self._heads_given_away(fr.index, inst, got, order)
                if redone is not None:
                    got, by_piece = redone[0], dict(enumerate(redone[1]))
            tracks = []
            for c, piece in enumerate(got):
                t = by_piece.get(c)
                if t is None:
                    t = self._new_track(piece, fr.index)
                else:
                    shape = redone is None or _head_area(piece) >= REDONE_SHAPE_HEAD_PX
                    self._update(t, piece, fr.index, merged=False, shape=shape)
                    if redone is not None and t.boxes_frame == fr.index:
                        t.boxes_entering = len(self._runs_of(piece)) == 1
                tracks.append(t)
            for a in group:  # known instruments the split did not find: coast
                if a not in taken:
                    self._hide(fr.live[a], fr.index)
            fr.pieces[b] = got
            fr.piece_tracks[b] = tracks

    def _heads_given_away(
        self,
        frame: int,
        inst: InstanceObservation,
        pieces: list[InstanceObservation],
        tracks: list[Track],
    ) -> tuple[list[InstanceObservation], list[Track]] | None:
        """An entry split whose pieces all went to known tracks (``tracks[k]`` takes
        ``pieces[k]``), redone by the crossing split when it left a tool without a head
        (no wrist, no jaws) while its reference shape has one, and the crossing split
        (:meth:`_split_blob`, on the tracks' reference shapes) gives each such tool head
        pixels: ``(pieces, tracks)``, else None (the entry split stands).

        The entry split cuts along half-lines from the border and gives each head pixel
        to the nearest; two tools' heads meeting in the blob mostly went to one of them
        (twox s1 frames 119-128: the other's shaft ran on through both heads to the far
        border), and that tool's head was still in view in nearly every such frame
        (``mask_areas.csv``). The crossing split places each head by its tool's
        reference shape (:func:`~mistool.tracking.split.split_with_heads`); its pieces
        are then updated as the entry split's would have been."""
        bare = [
            t
            for t, p in zip(tracks, pieces, strict=True)
            if not any(h in p.parts for h in HEAD_PARTS)
            and (boxes := self._reference_of(t)) is not None
            and any(h in boxes for h in HEAD_PARTS)
        ]
        if not bare:
            return None
        got = self._split_blob(frame, tracks, BlobPixels(inst), set())
        if got is None:
            return None
        for t, piece in zip(got[1], got[0], strict=True):
            if any(t is u for u in bare) and not any(h in piece.parts for h in HEAD_PARTS):
                return None
        return got

    def _entry_split(
        self,
        inst: InstanceObservation,
        runs: list[tuple[np.ndarray, int]],
        entries: list[tuple[np.ndarray, np.ndarray, float]],
    ) -> list[InstanceObservation] | None:
        """The instance split on its shafts' entries; when that fails, again with each
        entering shaft's direction taken from its own lane
        (:func:`~mistool.tracking.split.border_entries` ``lanes``: another tool's shaft
        passing near a stub's entry had turned the stub's direction along the border)."""
        min_area = max(self._config.min_area_px, 1)
        got = split_on_entries(inst, entries, min_area)
        if got is not None:
            return got
        lanes = border_entries(inst, runs, lanes=True)
        if len(lanes) != len(entries) or not distinct_lanes(lanes, runs):
            return None
        got = split_on_entries(inst, lanes, min_area)
        if got is None:
            return None
        # a stub whose first fit lay along the border is a tool entering: its head hangs
        # in the view beyond it (none: its lane ran into another tool's shaft)
        length = _run_lengths(runs)
        for (p, _, w), piece in zip(entries, got, strict=True):
            stub = w < LANE_MIN_SIN * length.get((float(p[0]), float(p[1])), 0.0)
            if stub and not any(h in piece.parts for h in HEAD_PARTS):
                return None
        return got

    def _match_entries(
        self,
        fr: _Frame,
        inst: InstanceObservation,
        entries: list[tuple[np.ndarray, np.ndarray, float]],
        pieces: list[InstanceObservation],
        cands: list[int],
        n_group: int,
    ) -> list[tuple[int, int]]:
        """Candidate tracks (the blob's own first) to pieces split on border entries."""
        cost = np.full((len(cands), len(pieces)), np.inf)
        diag = math.hypot(*inst.image_shape) if inst.image_shape else 1000.0
        for r, a in enumerate(cands):
            t = fr.live[a]
            for c, piece in enumerate(pieces):
                if r >= n_group:
                    cost[r, c] = self._cost(t, piece, fr.index)
                elif t.entry is not None:  # where its shaft entered the view
                    dist = float(np.hypot(*(t.entry - entries[c][0])))
                    cost[r, c] = dist / (self._weights.entry_scale_frac * diag)
                else:  # the blob's own instruments: their state is the blob's
                    cost[r, c] = 0.5 * self._cost(t, piece, fr.index)
        return gated_assignment(cost, self._weights.max_cost)

    def _hand_over(self, fr: _Frame) -> bool:
        """Heads handed back to their own tool among the instances and split pieces
        given one track's name (:func:`~mistool.tracking.heads.hand_over_heads`); the
        changed ones replaced in ``fr`` (``fr.instances`` copied first). Whether any
        changed."""
        if len(fr.instances) < 2 and not fr.pieces:
            return False  # (one instance, not split: no other to hand a head over to)
        slots: list[tuple[int, int]] = []  # (instance, piece index or -1)
        insts: list[InstanceObservation | None] = []
        tracks: list[Track] = []
        for b, inst in enumerate(fr.instances):
            if b in fr.piece_tracks:
                continue  # split on entries: those tracks are updated already
            if b in fr.pieces:
                for k, (t, piece) in enumerate(zip(fr.split_tracks[b], fr.pieces[b], strict=True)):
                    slots.append((b, k))
                    insts.append(piece)
                    tracks.append(t)
            elif b in fr.owner and b not in fr.blob_of:
                slots.append((b, -1))
                insts.append(inst)
                tracks.append(fr.live[fr.owner[b]])
        if len(insts) < 2 or not _heads_within_reach(insts, tracks, fr.index):
            return False  # (no head expected near another's pixels: nothing to hand over)
        expected = [t.expected_heads(fr.index) for t in tracks]
        got = hand_over_heads(insts, expected, max(self._config.min_area_px, 1))
        changed = False
        for (b, k), old, new in zip(slots, insts, got, strict=True):
            if new is old or new is None:
                continue
            if not changed:
                fr.instances = list(fr.instances)
                changed = True
            if k < 0:
                fr.instances[b] = new
            else:
                fr.pieces[b] = [new if j == k else p for j, p in enumerate(fr.pieces[b])]
        return changed

    def _update_all(self, fr: _Frame) -> tuple[list[InstanceObservation], list[str]]:
        """Update the tracks, name new instances, coast the hidden tracks."""
        handed = self._hand_over(fr)
        if handed or fr.pieces or fr.blob_of:
            return self._update_all_general(fr, handed)
        # (the usual frame: nothing split, hidden or handed over; what
        # :meth:`_update_all_general` does then, in the same order)
        owner, live, index = fr.owner, fr.live, fr.index
        names: list[str] = []
        for b, inst in enumerate(fr.instances):
            a = owner.get(b)
            if a is None:
                names.append(self._new_track(inst, index).name)
            else:
                t = live[a]
                self._update(t, inst, index, merged=False)
                names.append(t.name)
        return fr.instances, names

    def _update_all_general(
        self, fr: _Frame, handed: bool
    ) -> tuple[list[InstanceObservation], list[str]]:
        """:meth:`_update_all` after the hand-over (``handed``: whether it changed any
        instance)."""
        out: list[InstanceObservation] = []
        names: list[str] = []
        for b, inst in enumerate(fr.instances):
            if b in fr.piece_tracks:
                out.extend(fr.pieces[b])
                names.extend(t.name for t in fr.piece_tracks[b])
            elif b in fr.pieces:
                tracks = fr.split_tracks[b]
                crowded = 1 + len(fr.blob_of[b]) >= CROWDED_SPLIT_TRACKS
                for t, piece in zip(tracks, fr.pieces[b], strict=True):
                    self._update(t, piece, fr.index, merged=False, apart=False, crowded=crowded)
                    out.append(piece)
                    names.append(t.name)
                group = [fr.live[fr.owner[b]]] + [fr.live[a] for a in fr.blob_of[b]]
                for t in group:
                    if all(t is not u for u in tracks):  # no piece of its own: coasts
                        self._hide(t, fr.index)
            elif b in fr.owner:
                t = fr.live[fr.owner[b]]
                self._update(t, inst, fr.index, merged=b in fr.blob_of)
                out.append(inst)
                names.append(t.name)
            else:
                out.append(inst)
                names.append(self._new_track(inst, fr.index).name)
        for b, hidden in fr.blob_of.items():
            if b not in fr.pieces:
                host = fr.live[fr.owner[b]] if b in fr.owner else None
                for a in hidden:  # keep them coasting on their predicted motion
                    t = fr.live[a]
                    if _fragment_of(t, host):
                        t.state = _ABSORBED
                    else:
                        self._hide(t, fr.index)
        if not fr.pieces and not handed:
            return fr.instances, names  # the caller's own list: nothing was split
        return out, names

    # track updates --------------------------------------------------------------------
    @staticmethod
    def _hide(t: Track, frame: int) -> None:
        """A track hidden in a blob carrying another's name coasts on its motion."""
        t.motion.coast(t.predict_steps(frame))
        t.last_frame = frame
        t.state = _HIDDEN
        t.in_blob = True

    def _update(
        self,
        t: Track,
        inst: InstanceObservation,
        frame: int,
        *,
        merged: bool,
        apart: bool = True,
        crowded: bool = False,
        shape: bool = True,
    ) -> None:
        """Update a track with the instance given its name (``merged``: a blob holding
        others too, whose centroid is not this instrument's: it coasts; ``apart``: seen
        apart from others, not a split's piece; ``crowded``: a piece of a blob split
        between at least :data:`CROWDED_SPLIT_TRACKS` tools, its motion along its shaft
        unsure; a track's first velocity is not measured on one; ``shape``: whether the
        instance may become its reference shape, see :data:`REDONE_SHAPE_HEAD_PX`)."""
        gap = frame - t.last_frame
        t.in_blob = merged or not apart
        if merged:
            t.motion.coast(t.predict_steps(frame))
            t.state = _COASTING
        else:
            unsure = unit_vector(t.angle) if crowded and t.angle is not None else None
            t.motion.update(
                inst.centroid_px,
                gap,
                # a new track's first displacement to a crowded piece is no velocity:
                # the piece's cut moved (held-out seed 6 frame 55: 70 px in a frame);
                # nor is one whose head jumped
                continuous=t.state is _TRACKED
                and not (crowded and (t.seen == 1 or _head_jumped(t, inst, frame))),
                first=t.seen == 1,
                unsure_along=unsure,
            )
            if gap > LOST_AFTER_FRAMES:  # back after being lost: its old shape is stale
                t.motion.reset_velocity()
                t.boxes = None
            t.area = float(inst.area_px)
            t.size = max(t.size, math.sqrt(t.area))
            t.angle, t.elongation = _appearance(inst)
            parts = inst.parts
            runs = self._runs_of(inst)
            # a split piece is no reference shape, nor a blob of two shafts entering
            if apart:
                t.shaftless = 0 if "shaft" in parts else t.shaftless + 1
            if not shape:
                pass  # (a redone entry piece with too little head: the shape stands)
            elif apart and "shaft" in parts and len(runs) <= 1:
                t.set_boxes_from(inst, runs, frame)
            elif (
                t.boxes_entering
                and not crowded
                and len(runs) == 1
                and "shaft" in parts
                and any(h in parts for h in HEAD_PARTS)
                and (ref := self._reference_of(t)) is not None
                and parts["shaft"].box.length > ENTERING_GROWTH * ref["shaft"].length
            ):
                t.set_boxes_from(inst, runs, frame)
                t.boxes_entering = True
            # (:meth:`_set_entry`, written out: an update per track and frame)
            if not t.at_border:
                t.at_border = _touches_border(inst)
            if len(runs) == 1:  # one shaft entering: this instrument's (not a blob's)
                t.entry = runs[0][0][1]
            for p in HEAD_PARTS:
                # a crowded piece's head part of two large label components spans two
                # tools' heads: the hand-over remembers the part's last box before it
                if p in parts and not (crowded and _two_pieces(parts[p])):
                    t.heads[p] = (parts[p].box, frame)
            t.state = _TRACKED
        t.last_frame = frame
        t.seen += 1

    def _set_entry(
        self, t: Track, inst: InstanceObservation, runs: list[tuple[np.ndarray, int]]
    ) -> None:
        """Whether the track touched the border, and where its one shaft entered the view
        (``runs``: the instance's :meth:`_runs_of`)."""
        t.at_border = t.at_border or _touches_border(inst)
        entry = _one_entry(runs)
        if entry is not None:  # one shaft entering: this instrument's (not a blob's)
            t.entry = entry

    def _runs_of(self, inst: InstanceObservation) -> list[tuple[np.ndarray, int]]:
        """:func:`~mistool.tracking.split.border_runs` of an instance of this frame,
        computed once per instance."""
        got = self._runs.get(id(inst))
        if got is None or got[0] is not inst:
            got = (inst, border_runs(inst))
            self._runs[id(inst)] = got
        return got[1]

    def _new_track(self, inst: InstanceObservation, frame: int) -> Track:
        angle, elong = _appearance(inst)
        t = Track(
            name=str(self._next),
            motion=ConstantVelocity(inst.centroid_px),
            last_frame=frame,
            area=float(inst.area_px),
            angle=angle,
            elongation=elong,
            size=math.sqrt(inst.area_px),
            first_frame=frame,
        )
        t.shaftless = 0 if "shaft" in inst.parts else 1
        runs = self._runs_of(inst)
        if "shaft" in inst.parts:
            t.set_boxes_from(inst, runs, frame)
        self._set_entry(t, inst, runs)
        t.heads = {p: (inst.parts[p].box, frame) for p in HEAD_PARTS if p in inst.parts}
        self._next += 1
        self._tracks.append(t)
        return t
