#!/usr/bin/env python3
"""Regenerate ``sample_masks/``: the bundled sequence ``mistool serve`` shows by default.

Two robotic instruments (8 mm shafts) enter one after the other, pivot about their trocars,
grasp (jaws opening and closing) and cross each other; 250 frames (10 s at 25 fps),
720x576, EndoVis'15 label values (shaft 160, clasper 70) shared by both tools as in the
real dataset, the camera in ``mistool.toml``, and mild corruptions like a good
segmentation network's output (1 px boundary jitter, a specular hole and a couple of
specks per frame). ``truth.csv`` holds the exact ground truth.

Under the masks, ``video.mp4`` (``source`` in ``mistool.toml``) is a synthetic endoscope
video rendered from the same geometry without the corruptions: wet tissue (smooth pink and
red folds, vessels, fat, specular glints, the endoscope light's fall-off, a slow breathing
drift), and the instruments drawn over it as shaded cylinders (dark shafts, metallic
claspers) with their soft shadows. H.264 through PyAV (``pip install av``), one thread.

Deterministic: the same command writes byte-identical files.

Usage: python scripts/make_sample.py [--out sample_masks] [--check]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from mistool.sequence import list_frames
from mistool.synth import Corruptions, synthesize

ROOT = Path(__file__).resolve().parent.parent
SEED = 0
FRAMES = 250
MAX_BYTES = 3_000_000
#: The rendered endoscope video beside the masks (``source`` in mistool.toml).
VIDEO_NAME = "video.mp4"
#: H.264 constant rate factor of the video (higher: smaller, blurrier).
VIDEO_CRF = "30"
#: Label values of the sample's parts (EndoVis'15).
SHAFT, CLASPER = 160, 70
#: Pixels the tissue drifts with breathing (peak), and the breathing period (s).
BREATH_PX, BREATH_S = 5.0, 4.0


def _noise(rng: np.random.Generator, h: int, w: int, cell: int) -> np.ndarray:
    """Smooth noise in [0, 1] with features of about ``cell`` px."""
    small = rng.random((h // cell + 2, w // cell + 2)).astype(np.float32)
    big = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    return cv2.normalize(big, None, 0.0, 1.0, cv2.NORM_MINMAX)


def tissue(h: int, w: int, seed: int) -> np.ndarray:
    """A wet tissue texture, float32 RGB in [0, 255], shape (h, w, 3)."""
    rng = np.random.default_rng(seed)
    folds = 0.5 * _noise(rng, h, w, 90) + 0.3 * _noise(rng, h, w, 30) + 0.2 * _noise(rng, h, w, 9)
    deep = np.array([150.0, 45.0, 45.0])
    light = np.array([225.0, 125.0, 110.0])
    img = deep + folds[..., None] * (light - deep)
    fat = np.clip((_noise(rng, h, w, 120) - 0.72) * 5.0, 0.0, 1.0)[..., None]
    img = img * (1 - fat) + fat * np.array([225.0, 190.0, 120.0])
    vessels = np.zeros((h, w), np.uint8)
    for _ in range(9):  # a few wandering vessels
        pts = [rng.random(2) * (w, h)]
        heading = rng.random() * 2 * np.pi
        for _ in range(30):
            heading += rng.normal(0.0, 0.35)
            pts.append(pts[-1] + 14.0 * np.array([np.cos(heading), np.sin(heading)]))
        width = int(rng.integers(1, 4))
        cv2.polylines(vessels, [np.round(pts).astype(np.int32)], False, 255, width, cv2.LINE_AA)
    v = cv2.GaussianBlur(vessels, (0, 0), 1.2).astype(np.float32)[..., None] / 255.0
    img = img * (1 - 0.6 * v) + 0.6 * v * np.array([110.0, 20.0, 30.0])
    return img.astype(np.float32)


def _shading(mask: np.ndarray) -> np.ndarray:
    """Cylinder-like shading of a part's mask: 0 at its edges, 1 on its centre line."""
    dt = cv2.distanceTransform(mask, cv2.DIST_L2, 5)
    radius = cv2.dilate(dt, np.ones((21, 21), np.uint8))
    return np.where(mask > 0, dt / np.maximum(radius, 1.0), 0.0).astype(np.float32)


def render_frame(
    labels: np.ndarray, texture: np.ndarray, t_s: float, noise_seed: int
) -> np.ndarray:
    """One endoscope frame (RGB uint8) for a clean label image."""
    h, w = labels.shape
    dx = int(round(BREATH_PX * np.sin(2 * np.pi * t_s / BREATH_S)))
    dy = int(round(0.6 * BREATH_PX * np.sin(2 * np.pi * t_s / BREATH_S + 1.0)))
    m = int(BREATH_PX) + 1
    img = texture[m + dy : m + dy + h, m + dx : m + dx + w].copy()
    tools = ((labels == SHAFT) | (labels == CLASPER)).astype(np.uint8)
    shadow = cv2.GaussianBlur(np.roll(tools, (14, 10), axis=(0, 1)).astype(np.float32), (0, 0), 9)
    img *= (1.0 - 0.55 * shadow)[..., None]
    for value, colour, shine in (
        (SHAFT, (48.0, 50.0, 56.0), 150.0),
        (CLASPER, (150.0, 152.0, 160.0), 95.0),
    ):
        part = (labels == value).astype(np.uint8)
        if not part.any():
            continue
        s = _shading(part)[..., None]
        metal = np.array(colour) * (0.45 + 0.75 * s) + shine * s**6
        img = np.where(part[..., None] > 0, metal, img)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xx - w / 2) / (0.62 * w)) ** 2 + ((yy - h / 2) / (0.62 * h)) ** 2
    img *= (1.0 / (1.0 + 0.9 * r2))[..., None]  # the endoscope light falls off
    rng = np.random.default_rng(noise_seed)
    img += rng.normal(0.0, 2.5, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def write_video(clean: Path, out: Path, fps: float) -> None:
    """Render every frame of the clean sequence ``clean`` into the H.264 video ``out``."""
    import av  # only to regenerate the sample

    files = list_frames(clean)
    first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
    h, w = first.shape
    m = int(BREATH_PX) + 1
    texture = tissue(h + 2 * m, w + 2 * m, SEED + 1)
    with av.open(str(out), "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=int(round(fps)))
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        # One encoding thread and no lookahead threads: the same bytes on every run.
        stream.options = {
            "crf": VIDEO_CRF,
            "preset": "medium",
            "threads": "1",
            "x264-params": "threads=1:lookahead-threads=1:sliced-threads=0",
        }
        stream.codec_context.thread_count = 1
        for k, f in enumerate(files):
            labels = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            rgb = render_frame(labels, texture, k / fps, SEED * 100_000 + k)
            frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            frame.pts = k
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=ROOT / "sample_masks")
    args = ap.parse_args()
    res = synthesize(
        args.out,
        frames=FRAMES,
        instruments=2,
        seed=SEED,
        preset="endovis15",
        fps=25.0,
        corruptions=Corruptions(jitter_px=1.0, holes=1.0, speckle=2.0),
        force=True,
        png_compression=9,
    )
    with tempfile.TemporaryDirectory() as d:  # the same geometry, without corruptions
        clean = synthesize(Path(d) / "clean", frames=FRAMES, instruments=2, seed=SEED)
        write_video(clean.path, res.path / VIDEO_NAME, 25.0)
    toml = res.path / "mistool.toml"
    text = toml.read_text(encoding="utf-8").splitlines(keepends=True)
    text.insert(
        1, f'source = "{VIDEO_NAME}"  # synthetic endoscope video (scripts/make_sample.py)\n'
    )
    toml.write_text("".join(text), encoding="utf-8")
    size = sum(p.stat().st_size for p in res.path.iterdir())
    t = res.truth
    print(f"{res.path}: {FRAMES} frames, {size / 1e6:.2f} MB")
    for name in sorted(set(t["instrument"])):
        rows = t["instrument"] == name
        frames = t["frame"][rows]
        jaw = t["jaw_open_deg"][rows]
        print(
            f"  instrument {name}: visible frames {frames.min()}..{frames.max()} "
            f"({len(set(frames.tolist()))}), jaw opening {jaw.min():.0f}..{jaw.max():.0f} "
            "deg"
        )
    # crossing: instrument 1 comes from the right, 2 from the left; they have crossed
    # when 1's tip is left of 2's tip
    tips = t[t["part"] == "clasper"]
    x = {
        n: dict(
            zip(
                tips["frame"][tips["instrument"] == n].tolist(),
                tips["cx_px"][tips["instrument"] == n].tolist(),
                strict=True,
            )
        )
        for n in ("1", "2")
    }
    common = sorted(set(x["1"]) & set(x["2"]))
    crossed = sum(x["1"][f] < x["2"][f] for f in common)
    print(f"  both tips visible in {len(common)} frames; crossed in {crossed}")
    if size > MAX_BYTES:
        print(f"error: {size} bytes > {MAX_BYTES}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
