"""Motion models of the identity tracker: where a track is expected next.

A motion model keeps a track's image position (px) and velocity (px per frame), predicts
the position a few frames ahead, and takes a new measurement. The tracker uses it through
``predict`` / ``update`` / ``coast`` only, so another model can replace it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ConstantVelocity"]

#: Weight of the newest frame-to-frame velocity in the velocity estimate (exponential
#: smoothing; the rest is the previous estimate).
VELOCITY_GAIN = 0.5


@dataclass
class ConstantVelocity:
    """Constant-velocity motion of an image point, velocity smoothed exponentially.

    The velocity is the displacement between consecutive measurements per frame,
    smoothed with gain :data:`VELOCITY_GAIN` (the first one taken as is).
    """

    position: np.ndarray
    """(2,) px: where the point is believed to be at the last update."""
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """(2,) px per frame."""

    def predict(self, steps: float) -> np.ndarray:
        """(2,) px: the position ``steps`` frames after the last update."""
        return self.position + self.velocity * steps

    def predict_xy(self, steps: float) -> tuple[float, float]:
        """:meth:`predict` as two floats (the same values: one multiply and one add per
        coordinate, without numpy's per-call cost)."""
        (x, y), (vx, vy) = self.position.tolist(), self.velocity.tolist()
        return x + vx * steps, y + vy * steps

    def update(
        self,
        measured: np.ndarray,
        gap: int,
        *,
        continuous: bool,
        first: bool,
        unsure_along: np.ndarray | None = None,
    ) -> None:
        """Take a measurement ``gap`` frames after the last update.

        Args:
            measured: (2,) px.
            gap: frames since the last update, >= 1.
            continuous: the previous position was measured recently (not a coasted or
                a lost track's): the displacement gives a velocity. Otherwise the
                velocity is kept (:meth:`reset_velocity` restarts it).
            first: the track's first update: the displacement's velocity is taken as is.
            unsure_along: (2,) unit vector, or None: the measurement is unsure along it
                (the centroid of a piece of a blob slides along its shaft as the cut
                between tools moves): the displacement's component along it counts no
                faster than the velocity's own component (across it, as measured).
        """
        measured = np.asarray(measured, dtype=np.float64)
        if continuous and (unsure_along is None or first):
            # (plain floats: numpy's values, one operation at a time as its (2,) arrays
            # did, without their per-call cost)
            (mx, my), (px, py) = measured.tolist(), self.position.tolist()
            vx, vy = (mx - px) / gap, (my - py) / gap
            if not first:
                ox, oy = self.velocity.tolist()
                keep = 1.0 - VELOCITY_GAIN
                vx, vy = VELOCITY_GAIN * vx + keep * ox, VELOCITY_GAIN * vy + keep * oy
            self.velocity = np.array([vx, vy])
        elif continuous:
            d = measured - self.position
            if unsure_along is not None and not first:
                along = float(d @ unsure_along)
                most = abs(float(self.velocity @ unsure_along)) * gap
                d = d + (max(-most, min(most, along)) - along) * unsure_along
            v = d / gap
            self.velocity = (
                v if first else VELOCITY_GAIN * v + (1.0 - VELOCITY_GAIN) * self.velocity
            )
        self.position = measured

    def reset_velocity(self) -> None:
        """Forget the velocity (a track found again after being lost)."""
        self.velocity = np.zeros(2)

    def coast(self, steps: float) -> None:
        """Move the position along the velocity by ``steps`` frames (no measurement)."""
        self.position = self.predict(steps)
