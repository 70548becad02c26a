"""Surgical skill metrics of a motion table (``mistool skill``, ``mistool.skill(table)``).

One row per recording x instrument (x time window), computed from one 3D point per
instrument in the camera frame (mm): the **tip** (the clasper's ``end_*_mm``) when the
instrument's clasper has a metric estimate in any frame, else the **joint** J (the
shaft's ``end_*_mm``). The point never switches within an instrument: a mixed track would
jump by the clasper length each time it switched.

What the metrics see (see docs/teaching.md for every definition and its source):

1. the table's own positions (``mistool track`` smooths the metric pose with its Kalman
   filter, ``--smoothing offline`` by default; a ground-truth table is exact);
2. outliers dropped: a sample that would imply a speed above :data:`MAX_SPEED_MM_S` from
   the last accepted sample less than :data:`MAX_GAP_S` before it (a jump to another
   tool's tip at a crossing, a merged blob); after a longer time a sample is accepted
   again as the start of a new run;
3. gaps of at most :data:`MAX_GAP_S` bridged by linear interpolation unless that implies
   a speed above :data:`MAX_SPEED_MM_S` (a longer or faster gap splits the track into
   separate runs: no path, speed or jerk across it);
4. a zero-phase Gaussian low-pass of standard deviation ``smoothing_s`` (default
   :data:`SMOOTHING_S`) along time within each run, so that frame-to-frame estimation
   noise does not add path length; ``smoothing_s=0`` turns it off.

Speeds are central differences of the smoothed positions at the table's frame rate.
Conventions: a metric that cannot be computed (too few samples, one instrument for
``bimanual_dexterity``) is NaN, never 0.
"""

from __future__ import annotations

import math
import sys
import types
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mistool.errors import ConfigError, TableError
from mistool.model import TrackTable, require_columns

#: Frame rate assumed when the table has no usable ``time_s`` and none is given (Hz).
DEFAULT_FPS = 25.0
#: Gaps in a track up to this long are bridged by linear interpolation (s).
MAX_GAP_S = 0.5
#: A sample implying a faster move than this from the last accepted sample (within
#: :data:`MAX_GAP_S`) is an outlier and dropped (mm/s); instrument tips move far slower.
MAX_SPEED_MM_S = 500.0
#: Standard deviation of the Gaussian low-pass applied to positions (s).
SMOOTHING_S = 0.1
#: Idle: speed at or below this, measured on the track resampled to 1 Hz (mm/s).
IDLE_SPEED_MM_S = 5.0
#: Rate the track is resampled to for the idle metric (Hz).
IDLE_RESAMPLE_HZ = 1.0
#: A movement: speed above this ...
MOVEMENT_SPEED_MM_S = 50.0
#: ... for at least this long (s).
MOVEMENT_MIN_S = 0.2
#: The working volume's box spans these quantiles of the positions per axis (a robust
#: bounding box: a few extreme or spurious frames do not set the volume).
VOLUME_QUANTILES = (0.025, 0.975)
#: Runs shorter than this have no LDLJ (the jerk of a short run is mostly its edges) (s).
LDLJ_MIN_RUN_S = 1.0

_END = ("end_x_mm", "end_y_mm", "end_z_mm")
_AXIS = ("axis_x", "axis_y", "axis_z")


@dataclass(frozen=True)
class MetricInfo:
    """What a metric column means."""

    name: str
    """Column name."""
    unit: str
    """Unit ('' when dimensionless)."""
    better: str
    """``"lower"`` or ``"higher"`` when experts tend to score that way, else ``""``."""
    label: str
    """A short human label."""


#: Every metric column, in output order.
METRICS: tuple[MetricInfo, ...] = (
    MetricInfo("duration_s", "s", "", "duration"),
    MetricInfo("visible_s", "s", "", "time with a 3D estimate"),
    MetricInfo("out_of_view_s", "s", "lower", "time out of view"),
    MetricInfo("path_length_mm", "mm", "lower", "path length"),
    MetricInfo("depth_perception_mm", "mm", "lower", "depth perception (path along shaft)"),
    MetricInfo("mean_speed_mm_s", "mm/s", "higher", "mean speed"),
    MetricInfo("ldlj", "", "higher", "smoothness (LDLJ)"),
    MetricInfo("idle_fraction", "", "lower", "idle fraction"),
    MetricInfo("working_volume_cm3", "cm³", "lower", "working volume (bounding box)"),
    MetricInfo("economy_of_volume", "", "higher", "economy of volume"),
    MetricInfo("movements", "", "lower", "movements"),
    MetricInfo("bimanual_dexterity", "", "higher", "bimanual dexterity (r of speeds)"),
)
METRIC_NAMES: tuple[str, ...] = tuple(m.name for m in METRICS)
#: Leading columns of the result, before the metrics.
KEY_COLUMNS: tuple[str, ...] = (
    "recording",
    "instrument",
    "point",
    "window_start_s",
    "window_end_s",
    "phase",
    "fps",
)
COLUMNS: tuple[str, ...] = KEY_COLUMNS + METRIC_NAMES


@dataclass(frozen=True)
class PointTrack:
    """One instrument's metric point on the dense frame grid of its recording."""

    instrument: str
    """Instrument name."""
    point: str
    """``"tip"`` (clasper end) or ``"joint"`` (shaft end J)."""
    xyz_mm: np.ndarray
    """(N, 3) float64, the point per frame 0..N-1 as in the table; NaN where unknown."""
    axis: np.ndarray
    """(N, 3) float64, the shaft's unit axis per frame; NaN where unknown."""
    seen: np.ndarray
    """(N,) bool, the instrument has a row (some part visible) in the frame."""


def table_fps(table: TrackTable, default: float = DEFAULT_FPS) -> float:
    """The frame rate implied by ``frame`` and ``time_s`` (median of frame / time)."""
    if "time_s" not in table or table.num_rows == 0:
        return default
    t = np.asarray(table["time_s"], dtype=np.float64)
    f = np.asarray(table["frame"], dtype=np.float64)
    ok = np.isfinite(t) & (t > 0)
    if not ok.any():
        return default
    fps = float(np.median(f[ok] / t[ok]))
    return fps if math.isfinite(fps) and fps > 0 else default


def point_tracks(table: TrackTable, num_frames: int | None = None) -> list[PointTrack]:
    """Each instrument's metric point (tip, else joint) on frames ``0 .. num_frames-1``.

    Args:
        table: a motion table with ``frame, instrument, part`` and ``end_*_mm``
            (``axis_*`` of the shaft for the depth metric).
        num_frames: frames in the recording (default: the table's last frame + 1).

    Returns:
        One :class:`PointTrack` per instrument, in name order.
    """
    require_columns(table, ("frame", "instrument", "part"), "skill")
    frames = np.asarray(table["frame"], dtype=np.int64)
    n = int(frames.max()) + 1 if table.num_rows else 0
    n = max(n, int(num_frames or 0))
    end = np.stack([np.asarray(table[c], dtype=np.float64) for c in _END], axis=1)
    axis = np.stack([np.asarray(table[c], dtype=np.float64) for c in _AXIS], axis=1)
    parts = np.asarray(table["part"]).astype(str)
    names = np.asarray(table["instrument"]).astype(str)
    finite = np.all(np.isfinite(end), axis=1)
    out = []
    for name in sorted(set(names.tolist())):
        mine = names == name
        clasper = mine & (parts == "clasper") & finite
        point, rows = ("tip", clasper) if clasper.any() else ("joint", mine & (parts == "shaft"))
        xyz = np.full((n, 3), np.nan)
        xyz[frames[rows]] = end[rows]
        shaft = mine & (parts == "shaft")
        ax = np.full((n, 3), np.nan)
        ax[frames[shaft]] = axis[shaft]
        seen = np.zeros(n, dtype=bool)
        seen[frames[mine]] = True
        out.append(PointTrack(name, point, xyz, ax, seen))
    return out


def runs(valid: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of consecutive True values."""
    v = np.concatenate([[False], np.asarray(valid, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(v.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def bridge_gaps(values: np.ndarray, max_gap: int, max_step: float = math.inf) -> np.ndarray:
    """Fill gaps of at most ``max_gap`` samples (NaN rows) between known rows by linear
    interpolation; longer gaps, gaps across a move faster than ``max_step`` per sample,
    and the ends stay NaN.

    Args:
        values: (N, D) float64 with NaN rows where unknown.
        max_gap: longest gap (samples) to fill.
        max_step: the largest plausible change per sample (Euclidean).

    Returns:
        A new (N, D) array.
    """
    out = np.array(values, dtype=np.float64, copy=True)
    idx = np.flatnonzero(np.all(np.isfinite(out), axis=1))
    if len(idx) < 2:
        return out
    gap = np.diff(idx)
    jump = np.linalg.norm(np.diff(out[idx], axis=0), axis=1)
    fill = (gap > 1) & (gap <= max_gap + 1) & (jump <= max_step * gap)
    for a, b in zip(idx[:-1][fill].tolist(), idx[1:][fill].tolist(), strict=True):
        w = (np.arange(a + 1, b) - a) / (b - a)
        out[a + 1 : b] = out[a] + w[:, None] * (out[b] - out[a])
    return out


def gaussian_smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    """Zero-phase Gaussian low-pass along axis 0 within each run of finite rows, with
    reflected ends (a constant or linear run is unchanged).

    Args:
        values: (N, D) float64, NaN rows between runs.
        sigma: standard deviation in samples (<= 0: unchanged).
    """
    out = np.array(values, dtype=np.float64, copy=True)
    if sigma <= 0:
        return out
    radius = int(math.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    k /= k.sum()
    for a, b in runs(np.all(np.isfinite(out), axis=1)):
        seg = out[a:b]
        if len(seg) < 3:
            continue
        r = min(radius, len(seg) - 1)
        # odd reflection about the end samples keeps a linear trend linear
        head = 2 * seg[0] - seg[r:0:-1]
        tail = 2 * seg[-1] - seg[-2 : -r - 2 : -1]
        padded = np.concatenate([head, seg, tail])
        kk = k[radius - r : radius + r + 1]
        kk = kk / kk.sum()
        for d in range(seg.shape[1]):
            out[a:b, d] = np.convolve(padded[:, d], kk, mode="valid")
    return out


def drop_outliers(xyz: np.ndarray, max_step_mm: float, max_gap: int) -> np.ndarray:
    """Drop (NaN) each sample farther than ``max_step_mm`` per frame elapsed from the last
    accepted sample, unless that one is more than ``max_gap`` frames back (then the sample
    starts a new run).

    Args:
        xyz: (N, 3) positions, NaN rows unknown.
        max_step_mm: the largest plausible move per frame (mm).
        max_gap: frames after which a sample is accepted whatever its distance.
    """
    out = np.array(xyz, dtype=np.float64, copy=True)
    known = np.flatnonzero(np.all(np.isfinite(out), axis=1))
    if len(known) < 2:
        return out
    gaps = np.diff(known)
    steps = np.linalg.norm(np.diff(out[known], axis=0), axis=1)
    if np.all((steps <= max_step_mm * gaps) | (gaps > max_gap)):
        return out  # nothing to drop (the usual case): no per-sample loop
    points = out[known].tolist()  # plain floats: the loop below runs per sample
    last = -1
    drop = []
    for k, i in enumerate(known.tolist()):
        if last >= 0 and i - known[last] <= max_gap:
            if math.dist(points[k], points[last]) > max_step_mm * (i - known[last]):
                drop.append(i)
                continue
        last = k
    out[drop] = np.nan
    return out


def prepare(track: PointTrack, fps: float, smoothing_s: float = SMOOTHING_S) -> np.ndarray:
    """The positions the metrics see: outliers dropped, gaps bridged, then low-passed.
    (N, 3), NaN between runs."""
    max_gap = int(round(MAX_GAP_S * fps))
    kept = drop_outliers(track.xyz_mm, MAX_SPEED_MM_S / fps, max_gap)
    bridged = bridge_gaps(kept, max_gap, MAX_SPEED_MM_S / fps)
    return gaussian_smooth(bridged, smoothing_s * fps)


def speeds(xyz: np.ndarray, fps: float) -> np.ndarray:
    """Speed (mm/s) per frame by central differences within runs; NaN elsewhere and on
    runs of one sample. (N,) float64."""
    out = np.full(len(xyz), np.nan)
    for a, b in runs(np.all(np.isfinite(xyz), axis=1)):
        if b - a >= 2:
            out[a:b] = np.linalg.norm(np.gradient(xyz[a:b], 1.0 / fps, axis=0), axis=1)
    return out


def _steps(xyz: np.ndarray) -> np.ndarray:
    """Frame-to-frame displacement (N-1, 3); NaN where either end is unknown."""
    return np.diff(xyz, axis=0) if len(xyz) > 1 else np.zeros((0, 3))


def path_length(xyz: np.ndarray) -> float:
    """Sum of the frame-to-frame distances within runs (mm); NaN with no step."""
    d = np.linalg.norm(_steps(xyz), axis=1)
    d = d[np.isfinite(d)]
    return float(d.sum()) if len(d) else math.nan


def depth_perception(xyz: np.ndarray, axis: np.ndarray) -> float:
    """Sum of |displacement . shaft axis| over frame steps (mm), PerkTutor's definition;
    the axis of a step is the mean of its two frames' axes (steps without one are
    skipped)."""
    step = _steps(xyz)
    a = axis[:-1] + axis[1:] if len(axis) > 1 else np.zeros((0, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        a = a / np.linalg.norm(a, axis=1, keepdims=True)
    d = np.abs(np.sum(step * a, axis=1))
    ok = np.all(np.isfinite(step), axis=1)
    if not ok.any():
        return math.nan
    return float(np.nansum(d[ok]))


def ldlj(speed: np.ndarray, fs: float) -> float:
    """Log dimensionless jerk of one speed profile (Balasubramanian et al. 2015).

    ``LDLJ = -ln( T^3 / v_peak^2 * integral (d^2 v / dt^2)^2 dt )`` with ``T`` the
    profile's duration (samples / fs), second differences for the derivative and a
    rectangle sum for the integral, as the authors' reference implementation. Higher
    (closer to zero) is smoother.

    Args:
        speed: (N,) speed samples (any unit), N >= 3.
        fs: sampling rate (Hz).
    """
    v = np.asarray(speed, dtype=np.float64)
    if len(v) < 3 or not np.all(np.isfinite(v)):
        return math.nan
    peak = float(np.max(np.abs(v)))
    dt = 1.0 / fs
    jerk = np.diff(v, 2) / dt**2
    dlj = (len(v) * dt) ** 3 / peak**2 * float(np.sum(jerk**2)) * dt if peak > 0 else 0.0
    return -math.log(dlj) if dlj > 0 else math.nan


def mean_ldlj(speed: np.ndarray, fps: float) -> float:
    """Duration-weighted mean LDLJ of the runs of ``speed`` at least
    :data:`LDLJ_MIN_RUN_S` long; NaN without one."""
    vals, weights = [], []
    for a, b in runs(np.isfinite(speed)):
        if (b - a) / fps >= LDLJ_MIN_RUN_S:
            v = ldlj(speed[a:b], fps)
            if math.isfinite(v):
                vals.append(v)
                weights.append(b - a)
    return float(np.average(vals, weights=weights)) if vals else math.nan


def idle_fraction(xyz: np.ndarray, fps: float) -> float:
    """Share of 1-s intervals (track resampled to :data:`IDLE_RESAMPLE_HZ`) in which the
    point moves at most :data:`IDLE_SPEED_MM_S`; NaN without a whole interval."""
    step = fps / IDLE_RESAMPLE_HZ
    idle = total = 0
    for a, b in runs(np.all(np.isfinite(xyz), axis=1)):
        t = np.arange(a, b - 1 + 1e-9, step)
        if len(t) < 2:
            continue
        grid = np.arange(a, b)
        p = np.stack([np.interp(t, grid, xyz[a:b, d]) for d in range(3)], axis=1)
        v = np.linalg.norm(np.diff(p, axis=0), axis=1) * IDLE_RESAMPLE_HZ
        idle += int(np.sum(v <= IDLE_SPEED_MM_S))
        total += len(v)
    return idle / total if total else math.nan


def working_volume_cm3(xyz: np.ndarray, quantiles: tuple[float, float] = VOLUME_QUANTILES) -> float:
    """Volume of the axis-aligned bounding box (camera frame) of the positions (cm³), as
    PerkTutor's Bounding Box Volume, but spanning the ``quantiles`` of each axis
    (``(0, 1)``: PerkTutor's min-max box); NaN with fewer than 2 positions."""
    p = xyz[np.all(np.isfinite(xyz), axis=1)]
    if len(p) < 2:
        return math.nan
    lo, hi = np.quantile(p, quantiles, axis=0)
    return float(np.prod(hi - lo)) / 1000.0


def movements(speed: np.ndarray, fps: float) -> int:
    """Number of runs with speed > :data:`MOVEMENT_SPEED_MM_S` lasting at least
    :data:`MOVEMENT_MIN_S`."""
    need = MOVEMENT_MIN_S * fps - 1e-9
    fast = np.isfinite(speed) & (np.nan_to_num(speed) > MOVEMENT_SPEED_MM_S)
    return sum(1 for a, b in runs(fast) if b - a >= need)


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson r over samples where both are finite; NaN with < 3 or no variance."""
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3:
        return math.nan
    x, y = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    den = math.sqrt(float(np.sum(x * x)) * float(np.sum(y * y)))
    return float(np.sum(x * y)) / den if den > 0 else math.nan


def _window_metrics(
    track: PointTrack,
    xyz: np.ndarray,
    speed: np.ndarray,
    fps: float,
    sl: slice,
) -> dict[str, float]:
    p, v = xyz[sl], speed[sl]
    n = len(p)
    length = path_length(p)
    moving = sum(b - a - 1 for a, b in runs(np.all(np.isfinite(p), axis=1)))
    volume = working_volume_cm3(p)
    return {
        "duration_s": n / fps,
        "visible_s": float(np.all(np.isfinite(track.xyz_mm[sl]), axis=1).sum()) / fps,
        "out_of_view_s": float((~track.seen[sl]).sum()) / fps,
        "path_length_mm": length,
        "depth_perception_mm": depth_perception(p, track.axis[sl]),
        "mean_speed_mm_s": length / (moving / fps) if moving > 0 else math.nan,
        "ldlj": mean_ldlj(v, fps),
        "idle_fraction": idle_fraction(p, fps),
        "working_volume_cm3": volume,
        "economy_of_volume": (volume * 1000.0) ** (1 / 3) / length
        if length > 0 and math.isfinite(volume)
        else math.nan,
        "movements": float(movements(v, fps)),
    }


def parse_window(text: str | float | None) -> float | None:
    """``"60s"``, ``"2min"``, ``"90"`` (seconds) -> seconds; None/'' -> None."""
    if text is None or text == "":
        return None
    if isinstance(text, (int, float)):
        value = float(text)
    else:
        s = text.strip().lower()
        scale = 60.0 if s.endswith(("min", "m")) else 1.0
        s = s.removesuffix("min").removesuffix("m").removesuffix("s")
        try:
            value = float(s) * scale
        except ValueError:
            raise ConfigError(
                f"--window {text!r}: expected a duration such as 60s, 2min or 90"
            ) from None
    if not value > 0 or not math.isfinite(value):
        raise ConfigError(f"--window {text!r}: must be a duration > 0")
    return value


def skill(
    table: TrackTable,
    *,
    recording: str = "",
    num_frames: int | None = None,
    fps: float | None = None,
    window_s: float | str | None = None,
    phases: Sequence[tuple[int, str]] | None = None,
    smoothing_s: float = SMOOTHING_S,
) -> dict[str, np.ndarray]:
    """Skill metrics of one recording, one row per instrument (and time window).

    Args:
        table: the recording's motion table (tracked, or a ground truth).
        recording: a name put in the ``recording`` column.
        num_frames: frames in the recording (default: the table's last frame + 1).
        fps: frame rate (default: from ``time_s``, else :data:`DEFAULT_FPS`).
        window_s: split the recording into windows of this many seconds (phases); a
            number or a text such as ``"60s"``. Default: one window.
        phases: split the recording at these ``(start frame, name)`` instead (e.g. the
            ``phase`` bookmarks): each phase runs to the next one's start; frames before
            the first phase form a window named ``""``.
        smoothing_s: the Gaussian low-pass's standard deviation (s; 0 = none).

    Returns:
        Columns :data:`COLUMNS` (``dict[str, ndarray]``, equal lengths; ``recording``,
        ``instrument`` and ``point`` are str, the rest float64). Zero rows when the table
        has no instrument.

    Raises:
        TableError: the table lacks ``frame``, ``instrument`` or ``part``.
        ConfigError: a bad ``fps``, ``window_s``, ``phases`` or ``smoothing_s``.
    """
    if fps is not None and not (fps > 0 and math.isfinite(fps)):
        raise ConfigError(f"skill: fps must be > 0, got {fps}")
    if not (smoothing_s >= 0 and math.isfinite(smoothing_s)):
        raise ConfigError(f"skill: smoothing must be >= 0 s, got {smoothing_s}")
    window = parse_window(window_s)
    rate = fps or table_fps(table)
    tracks = point_tracks(table, num_frames)
    n = len(tracks[0].seen) if tracks else 0
    xyz = [prepare(t, rate, smoothing_s) for t in tracks]
    speed = [speeds(p, rate) for p in xyz]
    rows: list[dict[str, Any]] = []
    for sl, name in windows(n, rate, window, phases):
        for k, track in enumerate(tracks):
            row: dict[str, Any] = {
                "recording": recording,
                "instrument": track.instrument,
                "point": track.point,
                "window_start_s": sl.start / rate,
                "window_end_s": sl.stop / rate,
                "phase": name,
                "fps": rate,
            }
            row.update(_window_metrics(track, xyz[k], speed[k], rate, sl))
            row["bimanual_dexterity"] = (
                pearson(speed[0][sl], speed[1][sl]) if len(tracks) == 2 else math.nan
            )
            rows.append(row)
    return _columns(rows)


def windows(
    n: int, fps: float, window_s: float | None, phases: Sequence[tuple[int, str]] | None
) -> list[tuple[slice, str]]:
    """The frame ranges metrics are computed over, with their phase names."""
    if window_s is not None and phases:
        raise ConfigError("skill: give time windows or phases, not both")
    if n == 0:
        return []
    if phases:
        starts = sorted((int(f), str(name)) for f, name in phases if 0 <= int(f) < n)
        if not starts:
            return [(slice(0, n), "")]
        if starts[0][0] > 0:
            starts.insert(0, (0, ""))
        ends = [f for f, _ in starts[1:]] + [n]
        return [(slice(f, e), name) for (f, name), e in zip(starts, ends, strict=True) if e > f]
    step = n if window_s is None else max(1, int(round(window_s * fps)))
    return [(slice(w0, min(n, w0 + step)), "") for w0 in range(0, n, step)]


def _columns(rows: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        if c in ("recording", "instrument", "point", "phase"):
            arr = np.empty(len(rows), dtype=object)
            arr[:] = [str(r[c]) for r in rows]
            out[c] = arr
        else:
            out[c] = np.array([float(r[c]) for r in rows], dtype=np.float64)
    return out


def concat(results: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Stack several :func:`skill` results row-wise."""
    if not results:
        return _columns([])
    return {c: np.concatenate([r[c] for r in results]) for c in COLUMNS}


def check_table(table: TrackTable, where: str) -> None:
    """Raise :class:`TableError` when ``table`` has no metric position at all."""
    require_columns(table, ("frame", "instrument", "part"), where)
    if table.num_rows and not all(c in table for c in _END):
        raise TableError(
            f"{where}: no end_x_mm/end_y_mm/end_z_mm columns: skill metrics need the "
            "metric 3D pose (track with a [camera] in mistool.toml)"
        )


class _CallableModule(types.ModuleType):
    """``mistool.skill`` is both this module and, called, :func:`skill`: importing the
    module sets the package attribute ``mistool.skill`` to the module, which would
    otherwise hide the function that ``mistool.skill(table)`` names."""

    def __call__(self, table: TrackTable, **kwargs: Any) -> dict[str, np.ndarray]:
        return skill(table, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
