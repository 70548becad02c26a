"""``synthesize``: render a sequence with exact ground truth and write it as a folder.

The folder (written to a temporary folder beside ``out_dir``, then renamed, so a failure
never leaves a half-written sequence) holds:

- ``000000.png ...``: 8-bit label images (the possibly corrupted masks);
- ``mistool.toml``: fps, label preset, camera, shaft diameter and clasper length, and
  ``[[instrument]]`` tables when instruments have their own label values;
- ``truth.csv``: the motion table of the truth (see :func:`truth_rows`);
- ``mask_areas.csv``: per truth row (``frame``, ``instrument``, ``part``) its pixels left
  in the written masks, ``mask_area_px`` (:func:`mask_area_rows`; the corruptions change
  it, never the truth);
- ``synth.json``: the options and seed that produced it;
- ``masks.avi`` (with ``video``): the same masks through a lossy video codec.

Label values: by default every instrument shares the preset's values, as in the real
EndoVis'15 (shaft 160, clasper 70) and EndoVis'17 masks (shaft 10, wrist 20, clasper 30);
instruments are then told apart by connectivity, and instrument names in a prediction may
differ from the truth's ``"1"``, ``"2"`` (``mistool eval`` matches them). With
``distinct_labels`` instrument ``i`` (0-based) gets value ``v - i`` for each preset value
``v`` and its own ``[[instrument]]`` table. Presets without a wrist label (endovis15) label
the wrist as clasper: the metallic head.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from mistool.config import (
    CAMERA_MODELS,
    COLOUR_PRESETS,
    PRESETS,
    Camera,
    Config,
    load_config,
    make_camera,
)
from mistool.errors import ConfigError, InputPathError
from mistool.export import atomic_write, write_csv, write_table_csv
from mistool.geometry import mask_box
from mistool.model import RotatedBox, TrackTable
from mistool.paper import paper_motion
from mistool.synth.corrupt import Corruptions, Corruptor
from mistool.synth.motion import MotionOptions, generate_motion
from mistool.synth.render import PART_CODES, RayCaster
from mistool.synth.scene import (
    ImageCamera,
    InstrumentGeometry,
    InstrumentPose,
    PartGeometry,
    instrument_parts,
    matrix_to_wxyz,
    merged_head,
)

#: Lossy codecs this OpenCV build can write into ``masks.avi`` (checked with OpenCV 5.0).
VIDEO_CODECS: dict[str, str] = {"mjpg": "MJPG", "xvid": "XVID", "mp4v": "mp4v"}


@dataclass(frozen=True)
class SceneOptions:
    """The camera and instruments of a synthetic sequence."""

    width: int = 720
    """Image width (px)."""
    height: int = 576
    """Image height (px)."""
    focal_px: float = 600.0
    """Focal length (px), square pixels, principal point at the image centre."""
    distortion: tuple[float, ...] = ()
    """Lens distortion, OpenCV's coefficients (pinhole: 4, 5, 8, 12 or 14; fisheye: 4);
    the masks are rendered through it exactly (:mod:`mistool.synth.render`)."""
    lens_model: str = "pinhole"
    """``"pinhole"`` or ``"fisheye"`` (:class:`mistool.config.Camera`'s ``model``)."""
    tool: str = "robotic"
    """``"robotic"`` (8 mm shaft, bending wrist) or ``"laparoscopic"`` (5 mm, straight)."""
    shaft_diameter_mm: float | None = None
    """Override of the tool's shaft diameter (mm)."""
    motion: MotionOptions = field(default_factory=MotionOptions)
    """How the instruments move."""


@dataclass(frozen=True)
class SynthResult:
    """What :func:`synthesize` wrote."""

    path: Path
    """The sequence folder."""
    truth: TrackTable
    """The ground truth (as written to ``truth.csv``)."""
    config: Config
    """The sequence's ``mistool.toml``, as mistool reads it."""


def label_values(preset: str, instruments: int, distinct: bool) -> list[dict[str, int]]:
    """Per instrument: label part -> value (see the module docstring)."""
    grey = [p for p in PRESETS if p not in COLOUR_PRESETS]
    if preset not in grey:
        raise ConfigError(f"preset {preset!r} is not one of {', '.join(grey)} (grey-level presets)")
    base = PRESETS[preset]
    if not distinct:
        return [dict(base) for _ in range(instruments)]
    values = sorted(base.values())
    gap = min([b - a for a, b in zip(values[:-1], values[1:], strict=True)] + [values[0] + 1])
    if instruments > gap:
        raise ConfigError(
            f"distinct labels: preset {preset} leaves room for at most {gap} "
            f"instruments, got {instruments}"
        )
    return [{p: v - i for p, v in base.items()} for i in range(instruments)]


def _label_part(preset: str, part3d: str) -> str:
    """The label part a 3D part is painted as (no wrist label -> clasper)."""
    if part3d == "wrist" and "wrist" not in PRESETS[preset]:
        return "clasper"
    return part3d


def _part_box(mask: np.ndarray) -> tuple[RotatedBox, np.ndarray, int] | None:
    """The part's box exactly as tracking measures it (:func:`mistool.geometry.mask_box`:
    every pixel, grown to pixel edges), so truth and estimates share one convention."""
    area = int(np.count_nonzero(mask))
    if area == 0:
        return None
    fit = mask_box(mask.astype(np.uint8))
    if fit is None:
        return None
    box, corners = fit
    return box, corners, area


def truth_rows(
    frame: int,
    fps: float,
    labels_clean: np.ndarray,
    instance: np.ndarray,
    alone: list[np.ndarray],
    parts: list[list[PartGeometry]],
    poses: list[InstrumentPose],
    values: list[dict[str, int]],
    names: list[str],
) -> list[dict]:
    """The truth rows of one frame: one per instrument x label part with >= 1 clean pixel.

    ``cx_px .. angle_deg``, corners and ``area_px`` come from the clean mask of that
    instrument's part (its own pixels after occlusion by nearer instruments);
    ``end_*``, ``axis_*``, ``start_*``, ``q*`` and ``trocar_*`` are exact from the 3D model;
    ``visible_frac`` is the part's clean area over its area with no other instrument in
    the scene (``alone``: per instrument, the label image it would have alone).
    """
    rows: list[dict] = []
    for i, (pgs, pose) in enumerate(zip(parts, poses, strict=True)):
        by_name = {pg.part: pg for pg in pgs}
        if "wrist" not in values[i]:  # the wrist is painted as clasper: one head part
            by_name["clasper"] = merged_head(by_name["wrist"], by_name["clasper"])
        mine = instance == i + 1
        for lpart, value in values[i].items():
            found = _part_box(mine & (labels_clean == value))
            if found is None:
                continue
            box, corners, area = found
            geo = by_name[lpart]
            full = int(np.count_nonzero(alone[i] == value)) if len(alone) > 1 else area
            row = {
                "frame": frame,
                "time_s": frame / fps,
                "instrument": names[i],
                "part": lpart,
                "cx_px": box.cx,
                "cy_px": box.cy,
                "length_px": box.length,
                "width_px": box.width,
                "angle_deg": box.angle_deg,
                "area_px": float(area),
            }
            for k in range(4):
                row[f"x{k + 1}_px"], row[f"y{k + 1}_px"] = corners[k]
            axis = geo.rotation[:, 2]
            q = matrix_to_wxyz(geo.rotation)
            for j, ax in enumerate("xyz"):
                row[f"end_{ax}_mm"] = geo.end_mm[j]
                row[f"axis_{ax}"] = axis[j]
                row[f"start_{ax}_mm"] = geo.start_mm[j]
                row[f"trocar_{ax}_mm"] = pose.trocar_mm[j]
            row.update(qw=q[0], qx=q[1], qy=q[2], qz=q[3])
            row.update(
                visible_frac=area / max(full, area),
                roll_deg=pose.roll_deg,
                wrist_deg=pose.wrist_deg,
                jaw_yaw_deg=pose.jaw_yaw_deg,
                jaw_open_deg=pose.jaw_open_deg,
                insertion_mm=pose.insertion_mm,
            )
            rows.append(row)
    return rows


def mask_area_rows(
    frame: int,
    labels: np.ndarray,
    instance: np.ndarray,
    truth: list[dict],
    values: list[dict[str, int]],
    names: list[str],
) -> list[dict]:
    """Rows of ``mask_areas.csv`` for one frame's truth rows ``truth``: ``frame``,
    ``instrument``, ``part`` and ``mask_area_px``, that part's pixels left in the written
    (corrupted) label image ``labels``; ``instance``: (H, W) uint8, i + 1 where
    instrument i was rendered."""
    index = {name: i for i, name in enumerate(names)}
    out = []
    for row in truth:
        i = index[row["instrument"]]
        mine = (instance == i + 1) & (labels == values[i][row["part"]])
        out.append(
            {
                "frame": frame,
                "instrument": row["instrument"],
                "part": row["part"],
                "mask_area_px": float(np.count_nonzero(mine)),
            }
        )
    return out


def _rows_to_table(rows: list[dict]) -> TrackTable:
    if not rows:
        from mistool.model import empty_table

        return empty_table()
    names = list(rows[0])
    return TrackTable({n: [r.get(n, math.nan) for r in rows] for n in names})


def _toml_text(
    preset: str,
    fps: float,
    cam: Camera,
    geom: InstrumentGeometry,
    values: list[dict[str, int]],
    distinct: bool,
    names: list[str],
    ranges: dict[str, tuple[int, int]] | None,
    header: str,
) -> str:
    lines = [f"# {line}" for line in header.splitlines()]
    lines += [
        f"fps = {fps!r}",
        f'labels = "{preset}"',
        f"shaft_diameter_mm = {geom.shaft_diameter_mm!r}",
        f"clasper_length_mm = {geom.clasper_length_mm!r}",
        "",
    ]
    if ranges:
        lines += ["# value ranges wide enough for the lossy masks.avi", "[parts]"]
        lines += [f"{p} = [{lo}, {hi}]" for p, (lo, hi) in ranges.items()] + [""]
    lines += [
        "[camera]",
        f"fx = {cam.fx!r}",
        f"fy = {cam.fy!r}",
        f"cx = {cam.cx!r}",
        f"cy = {cam.cy!r}",
    ]
    if cam.distorted:
        lines += [
            f'model = "{cam.model}"',
            f"distortion = [{', '.join(repr(d) for d in cam.distortion)}]",
        ]
    lines += [""]
    if distinct:
        for name, vals in zip(names, values, strict=True):
            lines += ["[[instrument]]", f'name = "{name}"']
            lines += [f"{p} = {v}" for p, v in vals.items()]
            lines += [
                f"shaft_diameter_mm = {geom.shaft_diameter_mm!r}",
                f"clasper_length_mm = {geom.clasper_length_mm!r}",
                "",
            ]
    return "\n".join(lines)


def _video_ranges(preset: str) -> dict[str, tuple[int, int]]:
    """Inclusive value ranges around each preset value, half-way to its neighbours."""
    base = PRESETS[preset]
    vals = sorted(base.values())
    out = {}
    for p, v in base.items():
        k = vals.index(v)
        lo = (v + vals[k - 1]) // 2 + 1 if k > 0 else v - 30
        hi = (v + vals[k + 1]) // 2 if k + 1 < len(vals) else v + 30
        out[p] = (max(1, lo), min(255, hi))
    return out


def _prepare_out(out: Path, force: bool) -> None:
    if out.exists():
        if not out.is_dir():
            raise InputPathError(f"{out}: exists and is not a folder")
        if any(out.iterdir()):
            if not force:
                raise InputPathError(
                    f"{out}: folder is not empty; choose another folder or "
                    "pass --force to replace it"
                )
            if not (out / "synth.json").is_file():
                # --force replaces an earlier synth output, never an arbitrary folder
                raise InputPathError(
                    f"{out}: --force only replaces a folder written by "
                    "mistool synth (with synth.json); this one is not"
                )
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputPathError(f"{out.parent}: cannot create folder: {exc.strerror or exc}") from None


def _swap_in(tmp: Path, out: Path) -> None:
    """Replace ``out`` by ``tmp`` (renames; the old folder is removed last)."""
    if out.exists():
        trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
        os.replace(out, trash / out.name)
        os.replace(tmp, out)
        shutil.rmtree(trash, ignore_errors=True)
    else:
        os.replace(tmp, out)


def _check_options(
    frames: int,
    instruments: int,
    fps: float,
    sc: SceneOptions,
    video: str | None,
    distinct_labels: bool,
) -> None:
    """Raise :class:`ConfigError` for an invalid :func:`synthesize` option."""
    if not isinstance(frames, int) or frames < 1:
        raise ConfigError(f"frames must be an integer >= 1, got {frames!r}")
    if not isinstance(instruments, int) or not 1 <= instruments <= 4:
        raise ConfigError(f"instruments must be an integer in 1..4, got {instruments!r}")
    if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
        raise ConfigError(f"fps must be a number > 0, got {fps!r}")
    if sc.width < 16 or sc.height < 16 or not sc.focal_px > 0:
        raise ConfigError(
            f"image {sc.width}x{sc.height} with focal {sc.focal_px} px: need "
            "width, height >= 16 and a focal length > 0"
        )
    if sc.lens_model not in CAMERA_MODELS:
        raise ConfigError(f"lens model {sc.lens_model!r} is not one of {', '.join(CAMERA_MODELS)}")
    if sc.shaft_diameter_mm is not None and not 0 < sc.shaft_diameter_mm <= 30:
        raise ConfigError(f"shaft diameter must be in (0, 30] mm, got {sc.shaft_diameter_mm}")
    if sc.tool not in ("robotic", "laparoscopic"):
        raise ConfigError(f"tool must be robotic or laparoscopic, got {sc.tool!r}")
    if video is not None and video not in VIDEO_CODECS:
        raise ConfigError(f"video codec {video!r} is not one of {', '.join(VIDEO_CODECS)}")
    if video is not None and distinct_labels:
        raise ConfigError(
            "video and distinct labels do not mix: a lossy codec smears the "
            "close per-instrument values into each other"
        )


def _video_writer(path: Path, video: str, fps: float, size_wh: tuple[int, int]) -> cv2.VideoWriter:
    """An open grey-video writer with codec ``video`` (see :data:`VIDEO_CODECS`)."""
    writer = cv2.VideoWriter(
        str(path), cv2.VideoWriter.fourcc(*VIDEO_CODECS[video]), fps, size_wh, False
    )
    if not writer.isOpened():
        raise ConfigError(f"this OpenCV build cannot write {video} video")
    return writer


def _write_png(path: Path, labels: np.ndarray, level: int) -> None:
    """Write one label image as PNG at zlib ``level``."""
    if not cv2.imwrite(str(path), labels, [cv2.IMWRITE_PNG_COMPRESSION, int(level)]):
        raise InputPathError(f"{path}: cannot write")


def synthesize(
    out_dir: str | Path,
    frames: int = 100,
    instruments: int = 2,
    seed: int = 0,
    preset: str = "endovis15",
    fps: float = 25.0,
    corruptions: Corruptions | None = None,
    scene: SceneOptions | None = None,
    *,
    distinct_labels: bool = False,
    video: str | None = None,
    force: bool = False,
    png_compression: int = 3,
    progress: Callable[[int, int], None] | None = None,
) -> SynthResult:
    """Render a synthetic mask sequence with its exact ground truth into ``out_dir``.

    Args:
        out_dir: the sequence folder to create (must be absent or empty, unless ``force``).
        frames: number of frames, >= 1.
        instruments: number of instruments, 1..4.
        seed: seeds the motion and every corruption; same seed and options, same files.
        preset: label preset (``endovis15`` | ``endovis17`` | ``ternaus``).
        fps: frame rate (Hz), > 0.
        corruptions: mask corruptions (none by default); never change ``truth.csv``.
        scene: camera and instrument options.
        distinct_labels: give each instrument its own label values and ``[[instrument]]``.
        video: also write ``masks.avi`` with this lossy codec (see :data:`VIDEO_CODECS`).
        force: replace a non-empty ``out_dir``.
        png_compression: PNG compression level 0-9.
        progress: called as ``progress(done, total)`` after each frame.

    Returns:
        A :class:`SynthResult` with the folder, the truth table and the config.

    Raises:
        ConfigError: invalid option. InputPathError: ``out_dir`` not writable or not empty.
    """
    corr = corruptions or Corruptions()
    sc = scene or SceneOptions()
    _check_options(frames, instruments, fps, sc, video, distinct_labels)
    values = label_values(preset, instruments, distinct_labels)
    out = Path(out_dir)
    _prepare_out(out, force)

    lens = make_camera(
        [sc.focal_px, sc.focal_px, 0.0, 0.0], list(sc.distortion), sc.lens_model, "synth lens"
    )
    cam = ImageCamera.default(sc.width, sc.height, sc.focal_px, lens.distortion, lens.model)
    geom = InstrumentGeometry.for_tool(sc.tool, sc.shaft_diameter_mm)
    motion = sc.motion
    if sc.tool == "laparoscopic" and motion.wrist:
        motion = MotionOptions(**{**asdict(motion), "wrist": False})
    poses = generate_motion(cam, [geom] * instruments, frames, float(fps), seed, motion)
    caster = RayCaster(cam)
    corruptor = Corruptor(corr, (sc.height, sc.width), frames, instruments, float(fps), seed)
    names = [str(i + 1) for i in range(instruments)]
    all_values = sorted({v for vals in values for v in vals.values()})
    # label lookup: (instance, 3D part code) -> label value
    lut = np.zeros((instruments + 1, 4), dtype=np.uint8)
    for i in range(instruments):
        for part3d, code in PART_CODES.items():
            lut[i + 1, code] = values[i][_label_part(preset, part3d)]

    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp.", dir=out.parent))
    except OSError as exc:
        raise InputPathError(f"{out.parent}: cannot write here: {exc.strerror or exc}") from None
    writer = None
    try:
        if video is not None:
            writer = _video_writer(tmp / "masks.avi", video, float(fps), (sc.width, sc.height))
        rows: list[dict] = []
        areas: list[dict] = []
        for f in range(frames):
            frame_poses = [p[f] for p in poses]
            parts = [instrument_parts(p, geom) for p in frame_poses]
            buf = caster.render(parts)
            clean = lut[buf.instance, buf.part]
            alone = [lut[i + 1][a] for i, a in enumerate(buf.alone)] if instruments > 1 else []
            frame_rows = truth_rows(
                f, float(fps), clean, buf.instance, alone, parts, frame_poses, values, names
            )
            rows += frame_rows
            shown = buf.instance  # which instrument each written pixel was rendered from
            if corr.bias_px:  # the biased masks are rendered; the truth stays clean
                bb = caster.render(parts, bias_px=float(corr.bias_px))
                shown = bb.instance
                labels = corruptor.apply(
                    lut[bb.instance, bb.part], bb.instance, bb.part, f, all_values, biased=True
                )
            elif corr.any():
                labels = corruptor.apply(clean, buf.instance, buf.part, f, all_values)
            else:
                labels = clean
            areas += mask_area_rows(f, labels, shown, frame_rows, values, names)
            _write_png(tmp / f"{f:06d}.png", labels, png_compression)
            if writer is not None:
                writer.write(labels)
            if progress is not None:
                progress(f + 1, frames)
        if writer is not None:
            writer.release()
            writer = None
        truth = _add_paper_motion(_rows_to_table(rows), cam.camera.fx)
        write_csv(truth, tmp / "truth.csv")
        with atomic_write(tmp / "mask_areas.csv", "w", newline="", encoding="utf-8") as fh:
            write_table_csv(_rows_to_table(areas).sorted(), fh)
        opts = {
            "frames": frames,
            "instruments": instruments,
            "seed": seed,
            "preset": preset,
            "fps": float(fps),
            "distinct_labels": distinct_labels,
            "video": video,
            "corruptions": asdict(corr),
            "scene": asdict(sc),
        }
        header = "written by mistool synth; ground truth in truth.csv, options in synth.json"
        ranges = _video_ranges(preset) if video is not None else None
        with atomic_write(tmp / "mistool.toml", "w", encoding="utf-8") as fh:
            fh.write(
                _toml_text(
                    preset,
                    float(fps),
                    cam.camera,
                    geom,
                    values,
                    distinct_labels,
                    names,
                    ranges,
                    header,
                )
            )
        with atomic_write(tmp / "synth.json", "w", encoding="utf-8") as fh:
            json.dump(opts, fh, indent=2, sort_keys=True)
            fh.write("\n")
        os.chmod(tmp, 0o755)
        _swap_in(tmp, out)
    except BaseException:
        if writer is not None:
            writer.release()
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    config = load_config(out / "mistool.toml")
    return SynthResult(out, truth, config)


def _add_paper_motion(truth: TrackTable, focal_px: float) -> TrackTable:
    """Fill the paper's motion columns of the truth: Algorithm 2 applied to the clean
    boxes with ``f = fx`` (what ``mistool track`` computes on perfect masks)."""
    truth = truth.sorted()
    return paper_motion(truth, focal_px=focal_px) if truth.num_rows else truth
