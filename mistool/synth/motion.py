"""Smooth, seeded instrument motion about a fixed trocar (the laparoscopic fulcrum).

Each instrument enters through its own trocar ``T`` outside the view and aims its tip at a
work point ``G(t)`` that wanders smoothly inside the view (sums of slow sinusoids with
seeded frequencies and phases), at depths of 50-150 mm. The shaft axis is the direction
``T -> G`` (pivoting about ``T``); the insertion brings the tip to ``G``; tools *enter* by
sliding in from the trocar during their first second or two, and optionally *leave* the
view (a full retraction and a return). Roll about the shaft, wrist bend and jaw yaw follow
smooth curves; the jaws open and close in grasping cycles. With two or more instruments,
the work points sweep across each other so that tools cross.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mistool.synth.scene import ImageCamera, InstrumentGeometry, InstrumentPose

#: Joint depth range the motion keeps the working tools in (mm).
DEPTH_RANGE_MM = (50.0, 150.0)


@dataclass(frozen=True)
class MotionOptions:
    """How instruments move (all seeded)."""

    enter: bool = True
    """Tools slide in from out of view at the start (staggered)."""
    leave_view: bool = False
    """Each tool retracts out of the view once and comes back."""
    cross: bool = True
    """Work points of different tools sweep across each other."""
    wrist: bool = True
    """Wrist bending and jaw yaw (robotic); False keeps the head straight (laparoscopic)."""
    speed: float = 1.0
    """Scales every motion frequency."""


def _smooth(
    rng: np.random.Generator, t: np.ndarray, fmin: float, fmax: float, n: int = 3
) -> np.ndarray:
    """A smooth random curve in about [-1, 1]: sum of ``n`` sinusoids (Hz range given)."""
    freqs = rng.uniform(fmin, fmax, n)
    phases = rng.uniform(0, 2 * math.pi, n)
    amps = rng.uniform(0.5, 1.0, n)
    y = sum(
        a * np.sin(2 * math.pi * f * t + p) for a, f, p in zip(amps, freqs, phases, strict=True)
    )
    return y / amps.sum() * 1.6


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def generate_motion(
    cam: ImageCamera,
    geoms: list[InstrumentGeometry],
    frames: int,
    fps: float,
    seed: int,
    options: MotionOptions | None = None,
) -> list[list[InstrumentPose]]:
    """Poses of every instrument in every frame: ``result[i][frame]``."""
    opts = options or MotionOptions()
    rng = np.random.default_rng([seed, 7919])
    t = np.arange(frames, dtype=np.float64) / fps * opts.speed
    duration = max(frames / fps * opts.speed, 1e-9)
    c = cam.camera
    k = len(geoms)
    out: list[list[InstrumentPose]] = []
    for i, geom in enumerate(geoms):
        # trocar: instruments come from the right, left, top, bottom, in turn
        side = [(1.0, 0.0), (-1.0, 0.0), (0.0, -1.0), (0.0, 1.0)][i % 4]
        lateral = rng.uniform(95.0, 125.0)
        trocar = np.array(
            [
                side[0] * lateral + (1 - abs(side[0])) * rng.uniform(-30, 30),
                side[1] * lateral + (1 - abs(side[1])) * rng.uniform(-50, -10),
                rng.uniform(-10.0, 15.0),
            ]
        )
        # work point G(t): depth, and image position as a fraction of the half-image
        z0 = rng.uniform(75.0, 105.0)
        z = z0 + 22.0 * _smooth(rng, t, 0.04, 0.15)
        fx = 0.25 * side[0] if side[0] else rng.uniform(-0.2, 0.2)
        fy = 0.25 * side[1] if side[1] else rng.uniform(-0.15, 0.15)
        sweep_x = 0.30 * _smooth(rng, t, 0.05, 0.18)
        sweep_y = 0.25 * _smooth(rng, t, 0.05, 0.2)
        if opts.cross and k > 1 and side[0]:
            # a slow sweep towards and past the image centre so that tools cross
            period = rng.uniform(0.6, 0.9) * max(duration, 4.0)
            phase = rng.uniform(0, 0.3)
            sweep_x = sweep_x - side[0] * 0.45 * (
                0.5 - 0.5 * np.cos(2 * math.pi * (t / period + phase))
            )
        gx_px = c.cx + (fx + sweep_x) * cam.width / 2.0
        gy_px = c.cy + (fy + sweep_y) * cam.height / 2.0
        z = np.clip(z, DEPTH_RANGE_MM[0] + 10.0, DEPTH_RANGE_MM[1] - 10.0)
        goal = np.stack([(gx_px - c.cx) / c.fx * z, (gy_px - c.cy) / c.fy * z, z], axis=1)
        vec = goal - trocar
        dist = np.linalg.norm(vec, axis=1)
        axis = vec / dist[:, None]
        # insertion: tip near G; in/out movements along the shaft on top
        reach = dist - geom.clasper_length_mm * 0.9
        reach = reach + 6.0 * _smooth(rng, t, 0.1, 0.4)
        out_of_view = 15.0  # joint 15 mm past the trocar: the whole tool is out of view
        retract = np.zeros(frames)
        if opts.enter:
            ramp = min(1.5, 0.2 * duration)
            start = (rng.uniform(0.0, 0.1) + 0.08 * i) * min(duration, 10.0)
            retract = np.maximum(retract, 1.0 - _smoothstep((t - start) / ramp))
        if opts.leave_view:
            mid = rng.uniform(0.45, 0.7) * duration
            width = max(0.12 * duration, 1.2)
            bump = np.clip(1.6 * (1 - np.abs(t - mid) / width), 0, 1)
            retract = np.maximum(retract, _smoothstep(bump))
        insertion = out_of_view + (reach - out_of_view) * (1.0 - retract)
        roll = 70.0 * _smooth(rng, t, 0.08, 0.3)
        if opts.wrist:
            wrist = 35.0 * _smooth(rng, t, 0.1, 0.35)
            yaw = 25.0 * _smooth(rng, t, 0.1, 0.4)
        else:
            wrist = np.zeros(frames)
            yaw = np.zeros(frames)
        # grasping cycles: open, hold, close, hold
        period = rng.uniform(1.8, 3.2)
        phase = rng.uniform(0, 1)
        cyc = (t / period + phase) % 1.0
        opening = np.where(
            cyc < 0.5, _smoothstep(cyc / 0.15), 1.0 - _smoothstep((cyc - 0.5) / 0.15)
        )
        jaw = rng.uniform(35.0, 55.0) * opening
        out.append(
            [
                InstrumentPose(
                    trocar,
                    axis[f],
                    float(insertion[f]),
                    float(roll[f]),
                    float(wrist[f]),
                    float(yaw[f]),
                    float(jaw[f]),
                )
                for f in range(frames)
            ]
        )
    return out
