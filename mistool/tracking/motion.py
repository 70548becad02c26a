"""Motion models of the identity tracker: where a track is expected next.

A motion model keeps a track's image position (px) and velocity (px per frame), predicts
the position a few frames ahead, and takes a new measurement. The tracker uses it through
``predict`` / ``update`` / ``coast`` only, so another model can replace it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ConstantVelocity"]

#: Weight of the newest frame-to-frame velocity in the velocity estimate (exponential
#: smoothing; the rest is the previous estimate).
VELOCITY_GAIN = 0.5


class ConstantVelocity:
    """Constant-velocity motion of an image point, velocity smoothed exponentially.

    The velocity is the displacement between consecutive measurements per frame,
    smoothed with gain :data:`VELOCITY_GAIN` (the first one taken as is).

    The state is four plain floats (``x``, ``y``, ``vx``, ``vy``): the identity step
    reads and updates it a few times per track and frame, and (2,) numpy arrays cost
    ~1 us per operation where a float costs tens of nanoseconds. Each operation is the
    one numpy did on each element of the arrays it replaces (the same bits).

    Args:
        position: (2,) px: where the point is at first.
        velocity: (2,) px per frame (default: still).
    """

    __slots__ = ("vx", "vy", "x", "y")

    def __init__(
        self,
        position: np.ndarray | tuple[float, float],
        velocity: np.ndarray | None = None,
    ) -> None:
        self.x: float
        self.y: float
        self.vx: float
        self.vy: float
        self.x, self.y = np.asarray(position, dtype=np.float64).tolist()
        self.vx, self.vy = 0.0, 0.0
        if velocity is not None:
            self.vx, self.vy = np.asarray(velocity, dtype=np.float64).tolist()

    def __repr__(self) -> str:
        return (
            f"ConstantVelocity(position=[{self.x!r}, {self.y!r}],"
            f" velocity=[{self.vx!r}, {self.vy!r}])"
        )

    @property
    def position(self) -> np.ndarray:
        """(2,) px: where the point is believed to be at the last update (a new array)."""
        return np.array([self.x, self.y])

    @position.setter
    def position(self, value: np.ndarray) -> None:
        self.x, self.y = np.asarray(value, dtype=np.float64).tolist()

    @property
    def velocity(self) -> np.ndarray:
        """(2,) px per frame (a new array)."""
        return np.array([self.vx, self.vy])

    @velocity.setter
    def velocity(self, value: np.ndarray) -> None:
        self.vx, self.vy = np.asarray(value, dtype=np.float64).tolist()

    def predict(self, steps: float) -> np.ndarray:
        """(2,) px: the position ``steps`` frames after the last update."""
        return np.array(self.predict_xy(steps))

    def predict_xy(self, steps: float) -> tuple[float, float]:
        """:meth:`predict` as two floats (one multiply and one add per coordinate)."""
        return self.x + self.vx * steps, self.y + self.vy * steps

    def update(
        self,
        measured: np.ndarray | tuple[float, float],
        gap: int,
        *,
        continuous: bool,
        first: bool,
        unsure_along: np.ndarray | None = None,
    ) -> None:
        """Take a measurement ``gap`` frames after the last update.

        Args:
            measured: (2,) px (an array, or two floats).
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
        if isinstance(measured, tuple):
            mx, my = float(measured[0]), float(measured[1])
        else:
            mx, my = np.asarray(measured, dtype=np.float64).tolist()
        if continuous and (unsure_along is None or first):
            vx, vy = (mx - self.x) / gap, (my - self.y) / gap
            if not first:
                keep = 1.0 - VELOCITY_GAIN
                vx, vy = VELOCITY_GAIN * vx + keep * self.vx, VELOCITY_GAIN * vy + keep * self.vy
            self.vx, self.vy = vx, vy
        elif continuous:  # (rare: numpy's dot products, as before)
            d = np.array([mx, my]) - self.position
            velocity = self.velocity
            if unsure_along is not None and not first:
                along = float(d @ unsure_along)
                most = abs(float(velocity @ unsure_along)) * gap
                d = d + (max(-most, min(most, along)) - along) * unsure_along
            v = d / gap
            self.velocity = v if first else VELOCITY_GAIN * v + (1.0 - VELOCITY_GAIN) * velocity
        self.x, self.y = mx, my

    def reset_velocity(self) -> None:
        """Forget the velocity (a track found again after being lost)."""
        self.vx = self.vy = 0.0

    def coast(self, steps: float) -> None:
        """Move the position along the velocity by ``steps`` frames (no measurement)."""
        self.x, self.y = self.predict_xy(steps)
