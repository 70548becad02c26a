"""``mistool.toml``: what the pixels of a sequence mean, its frame rate and its camera.

Layout (every key optional; no file at all means EndoVis'15 defaults)::

    fps = 25.0
    source = "Video.avi"        # the procedure's own video or RGB frame folder (viewer)
    labels = "endovis15"        # preset: endovis15 | endovis17 | ternaus | endovis18 (colour)
    min_area_px = 20            # connected specks smaller than this are ignored
    shaft_diameter_mm = 8.0     # defaults for instruments without their own table
    clasper_length_mm = 10.0

    [parts]                     # override the preset's shared part values
    shaft = 160                 # a value, an inclusive [lo, hi] range, or "#rrggbb"
    clasper = [60, 80]

    [camera]                    # enables metric 3D
    fx = 580.0
    fy = 580.0
    cx = 359.5
    cy = 287.5
    distortion = [-0.2, 0.05, 0.0, 0.0, 0.0]   # optional, OpenCV's order (4/5/8/12/14)
    model = "pinhole"           # or "fisheye" (4 coefficients)
    # or instead of [camera]: calibration = "camera.yaml" (OpenCV FileStorage
    # YAML/XML/JSON or ROS camera_info YAML; relative to this file)

    [[instrument]]              # one table per instrument with its own label values
    name = "1"
    shaft = 160
    clasper = 70
    shaft_diameter_mm = 8.0
    clasper_length_mm = 10.0

Without ``[[instrument]]`` tables every instrument shares the part values (EndoVis'17
merged masks) and instruments are told apart by connectivity.
"""

from __future__ import annotations

import errno
import math
import os
import stat
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mistool.errors import ConfigError
from mistool.parts import PARTS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CONFIG_NAME = "mistool.toml"

#: Default largest frame decoded (px): 50 MP, above 8K UHD (7680 x 4320 = 33.2 MP).
MAX_PIXELS: int = 50_000_000
#: Largest ``max_pixels`` that can be configured (2^31 - 1: OpenCV's own ceiling).
MAX_PIXELS_LIMIT: int = 2**31 - 1


#: Label presets: part -> label value (single-channel masks), or packed ``#rrggbb`` colour
#: (:func:`pack_rgb`) for the presets in :data:`COLOUR_PRESETS`. ``endovis18``: the
#: EndoVis'18 Robotic Scene Segmentation colour-coded labels (instrument-shaft ``#00ff00``,
#: instrument-clasper ``#00ffff``, instrument-wrist ``#7dff0c``; the challenge's
#: ``labels.json``, as reproduced by MMSegmentation's ``Endovis2018Dataset`` palette).
PRESETS: dict[str, dict[str, int]] = {
    "endovis15": {"shaft": 160, "clasper": 70},
    "endovis17": {"shaft": 10, "wrist": 20, "clasper": 30},
    "ternaus": {"shaft": 85, "wrist": 170, "clasper": 255},
    "endovis18": {"shaft": 0x00FF00, "wrist": 0x7DFF0C, "clasper": 0x00FFFF},
}
#: Presets whose values are ``#rrggbb`` colours (frames are read as packed RGB).
COLOUR_PRESETS: frozenset[str] = frozenset({"endovis18"})

#: Value ranges are inclusive ``(lo, hi)`` of label values. Colours ``#rrggbb`` are packed
#: as ``r << 16 | g << 8 | b`` (see :func:`pack_rgb`), the value colour frames are read as.
ValueRange = tuple[int, int]


def matching_preset(values: Any, colour: bool = False) -> str | None:
    """The label preset whose part values are among ``values`` (label values, or packed
    colours when ``colour``), for a hint when a sequence's values are not in its config:
    at least two of a preset's values (all of them for a two-part preset) must be present;
    the preset with the most values present wins. None when no preset matches."""
    present = {int(v) for v in values}
    best, best_n = None, 0
    for name, parts in PRESETS.items():
        if (name in COLOUR_PRESETS) != colour:
            continue
        n = len(present & set(parts.values()))
        if n >= min(2, len(parts)) and n > best_n:
            best, best_n = name, n
    return best


def preset_hint(values: Any, colour: bool = False) -> str:
    """``'; they are the endovis17 preset's values: set labels = "endovis17" ...'`` when
    :func:`matching_preset` finds one, else an empty string."""
    name = matching_preset(values, colour)
    if name is None:
        return ""
    return (
        f'; they are the {name} preset\'s values: set labels = "{name}" in mistool.toml '
        f"(or --labels {name})"
    )


def pack_rgb(r: int, g: int, b: int) -> int:
    """Pack an RGB colour into the single integer label colour frames are read as."""
    return (int(r) << 16) | (int(g) << 8) | int(b)


#: Lens models: OpenCV's pinhole (+ radial/tangential/prism/tilt distortion) and fisheye.
CAMERA_MODELS: tuple[str, ...] = ("pinhole", "fisheye")
#: Allowed numbers of distortion coefficients per model (OpenCV's orders).
DISTORTION_LENGTHS: dict[str, tuple[int, ...]] = {"pinhole": (4, 5, 8, 12, 14), "fisheye": (4,)}


@dataclass(frozen=True)
class Camera:
    """A calibrated camera: pinhole intrinsics (px) and OpenCV lens distortion.

    The metric pose works in the *ideal* image of the same intrinsics without distortion
    (:mod:`mistool.lens` maps pixels between the two).
    """

    fx: float
    """Focal length along x (px), > 0."""
    fy: float
    """Focal length along y (px), > 0."""
    cx: float
    """Principal point x (px)."""
    cy: float
    """Principal point y (px)."""
    distortion: tuple[float, ...] = ()
    """OpenCV distortion coefficients: pinhole ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1,
    s2, s3, s4[, tx, ty]]]])`` (4, 5, 8, 12 or 14 values), fisheye ``(k1, k2, k3, k4)``;
    empty (or all zero, pinhole) for an ideal lens."""
    model: str = "pinhole"
    """``"pinhole"`` or ``"fisheye"`` (OpenCV's ``cv::fisheye`` model)."""
    image_wh: tuple[int, int] | None = None
    """(width, height) px of the images the intrinsics belong to (from a calibration
    file), or None when not known. Masks of another size are an error unless they are a
    uniform scaling of it (:func:`mistool.lens.fit_camera`)."""

    @property
    def distorted(self) -> bool:
        """Whether the lens distorts (a fisheye always does; a pinhole with nonzero
        coefficients)."""
        return self.model == "fisheye" or any(d != 0.0 for d in self.distortion)

    @property
    def K(self) -> Any:  # noqa: N802 - the usual name of the intrinsic matrix
        """The 3x3 intrinsic matrix, float64."""
        import numpy as np

        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class InstrumentSpec:
    """One instrument with its own label values."""

    name: str
    """Instrument name, as written in the motion table's ``instrument`` column."""
    parts: dict[str, ValueRange]
    """Part name -> inclusive label value range; parts in :data:`~mistool.parts.PARTS`."""
    shaft_diameter_mm: float | None = None
    """Shaft diameter (mm), needed for metric 3D."""
    clasper_length_mm: float | None = None
    """Clasper length, joint to tip (mm)."""


@dataclass(frozen=True)
class Config:
    """Everything mistool needs to know about a sequence."""

    fps: float = 25.0
    """Frames per second of the sequence."""
    source: Path | None = None
    """The procedure's own video (or RGB frame folder), absolute, or None."""
    labels: str = "endovis15"
    """Name of the label preset the shared part values came from."""
    parts: dict[str, ValueRange] = field(
        default_factory=lambda: {p: (v, v) for p, v in PRESETS["endovis15"].items()}
    )
    """Shared part values (merged masks): part -> inclusive range."""
    camera: Camera | None = None
    """Camera intrinsics, or None (then no metric 3D)."""
    instruments: tuple[InstrumentSpec, ...] = ()
    """Instruments with their own label values; empty means merged masks."""
    min_area_px: int = 20
    """Connected components smaller than this (px) are ignored as specks."""
    shaft_diameter_mm: float | None = 8.0
    """Default shaft diameter (mm) for instruments without their own value."""
    clasper_length_mm: float | None = 10.0
    """Default clasper length (mm) for instruments without their own value."""
    max_pixels: int = MAX_PIXELS
    """Largest frame (width x height, px) decoded; checked from the image header before
    decoding. The default, :data:`MAX_PIXELS`, is 6x a 4K UHD frame and 1.5x 8K UHD."""
    colour_masks: bool = False
    """True when parts are given as ``#rrggbb`` colours: frames are read as packed RGB."""
    path: Path | None = None
    """The file this config was read from, if any."""
    calibration: Path | None = None
    """The calibration file the camera was read from (``calibration = FILE`` or
    ``--calibration``), if any."""

    def part_names(self) -> tuple[str, ...]:
        """The parts this config can produce, proximal to distal."""
        names = set(self.parts)
        for inst in self.instruments:
            names |= set(inst.parts)
        return tuple(p for p in PARTS if p in names)

    def shaft_diameter_for(self, instrument: str) -> float | None:
        """Shaft diameter (mm) of an instrument by name, falling back to the default."""
        for inst in self.instruments:
            if inst.name == instrument and inst.shaft_diameter_mm is not None:
                return inst.shaft_diameter_mm
        return self.shaft_diameter_mm

    def clasper_length_for(self, instrument: str) -> float | None:
        """Clasper length (mm) of an instrument by name, falling back to the default."""
        for inst in self.instruments:
            if inst.name == instrument and inst.clasper_length_mm is not None:
                return inst.clasper_length_mm
        return self.clasper_length_mm

    def with_overrides(self, **changes: Any) -> Config:
        """A copy with the given fields replaced (command-line options override the file);
        ``None`` values are ignored."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})


_TOP_KEYS = {
    "max_pixels",
    "fps",
    "source",
    "labels",
    "min_area_px",
    "shaft_diameter_mm",
    "clasper_length_mm",
    "parts",
    "camera",
    "calibration",
    "instrument",
}
_INSTRUMENT_KEYS = {"name", "shaft_diameter_mm", "clasper_length_mm", *PARTS}


def _where(path: Path | None) -> str:
    return str(path) if path is not None else CONFIG_NAME


#: Inclusive range of a frame rate (frames per second): time-lapse to high-speed cameras.
FPS_RANGE: tuple[float, float] = (0.01, 10_000.0)
#: Inclusive range of an instrument size (mm: shaft diameter, clasper length).
SIZE_MM_RANGE: tuple[float, float] = (0.01, 1_000.0)
#: Inclusive range of any other positive number (e.g. focal lengths in px).
POSITIVE_RANGE: tuple[float, float] = (1e-3, 1e6)
#: Largest magnitude of any other number (e.g. a principal point in px).
MAX_MAGNITUDE: float = 1e6
#: Largest ``mistool.toml`` read (bytes): a real one is under a few kB.
MAX_CONFIG_BYTES: int = 1 << 20
#: Per-key ranges; other positive numbers use :data:`POSITIVE_RANGE`.
_RANGES: dict[str, tuple[float, float]] = {
    "fps": FPS_RANGE,
    "shaft_diameter_mm": SIZE_MM_RANGE,
    "clasper_length_mm": SIZE_MM_RANGE,
}


def check_number(name: str, value: float, lo: float, hi: float) -> float:
    """``value`` as a float when it is a finite number in ``[lo, hi]``, else a one-line
    :class:`ConfigError` naming ``name`` (e.g. ``--fps``), the value and the range."""
    if not math.isfinite(value) or not lo <= value <= hi:
        raise ConfigError(f"{name} must be a number in {lo:g}..{hi:g}, got {value!r}")
    return float(value)


def _number(value: Any, key: str, where: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where}: {key} must be a number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{where}: {key} must be > 0, got {value!r}")
    base = key.rsplit(".", 1)[-1]
    lo, hi = _RANGES.get(base, POSITIVE_RANGE if positive else (-MAX_MAGNITUDE, MAX_MAGNITUDE))
    return check_number(f"{where}: {key}", value, lo, hi)


def _value_range(value: Any, key: str, where: str) -> tuple[ValueRange, bool]:
    """Parse a part's label spec; returns (inclusive range, is_colour)."""
    if isinstance(value, str):
        text = value.strip()
        if len(text) == 7 and text[0] == "#":
            try:
                r, g, b = (int(text[i : i + 2], 16) for i in (1, 3, 5))
            except ValueError:
                pass
            else:
                packed = pack_rgb(r, g, b)
                return (packed, packed), True
        raise ConfigError(
            f'{where}: {key} = {value!r} is not a label value, [lo, hi] range or "#rrggbb" colour'
        )
    if isinstance(value, int) and not isinstance(value, bool):
        lo = hi = value
    elif (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
    ):
        lo, hi = value
    else:
        raise ConfigError(
            f"{where}: {key} must be an integer label value, an inclusive "
            f'[lo, hi] range or a "#rrggbb" colour, got {value!r}'
        )
    if lo < 0 or hi > 65535:
        raise ConfigError(f"{where}: {key} = {value!r} is outside the label range 0..65535")
    if lo > hi:
        raise ConfigError(f"{where}: {key} = [{lo}, {hi}] is a reversed range; write [{hi}, {lo}]")
    return (lo, hi), False


def _parts(table: Mapping[str, Any], where: str, prefix: str) -> tuple[dict[str, ValueRange], bool]:
    parts: dict[str, ValueRange] = {}
    colour = False
    for part in PARTS:
        if part in table:
            parts[part], is_colour = _value_range(table[part], f"{prefix}{part}", where)
            colour |= is_colour
    return parts, colour


_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "distortion", "model")


def _camera(cam: Any, where: str) -> Camera:
    """Parse and validate a ``[camera]`` table."""
    if not isinstance(cam, dict):
        raise ConfigError(f"{where}: [camera] must be a table with fx, fy, cx, cy")
    extra = sorted(set(cam) - set(_CAMERA_KEYS))
    missing = sorted({"fx", "fy", "cx", "cy"} - set(cam))
    if extra:
        raise ConfigError(
            f"{where}: unknown key(s) in [camera]: {', '.join(extra)}; "
            f"allowed: {', '.join(_CAMERA_KEYS)}"
        )
    if missing:
        raise ConfigError(f"{where}: [camera] is missing {', '.join(missing)}")
    model = cam.get("model", "pinhole")
    if model not in CAMERA_MODELS:
        raise ConfigError(
            f"{where}: camera.model = {model!r} is not a lens model; "
            f"choose one of {', '.join(CAMERA_MODELS)}"
        )
    dist = cam.get("distortion", [])
    if not isinstance(dist, list):
        raise ConfigError(f"{where}: camera.distortion must be a list of numbers, got {dist!r}")
    return make_camera(
        [
            _number(cam[k], f"camera.{k}", where, positive=k in ("fx", "fy"))
            for k in "fx fy cx cy".split()
        ],
        [_number(d, f"camera.distortion[{i}]", where) for i, d in enumerate(dist)],
        model,
        where,
    )


def make_camera(
    fxfycxcy: list[float],
    distortion: list[float],
    model: str,
    where: str,
    image_wh: tuple[int, int] | None = None,
) -> Camera:
    """A validated :class:`Camera` (``where`` names the source in errors)."""
    lengths = DISTORTION_LENGTHS[model]
    if distortion and len(distortion) not in lengths:
        raise ConfigError(
            f"{where}: camera.distortion has {len(distortion)} values; the {model} model "
            f"takes {' or '.join(map(str, lengths))} (OpenCV's order"
            + (": k1, k2, p1, p2, k3, ...)" if model == "pinhole" else ": k1, k2, k3, k4)")
        )
    if model == "fisheye" and not distortion:
        distortion = [0.0, 0.0, 0.0, 0.0]
    fx, fy, cx, cy = fxfycxcy
    return Camera(fx, fy, cx, cy, tuple(float(d) for d in distortion), model, image_wh)


def config_from_dict(data: Mapping[str, Any], path: Path | None = None) -> Config:
    """Build and validate a :class:`Config` from parsed TOML (``path`` names it in errors
    and anchors a relative ``source``)."""
    where = _where(path)
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(_TOP_KEYS))}"
        )
    kwargs: dict[str, Any] = {"path": path, **_scalars(data, where)}
    if "source" in data:
        if not isinstance(data["source"], str) or not data["source"]:
            raise ConfigError(f"{where}: source must be a path string, got {data['source']!r}")
        kwargs["source"] = _relative_to(data["source"], path)
    labels, parts, colour = _labels_and_parts(data, where)
    kwargs["labels"], kwargs["parts"] = labels, parts
    kwargs.update(_camera_entries(data, path, where))
    instruments, inst_colour = _instruments(data.get("instrument", []), where)
    kwargs["instruments"] = tuple(instruments)
    kwargs["colour_masks"] = colour or inst_colour
    _check_overlaps(parts, instruments, where, labels)
    return Config(**kwargs)


def _relative_to(value: str, path: Path | None) -> Path:
    """A path from mistool.toml: ``~`` expanded, relative to the file's folder."""
    out = Path(value).expanduser()
    if not out.is_absolute() and path is not None:
        out = path.parent / out
    return out


def _scalars(data: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The validated top-level numbers: fps, min_area_px, max_pixels and the sizes."""
    out: dict[str, Any] = {}
    if "fps" in data:
        out["fps"] = _number(data["fps"], "fps", where, positive=True)
    if "min_area_px" in data:
        v = data["min_area_px"]
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ConfigError(f"{where}: min_area_px must be an integer >= 0, got {v!r}")
        out["min_area_px"] = v
    if "max_pixels" in data:
        v = data["max_pixels"]
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_PIXELS_LIMIT:
            raise ConfigError(
                f"{where}: max_pixels must be an integer in 1..{MAX_PIXELS_LIMIT}, got {v!r}"
            )
        out["max_pixels"] = v
    for key in ("shaft_diameter_mm", "clasper_length_mm"):
        if key in data:
            out[key] = _number(data[key], key, where, positive=True)
    return out


def _labels_and_parts(
    data: Mapping[str, Any], where: str
) -> tuple[str, dict[str, ValueRange], bool]:
    """The label preset, its part values with ``[parts]`` applied, and whether they are
    colours."""
    labels = data.get("labels", "endovis15")
    if not isinstance(labels, str) or labels not in PRESETS:
        raise ConfigError(
            f"{where}: labels = {labels!r} is not a preset; choose one of {', '.join(PRESETS)}"
        )
    parts = {p: (v, v) for p, v in PRESETS[labels].items()}
    colour = labels in COLOUR_PRESETS
    if "parts" in data:
        if not isinstance(data["parts"], dict):
            raise ConfigError(f"{where}: [parts] must be a table")
        extra = sorted(set(data["parts"]) - set(PARTS))
        if extra:
            raise ConfigError(
                f"{where}: unknown key(s) in [parts]: {', '.join(extra)}; "
                f"allowed: {', '.join(PARTS)}"
            )
        override, colour = _parts(data["parts"], where, "parts.")
        parts.update(override)
    return labels, parts, colour


def _camera_entries(data: Mapping[str, Any], path: Path | None, where: str) -> dict[str, Any]:
    """``camera`` (from ``[camera]`` or ``calibration = FILE``) and ``calibration``."""
    if "camera" in data and "calibration" in data:
        raise ConfigError(
            f"{where}: give either [camera] or calibration = FILE, not both (they could disagree)"
        )
    if "camera" in data:
        return {"camera": _camera(data["camera"], where)}
    if "calibration" in data:
        cal = data["calibration"]
        if not isinstance(cal, str) or not cal:
            raise ConfigError(f"{where}: calibration must be a path string, got {cal!r}")
        cal_path = _relative_to(cal, path)
        from mistool.calibration import read_calibration  # same layer; avoids a cycle

        return {"camera": read_calibration(cal_path), "calibration": cal_path}
    return {}


def _instruments(tables: Any, where: str) -> tuple[list[InstrumentSpec], bool]:
    """The ``[[instrument]]`` tables, validated; and whether any gives colours."""
    if not isinstance(tables, list):
        raise ConfigError(f"{where}: instrument must be an array of tables ([[instrument]])")
    instruments: list[InstrumentSpec] = []
    colour = False
    for i, table in enumerate(tables):
        spec, inst_colour = _instrument(table, i, {inst.name for inst in instruments}, where)
        instruments.append(spec)
        colour |= inst_colour
    return instruments, colour


def _instrument(table: Any, i: int, taken: set[str], where: str) -> tuple[InstrumentSpec, bool]:
    """One ``[[instrument]]`` table (the ``i``-th; ``taken``: the names before it),
    validated; and whether it gives colours."""
    tag = f"instrument[{i}]"
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: {tag} must be a table")
    extra = sorted(set(table) - _INSTRUMENT_KEYS)
    if extra:
        raise ConfigError(
            f"{where}: unknown key(s) in {tag}: {', '.join(extra)}; "
            f"allowed: {', '.join(sorted(_INSTRUMENT_KEYS))}"
        )
    name = table.get("name", str(i + 1))
    if not isinstance(name, (str, int)) or isinstance(name, bool) or str(name) == "":
        raise ConfigError(f"{where}: {tag}.name must be a non-empty string, got {name!r}")
    name = str(name)
    if name in taken:
        raise ConfigError(f"{where}: {tag}.name {name!r} is used twice")
    inst_parts, colour = _parts(table, where, f"{tag}.")
    if not inst_parts:
        raise ConfigError(
            f"{where}: {tag} ({name}) gives no part values; set at least one of {', '.join(PARTS)}"
        )
    dims = {
        k: _number(table[k], f"{tag}.{k}", where, positive=True)
        for k in ("shaft_diameter_mm", "clasper_length_mm")
        if k in table
    }
    return InstrumentSpec(name=name, parts=inst_parts, **dims), colour


def _overlap(named: list[tuple[str, ValueRange]], where: str) -> None:
    """Raise when two of the named inclusive ranges share a label value."""
    ordered = sorted(named, key=lambda item: item[1])
    for (name_a, (lo_a, hi_a)), (name_b, (lo_b, hi_b)) in zip(ordered, ordered[1:], strict=False):
        if lo_b <= hi_a:
            raise ConfigError(
                f"{where}: {name_a} = {_spec(lo_a, hi_a)} and {name_b} = {_spec(lo_b, hi_b)} "
                "overlap; a label value must mean one part of one instrument"
            )


def _spec(lo: int, hi: int) -> str:
    return str(lo) if lo == hi else f"[{lo}, {hi}]"


def _check_overlaps(
    parts: dict[str, ValueRange], instruments: list[InstrumentSpec], where: str, labels: str
) -> None:
    """Part ranges must not overlap: among the shared parts, and among every instrument's
    parts (within and across instruments)."""
    _overlap([(f"parts.{p} (preset {labels} or [parts])", r) for p, r in parts.items()], where)
    named = [
        (f"instrument {inst.name!r} {p}", r) for inst in instruments for p, r in inst.parts.items()
    ]
    _overlap(named, where)


def load_config(path: str | Path) -> Config:
    """Read ``mistool.toml`` from a file, or from a sequence folder (defaults when the
    folder has none). Raises :class:`ConfigError` with the file name on any problem.

    The read is bounded: only a regular file (a FIFO or device is refused without
    blocking), at most :data:`MAX_CONFIG_BYTES`, UTF-8 TOML; a dangling or looping
    ``mistool.toml`` symlink is an error, not "no file"."""
    p = Path(path)
    if p.is_dir():
        p = p / CONFIG_NAME
        if not os.path.lexists(p):
            return Config()
    data = _parse(p, _read_bounded(p))
    return config_from_dict(data, p)


def _read_bounded(p: Path) -> str:
    """The text of a regular file of at most :data:`MAX_CONFIG_BYTES` bytes."""
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ConfigError(f"{p}: symlink loop") from None
        if exc.errno == errno.ENOENT and os.path.islink(p):
            raise ConfigError(f"{p}: dangling symlink to {os.readlink(p)}") from None
        raise ConfigError(f"{p}: cannot read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{p}: not a regular file; mistool.toml must be a text file")
        if st.st_size > MAX_CONFIG_BYTES:
            raise ConfigError(
                f"{p}: {st.st_size} bytes; a mistool.toml is at most {MAX_CONFIG_BYTES} bytes"
            )
        with os.fdopen(fd, "rb", closefd=False) as f:
            raw = f.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{p}: larger than {MAX_CONFIG_BYTES} bytes")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{p}: not UTF-8 text (byte {raw[exc.start]:#04x} at offset {exc.start}); "
            "TOML files are UTF-8"
        ) from None


def _parse(p: Path, text: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: invalid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{p}: invalid TOML: arrays or tables nested too deeply") from None
