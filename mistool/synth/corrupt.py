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

Real-looking masks (a segmentation network's typical failures; ``mistool synth --real``
turns them all on at a typical strength):

- ``fragments``: mean number of cuts per frame: a thin band of background (1-4 px) across
  an instrument, at its shaft-wrist/clasper junction (the jaws or wrist come out as
  separate components) or across its shaft (a specular streak or a thread cutting it);
- ``rough_px``: network-like boundary noise: a fine-grained random displacement of the
  outline (coherent over ~10 px, up to this amplitude), with small bites and bumps;
- ``missed``: mean number of missed blobs per frame (8-24 px ellipses of background on an
  instrument's outline or inside it: false negatives larger than specular holes);
- ``spurious``: mean number of spurious blobs per frame (5-15 px ellipses of a part value
  anywhere: false positives larger than specks, so ``min_area_px`` does not remove them);
- ``vignette``: the endoscope's dark corners: instrument pixels outside an ellipse of
  semi-axes ``(1 + vignette) x`` half the image size are lost, so a shaft entering at a
  corner is cut by a curved edge inside the image rather than by the image border.

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
    fragments: float = 0.0
    """Mean number of thin background cuts across instruments per frame."""
    rough_px: float = 0.0
    """Network-like (fine-grained) boundary noise amplitude (px)."""
    missed: float = 0.0
    """Mean number of missed (false negative) blobs per frame."""
    spurious: float = 0.0
    """Mean number of spurious (false positive) blobs per frame."""
    vignette: float = 0.0
    """Dark corners: instrument pixels outside the ellipse of semi-axes (1 + vignette) x
    half the image size are lost; 0 = off."""

    @staticmethod
    def real(scale: float = 1.0) -> Corruptions:
        """Real-looking masks at a typical strength (``scale`` x): fragments, network-like
        boundary noise, missed and spurious blobs, dark corners, plus mild jitter, specular
        holes and specks."""
        return Corruptions(
            jitter_px=1.0 * scale,
            holes=3.0 * scale,
            speckle=10.0 * scale,
            fragments=1.5 * scale,
            rough_px=1.0 * scale,
            missed=1.0 * scale,
            spurious=1.0 * scale,
            vignette=0.12,
        )

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
_FRAGMENT, _ROUGH, _MISSED, _SPURIOUS = range(7, 11)


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
        self._vignette: np.ndarray | None = None
        if corruptions.vignette > 0:  # True outside the endoscope's visible ellipse
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
            a, b = (1 + corruptions.vignette) * w / 2.0, (1 + corruptions.vignette) * h / 2.0
            ex, ey = (xx - (w - 1) / 2.0) / a, (yy - (h - 1) / 2.0) / b
            self._vignette = ex * ex + ey * ey > 1.0
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
        return self._real_looking(out, instance, part, frame, values)

    def _real_looking(
        self,
        out: np.ndarray,
        instance: np.ndarray,
        part: np.ndarray,
        frame: int,
        values: list[int],
    ) -> np.ndarray:
        """The real-looking corruptions (module docstring), after the others."""
        c = self.c
        if c.rough_px > 0:
            out = _displace(out, _rng(self.seed, _ROUGH, frame), c.rough_px, cell_px=10)
        if c.fragments > 0:
            self._fragments(out, instance, part, frame)
        if c.missed > 0:
            self._blobs_of(out, frame, _MISSED, c.missed, None)
        if self._vignette is not None:
            out[self._vignette] = 0
        if c.spurious > 0:
            self._blobs_of(out, frame, _SPURIOUS, c.spurious, values)
        return out

    def _fragments(
        self, out: np.ndarray, instance: np.ndarray, part: np.ndarray, frame: int
    ) -> None:
        """Thin background cuts across instruments (Poisson count); in place."""
        rng = _rng(self.seed, _FRAGMENT, frame)
        n = rng.poisson(self.c.fragments)
        present = [i for i in range(1, int(instance.max()) + 1) if np.any(instance == i)]
        for _ in range(n if present else 0):
            inst = instance == present[int(rng.integers(0, len(present)))]
            shaft = inst & (part == 1) & (out != 0)
            head = (inst & (part >= 2)).astype(np.uint8)
            width = int(rng.integers(1, 5))
            ys, xs = np.nonzero(shaft)
            if len(xs) < 10:
                continue
            if rng.random() < 0.5 and head.any():  # at the junction: the head comes apart
                k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * width + 1,) * 2)
                out[(cv2.dilate(head, k) > 0) & shaft] = 0
                continue
            pts = np.stack([xs, ys], axis=1).astype(np.float64)
            centre = pts.mean(axis=0)
            cov = np.cov((pts - centre).T)
            axis = np.linalg.eigh(cov)[1][:, -1]  # the shaft's image direction
            p = pts[int(rng.integers(0, len(pts)))]
            across = np.array([-axis[1], axis[0]]) * 400.0
            band = np.zeros(out.shape, np.uint8)
            a, b = (p - across).round().astype(int), (p + across).round().astype(int)
            cv2.line(band, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1, width)
            out[(band > 0) & inst] = 0

    def _blobs_of(
        self, out: np.ndarray, frame: int, which: int, mean: float, values: list[int] | None
    ) -> None:
        """Missed blobs (``values`` None: background ellipses on instrument pixels) or
        spurious ones (ellipses of a random part value anywhere); in place."""
        h, w = self.shape
        rng = _rng(self.seed, which, frame)
        n = rng.poisson(mean)
        ys, xs = np.nonzero(out)
        for _ in range(n):
            if values is None:
                if not len(xs):
                    return
                k = int(rng.integers(0, len(xs)))
                centre = (int(xs[k]), int(ys[k]))
                axes = (int(rng.integers(8, 25)), int(rng.integers(4, 13)))
                value = 0
            else:
                centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
                axes = (int(rng.integers(5, 16)), int(rng.integers(3, 9)))
                value = int(values[int(rng.integers(0, len(values)))])
            cv2.ellipse(out, centre, axes, float(rng.uniform(0, 180)), 0, 360, value, -1)

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


def _displace(labels: np.ndarray, rng: np.random.Generator, amp: float, cell_px: int) -> np.ndarray:
    """A random displacement field (up to ``amp`` px, coherent over ``cell_px``), applied by
    nearest-neighbour remap (labels stay labels)."""
    h, w = labels.shape
    gh, gw = max(2, h // cell_px), max(2, w // cell_px)
    dx = cv2.resize(
        rng.uniform(-amp, amp, (gh, gw)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
    )
    dy = cv2.resize(
        rng.uniform(-amp, amp, (gh, gw)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC
    )
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(
        labels, gx + dx, gy + dy, interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE
    )
