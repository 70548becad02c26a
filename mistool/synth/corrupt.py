"""Realistic corruptions of rendered label images, each optional and seeded.

They imitate what a segmentation network's masks look like, and change only the masks,
never the ground truth (``truth.csv`` always describes the clean, exact projection):

- ``jitter_px``: boundaries wobble by up to this many px (a smooth random displacement
  field, coherent along an edge, resampled every frame);
- ``bias_px``: a systematic over- (> 0) or under-segmentation (< 0): every outline moves
  outward (inward) by this many px, fractions included. ``synthesize`` renders it
  exactly: the ray caster inflates every primitive's radius by ``bias_px`` px at its depth
  (:mod:`mistool.synth.render`), so a 0.5 px bias moves a shaft's limb lines by 0.5 px.
  :meth:`Corruptor.apply` on a label image alone (no geometry) approximates it by a
  morphological dilation (> 0) or erosion (< 0) by ``round(|bias_px|)`` whole pixels;
- ``holes``: mean number of specular-highlight holes per frame (small ellipses of
  background on the instrument, 2-7 px);
- ``speckle``: mean number of label specks per frame (1-3 px blobs of a random part value,
  anywhere: false positives and wrong labels);
- ``occluders``: number of tissue blobs (unions of three ellipses, 30-90 px across) hiding
  whatever is under them; blob ``k`` hovers over instrument ``k mod K``'s head (the mean of
  its wrist and clasper pixels, else of its shaft), drifting about it on a slow smooth path,
  as tissue that the jaws work in covers them;
- ``hide_clasper``: fraction of frames in which the clasper (and wrist) of a tool is hidden
  (in runs of about a second, per instrument);
- lossy video encoding is done by the writer (``video`` codec) on the corrupted frames.

The random stream of each corruption depends only on ``(seed, corruption, frame)``, so
turning one corruption on or off does not change the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import cv2
import numpy as np


@dataclass(frozen=True)
class Corruptions:
    """Which corruptions to apply, and how strongly (all off by default)."""

    jitter_px: float = 0.0
    """Boundary jitter amplitude (px)."""
    bias_px: float = 0.0
    """Outline moved outward (> 0) or inward (< 0) by this many px (sub-pixel)."""
    holes: float = 0.0
    """Mean number of specular holes per frame."""
    speckle: float = 0.0
    """Mean number of label specks per frame."""
    occluders: int = 0
    """Number of tissue blobs drifting over the scene."""
    hide_clasper: float = 0.0
    """Fraction of frames in which each tool's clasper is hidden, in [0, 1]."""

    def any(self) -> bool:
        """True if any corruption is on."""
        return any(getattr(self, f.name) for f in fields(self))

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not math.isfinite(v) or (f.name != "bias_px" and v < 0):
                raise ValueError(f"{f.name} must be a finite number >= 0, got {v!r}")
        if self.hide_clasper > 1:
            raise ValueError(f"hide_clasper is a fraction in [0, 1], got {self.hide_clasper}")


_JITTER, _BIAS, _HOLES, _SPECKLE, _OCCLUDE, _HIDE = range(1, 7)


def _rng(seed: int, which: int, frame: int = -1) -> np.random.Generator:
    return np.random.default_rng([seed, 1000 + which, frame + 1])


class Corruptor:
    """Applies :class:`Corruptions` frame by frame (state: occluder paths, hidden runs)."""

    def __init__(
        self,
        corruptions: Corruptions,
        shape: tuple[int, int],
        frames: int,
        instruments: int,
        fps: float,
        seed: int,
    ) -> None:
        self.c = corruptions
        self.shape = shape
        self.seed = seed
        h, w = shape
        # occluders: offsets from the anchored instrument's head on slow smooth paths
        rng = _rng(seed, _OCCLUDE)
        self._blobs = []
        for k in range(corruptions.occluders):
            amp = rng.uniform(10.0, 45.0, 2)
            freq = rng.uniform(0.05, 0.25, 2)
            phase = rng.uniform(0, 2 * math.pi, 2)
            lobes = [
                (rng.uniform(-15, 15, 2), rng.uniform(15, 40, 2), rng.uniform(0, 180))
                for _ in range(3)
            ]
            self._blobs.append((k % max(1, instruments), amp, freq, phase, lobes))
        self.fps = fps
        # hidden clasper: per instrument, runs of ~1 s covering the requested fraction
        self._hidden = np.zeros((instruments, frames), dtype=bool)
        if corruptions.hide_clasper > 0 and frames:
            rng = _rng(seed, _HIDE)
            run = max(1, int(round(fps)))
            for i in range(instruments):
                target = int(round(corruptions.hide_clasper * frames))
                for s in rng.permutation(max(1, frames - run + 1)):
                    if self._hidden[i].sum() >= target:
                        break
                    self._hidden[i, s : s + run] = True
                idx = np.flatnonzero(self._hidden[i])
                self._hidden[i, idx[target:]] = False  # trim the overshoot

    def apply(
        self,
        labels: np.ndarray,
        instance: np.ndarray,
        part: np.ndarray,
        frame: int,
        values: list[int],
        biased: bool = False,
    ) -> np.ndarray:
        """Corrupt one frame.

        Args:
            labels: (H, W) uint8/uint16 clean label image (not modified), or the image
                already rendered with the boundary bias when ``biased``.
            instance: (H, W) uint8, 0 background, i + 1 for instrument i.
            part: (H, W) uint8 3D part codes (1 shaft, 2 wrist, 3 clasper).
            frame: frame index (seeds the random streams).
            values: the part label values used in this sequence (for speckle).
            biased: ``labels`` already carry ``bias_px`` (rendered by the ray caster);
                otherwise it is approximated morphologically (whole pixels).

        Returns:
            The corrupted label image, same shape and dtype.
        """
        c = self.c
        out = labels.copy()
        if c.hide_clasper > 0:
            for i in range(self._hidden.shape[0]):
                if self._hidden[i, frame]:
                    out[(instance == i + 1) & (part >= 2)] = 0
        if c.bias_px and not biased:
            out = _bias(out, int(round(c.bias_px)))
        if c.jitter_px > 0:
            out = self._jitter(out, frame)
        if c.holes > 0:
            self._holes(out, frame)
        if c.occluders > 0:
            out[self._occluder_mask(instance, part, frame) > 0] = 0
        if c.speckle > 0:
            self._speckle(out, frame, values)
        return out

    def _jitter(self, out: np.ndarray, frame: int) -> np.ndarray:
        """Smooth random displacement field (up to ``jitter_px``), nearest-neighbour remap."""
        c = self.c
        h, w = self.shape
        rng = _rng(self.seed, _JITTER, frame)
        gh, gw = 6, 8
        dx: np.ndarray = rng.uniform(-c.jitter_px, c.jitter_px, (gh, gw)).astype(np.float32)
        dy: np.ndarray = rng.uniform(-c.jitter_px, c.jitter_px, (gh, gw)).astype(np.float32)
        dx = cv2.resize(dx, (w, h), interpolation=cv2.INTER_CUBIC)
        dy = cv2.resize(dy, (w, h), interpolation=cv2.INTER_CUBIC)
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        return cv2.remap(
            out,
            gx + dx,
            gy + dy,
            interpolation=cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_REPLICATE,
        )

    def _holes(self, out: np.ndarray, frame: int) -> None:
        """Small background ellipses punched into the masks (Poisson count); in place."""
        rng = _rng(self.seed, _HOLES, frame)
        ys, xs = np.nonzero(out)
        n = rng.poisson(self.c.holes)
        if len(xs) and n:
            pick = rng.integers(0, len(xs), n)
            for x, y in zip(xs[pick], ys[pick], strict=True):
                hole_axes = (int(rng.integers(2, 8)), int(rng.integers(1, 4)))
                cv2.ellipse(
                    out, (int(x), int(y)), hole_axes, float(rng.uniform(0, 180)), 0, 360, 0, -1
                )

    def _occluder_mask(self, instance: np.ndarray, part: np.ndarray, frame: int) -> np.ndarray:
        """(H, W) uint8: 1 where an occluder blob (drifting over its tool's clasper) is."""
        h, w = self.shape
        t = frame / self.fps
        mask = np.zeros((h, w), dtype=np.uint8)
        anchors: dict[int, np.ndarray | None] = {}
        for inst, amp, freq, phase, lobes in self._blobs:
            if inst not in anchors:
                mine = instance == inst + 1
                ys, xs = np.nonzero(mine & (part >= 2))
                if len(xs) == 0:
                    ys, xs = np.nonzero(mine)
                anchors[inst] = np.array([xs.mean(), ys.mean()]) if len(xs) else None
            anchor = anchors[inst]
            if anchor is None:  # nothing of that tool to hide
                continue
            p = anchor + amp * np.sin(2 * math.pi * freq * t + phase)
            for off, axes, ang in lobes:
                q = p + off
                cv2.ellipse(
                    mask,
                    (int(round(q[0])), int(round(q[1]))),
                    (int(axes[0]), int(axes[1])),
                    float(ang),
                    0,
                    360,
                    1,
                    -1,
                )
        return mask

    def _speckle(self, out: np.ndarray, frame: int, values: list[int]) -> None:
        """Small discs of random part values (Poisson count); in place."""
        h, w = self.shape
        rng = _rng(self.seed, _SPECKLE, frame)
        n = rng.poisson(self.c.speckle)
        for _ in range(n):
            x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
            r = int(rng.integers(0, 2))
            v = int(values[int(rng.integers(0, len(values)))])
            cv2.circle(out, (x, y), r, v, -1)


def _bias(labels: np.ndarray, px: int) -> np.ndarray:
    """Dilate (px > 0) or erode (px < 0) every part value's region by ``|px|`` pixels."""
    if px == 0:
        return labels.copy()
    k = 2 * abs(px) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    out = labels.copy()
    if px < 0:  # shrink the instruments' outline; inner part boundaries stay
        fg = (labels != 0).astype(np.uint8)
        shrunk = cv2.erode(fg, kernel, borderType=cv2.BORDER_REPLICATE) > 0
        out[(fg > 0) & ~shrunk] = 0
        return out
    for v in (v for v in np.unique(labels) if v != 0):
        grown = cv2.dilate((labels == v).astype(np.uint8), kernel) > 0
        out[grown & (out == 0)] = v
    return out
