"""Instruments in each frame and their identity across frames.

A pipeline of small modules, imports flowing one way:

- :mod:`~mistool.tracking.instances`: one frame's instruments (:func:`observe_frame`:
  parts, Algorithm 1 boxes; grouping fragments of merged masks by one table of reach
  rules). Pure, per frame.
- :mod:`~mistool.tracking.split`: pure functions splitting a blob that holds several
  instruments (:func:`split_instance`).
- :mod:`~mistool.tracking.motion`: the tracks' motion model (constant velocity).
- :mod:`~mistool.tracking.identity`: :class:`IdentityTracker` (predict -> cost -> one
  gated assignment -> crossing and entry handlers -> update), :class:`TrackState`,
  :class:`CostWeights`, :func:`track_cost`.
- :mod:`~mistool.tracking.relink`: the names revisited over a whole tracked sequence
  (fragments absorbed, broken lives linked; :func:`mistool.api.refine` calls it).

The observation types live in :mod:`mistool.model` and are re-exported here, as is
:func:`unknown_values` (reading: :mod:`mistool.sequence`).
"""

from mistool.model import InstanceObservation, PartObservation
from mistool.sequence import unknown_values
from mistool.tracking.identity import CostWeights, IdentityTracker, Track, TrackState, track_cost
from mistool.tracking.instances import REACH_RULES, ReachRule, observe_frame
from mistool.tracking.split import split_instance

__all__ = [
    "REACH_RULES",
    "CostWeights",
    "IdentityTracker",
    "InstanceObservation",
    "PartObservation",
    "ReachRule",
    "Track",
    "TrackState",
    "observe_frame",
    "split_instance",
    "track_cost",
    "unknown_values",
]
