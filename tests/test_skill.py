"""Skill metrics: hand-computed values on constructed trajectories, a published reference
value for LDLJ, and tracked-vs-truth agreement on a noisy synthetic sequence."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import mistool
from mistool.annotations import Bookmark, save_annotations
from mistool.cli import main
from mistool.evaluation import match_instruments
from mistool.export import read_csv, write_csv
from mistool.model import TrackTable
from mistool.skill import (
    COLUMNS,
    bridge_gaps,
    drop_outliers,
    gaussian_smooth,
    ldlj,
    parse_window,
    skill,
    working_volume_cm3,
)

FPS = 25.0


def make_table(
    tracks: dict[str, np.ndarray],
    *,
    part: str = "clasper",
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0),
    fps: float = FPS,
) -> TrackTable:
    """One row per finite position: ``tracks[name]`` is (N, 3) mm, NaN rows = no row.
    A shaft row with ``axis`` is added for every frame with a position."""
    cols: dict[str, list] = {c: [] for c in ("frame", "time_s", "instrument", "part")}
    for c in ("end_x_mm", "end_y_mm", "end_z_mm", "axis_x", "axis_y", "axis_z"):
        cols[c] = []
    for name, xyz in tracks.items():
        for f, p in enumerate(xyz):
            if not np.all(np.isfinite(p)):
                continue
            rows = (
                [(part, p, axis)] if part == "shaft" else [("shaft", p - 20, axis), (part, p, axis)]
            )
            for prt, end, ax in rows:
                cols["frame"].append(f)
                cols["time_s"].append(f / fps)
                cols["instrument"].append(name)
                cols["part"].append(prt)
                for k, c in enumerate("xyz"):
                    cols[f"end_{c}_mm"].append(end[k])
                    cols[f"axis_{c}"].append(ax[k])
    return TrackTable(cols)


def line(n: int, v_mm_s: float, direction=(1.0, 0.0, 0.0), fps: float = FPS) -> np.ndarray:
    t = np.arange(n) / fps
    return np.outer(t * v_mm_s, direction) + np.array([0.0, 0.0, 80.0])


def test_constant_speed_line_hand_computed() -> None:
    # 100 frames at 25 fps, 10 mm/s along x: 99 steps of 0.4 mm
    r = skill(make_table({"a": line(100, 10.0)}))
    assert list(r) == list(COLUMNS)
    assert r["point"][0] == "tip"
    assert r["duration_s"][0] == pytest.approx(4.0)
    assert r["visible_s"][0] == pytest.approx(4.0)
    assert r["out_of_view_s"][0] == 0.0
    assert r["path_length_mm"][0] == pytest.approx(39.6, abs=1e-9)  # smoothing keeps a line
    assert r["mean_speed_mm_s"][0] == pytest.approx(10.0)
    assert r["depth_perception_mm"][0] == pytest.approx(39.6)  # moving along the shaft axis
    assert r["idle_fraction"][0] == 0.0  # 10 mm/s > 5 mm/s in each of its 3 whole seconds
    assert r["working_volume_cm3"][0] == 0.0  # a line has no volume
    assert r["movements"][0] == 0.0  # never above 50 mm/s
    assert math.isnan(r["bimanual_dexterity"][0])  # one instrument


def test_depth_perception_is_the_path_along_the_shaft_only() -> None:
    across = skill(make_table({"a": line(50, 10.0)}, axis=(0.0, 1.0, 0.0)))
    assert across["depth_perception_mm"][0] == pytest.approx(0.0, abs=1e-9)
    diagonal = skill(make_table({"a": line(50, 10.0, (0.6, 0.8, 0.0))}, axis=(0.0, 1.0, 0.0)))
    assert diagonal["depth_perception_mm"][0] == pytest.approx(0.8 * 10.0 * 49 / FPS)


def test_idle_fraction_counts_slow_seconds() -> None:
    # 2 s still, then 3 s at 20 mm/s: 1-Hz samples at 0..4 s, intervals 0-1 and 1-2 idle
    xyz = np.concatenate([line(50, 0.0), line(76, 20.0)[1:]])
    r = skill(make_table({"a": xyz}), smoothing_s=0.0)
    assert len(xyz) == 125
    assert r["idle_fraction"][0] == pytest.approx(2 / 4)


def test_movements_need_speed_above_50_for_0_2_s() -> None:
    # rest, 10 frames at 60 mm/s (0.4 s), rest, then 3 frames at 60 mm/s (0.12 s), rest
    steps = np.zeros(100)
    steps[10:20] = 60.0 / FPS
    steps[50:53] = 60.0 / FPS
    x = np.concatenate([[0.0], np.cumsum(steps)])
    xyz = np.stack([x, np.zeros_like(x), np.full_like(x, 80.0)], axis=1)
    r = skill(make_table({"a": xyz}), smoothing_s=0.0)
    assert r["movements"][0] == 1.0
    assert r["path_length_mm"][0] == pytest.approx(13 * 60.0 / FPS)


def test_gaps_short_are_bridged_long_are_out_of_view() -> None:
    xyz = line(200, 10.0)
    short = xyz.copy()
    short[40:45] = np.nan  # 0.2 s: bridged, the path is unchanged
    r = skill(make_table({"a": short}))
    assert r["path_length_mm"][0] == pytest.approx(10.0 * 199 / FPS)
    assert r["visible_s"][0] == pytest.approx(195 / FPS)
    assert r["out_of_view_s"][0] == pytest.approx(5 / FPS)
    long = xyz.copy()
    long[100:150] = np.nan  # 2 s: two runs, no path across the gap
    r = skill(make_table({"a": long}))
    assert r["path_length_mm"][0] == pytest.approx(10.0 * (99 + 49) / FPS)
    assert r["out_of_view_s"][0] == pytest.approx(2.0)


def test_outliers_are_dropped_and_a_lasting_jump_starts_a_new_run() -> None:
    xyz = line(100, 10.0)
    spiky = xyz.copy()
    spiky[30] += [0.0, 40.0, 0.0]  # one frame 40 mm off: 1000 mm/s, not a tip's motion
    spiky[61:63] += [0.0, 80.0, 0.0]  # two frames off
    r = skill(make_table({"a": spiky}), smoothing_s=0.0)
    assert r["path_length_mm"][0] == pytest.approx(10.0 * 99 / FPS)
    assert r["visible_s"][0] == pytest.approx(4.0)  # the samples were there
    assert r["movements"][0] == 0.0
    moved = xyz.copy()
    moved[50:] += [0.0, 300.0, 0.0]  # a lasting relocation: dropped for 0.5 s, then kept
    kept = drop_outliers(moved, 500.0 / FPS, 12)
    assert np.isnan(kept[50:62]).all() and np.isfinite(kept[62:]).all()
    r = skill(make_table({"a": moved}), smoothing_s=0.0)
    assert r["path_length_mm"][0] == pytest.approx(10.0 * (49 + 37) / FPS)  # no jump


def test_joint_is_used_when_the_clasper_is_not_tracked() -> None:
    r = skill(make_table({"a": line(30, 10.0)}, part="shaft"))
    assert r["point"][0] == "joint"
    assert r["path_length_mm"][0] == pytest.approx(10.0 * 29 / FPS)


def test_working_volume_is_a_robust_bounding_box() -> None:
    g = np.stack(np.meshgrid(*(np.linspace(0, s, 11) for s in (10, 20, 30))), -1).reshape(-1, 3)
    assert working_volume_cm3(g, (0.0, 1.0)) == pytest.approx(10 * 20 * 30 / 1000)
    spurious = np.concatenate([g, [[500.0, 500.0, 500.0]]])
    assert working_volume_cm3(spurious, (0.0, 1.0)) > 100  # PerkTutor's min-max box
    assert working_volume_cm3(spurious) == pytest.approx(working_volume_cm3(g), rel=0.02)
    # uniform positions: the central 95% of each side
    u = np.random.default_rng(0).uniform(0, 1, (20000, 3)) * [10, 20, 30]
    assert working_volume_cm3(u) == pytest.approx(0.95**3 * 6.0, rel=0.01)


def test_ldlj_matches_the_reference_implementation() -> None:
    # Balasubramanian et al.'s reference code (github.com/siva82kb/smoothness) documents
    # log_dimensionless_jerk(exp(-5 t^2), fs=100) over t in [-1, 1) as -5.81636
    t = np.arange(-1, 1, 0.01)
    assert ldlj(np.exp(-5 * t**2), 100.0) == pytest.approx(-5.81636, abs=1e-5)
    # dimensionless: the same shape at another amplitude or duration scores the same
    assert ldlj(7.0 * np.exp(-5 * t**2), 100.0) == pytest.approx(-5.81636, abs=1e-5)
    t2 = np.arange(-1, 1, 0.005)
    assert ldlj(np.exp(-5 * t2**2), 100.0) == pytest.approx(-5.81636, abs=2e-3)
    # a jerkier profile scores lower
    assert ldlj(np.exp(-5 * t**2) * (1 + 0.2 * np.sin(40 * t)), 100.0) < -5.9


def test_bimanual_dexterity_is_the_pearson_r_of_speeds() -> None:
    t = np.arange(200) / FPS
    x = 20 * (t - np.sin(2 * np.pi * 0.5 * t) / (2 * np.pi * 0.5))  # speed 20(1 - cos)
    a = np.stack([x, 0 * x, 80 + 0 * x], 1)
    b = np.stack([0 * x + 5, 2 * x, 80 + 0 * x], 1)  # twice the speed, same profile
    r = skill(make_table({"a": a, "b": b}), smoothing_s=0.0)
    assert r["bimanual_dexterity"] == pytest.approx([1.0, 1.0], abs=1e-9)
    c = np.stack([0 * x, 0.0 + 40 * t - x, 80 + 0 * x], 1)  # speed 20(1 + cos): opposite
    r = skill(make_table({"a": a, "c": c}), smoothing_s=0.0)
    assert r["bimanual_dexterity"][0] < -0.99


def test_windows_split_the_recording() -> None:
    r = skill(make_table({"a": line(100, 10.0)}), window_s="2s")
    assert list(r["window_start_s"]) == [0.0, 2.0]
    assert list(r["window_end_s"]) == [2.0, 4.0]
    assert r["path_length_mm"] == pytest.approx([10.0 * 49 / FPS] * 2)
    assert parse_window("2min") == 120.0 and parse_window("90") == 90.0


def test_phases_split_at_their_start_frames(tmp_path: Path) -> None:
    r = skill(make_table({"a": line(100, 10.0)}), phases=[(75, "closing"), (25, "suturing")])
    assert r["phase"].tolist() == ["", "suturing", "closing"]
    assert list(r["window_start_s"]) == [0.0, 1.0, 3.0]
    assert list(r["window_end_s"]) == [1.0, 3.0, 4.0]
    assert r["path_length_mm"] == pytest.approx([10.0 * 24 / FPS, 10.0 * 49 / FPS, 10.0 * 24 / FPS])
    with pytest.raises(mistool.MistoolError, match="not both"):
        skill(make_table({"a": line(10, 1.0)}), phases=[(0, "x")], window_s=1.0)
    src, marks = tmp_path / "rec.csv", tmp_path / "rec.json"
    write_csv(make_table({"a": line(100, 10.0)}), src)
    save_annotations(marks, [Bookmark(50, "second half", "phase"), Bookmark(10, "x", "event")])
    out = tmp_path / "s.csv"
    assert (
        main(["skill", str(src), "-o", str(out), "-q", "--phases", "--annotations", str(marks)])
        == 0
    )
    rows = out.read_text().splitlines()[1:]
    assert [r.split(",")[5] for r in rows] == ["", "second half"]
    assert main(["skill", str(src), "-o", str(out), "-q", "--phases"]) == 1


@pytest.mark.parametrize("bad", ["abc", "0s", "-5", "nan"])
def test_bad_window_is_a_config_error(bad: str) -> None:
    with pytest.raises(mistool.MistoolError, match="--window"):
        parse_window(bad)


def test_smoothing_keeps_lines_and_bridging_only_fills_inside() -> None:
    v = np.stack([np.arange(10.0)] * 3, 1)
    assert gaussian_smooth(v, 2.0) == pytest.approx(v)
    v[3:5] = np.nan
    b = bridge_gaps(v, 2)
    assert b == pytest.approx(np.stack([np.arange(10.0)] * 3, 1))
    assert np.isnan(bridge_gaps(v, 1)[3:5]).all()


def test_mistool_skill_is_callable_and_empty_safe() -> None:
    r = mistool.skill(make_table({"a": line(10, 1.0)}))
    assert r["instrument"].tolist() == ["a"]
    empty = mistool.skill(TrackTable())
    assert all(len(v) == 0 for v in empty.values()) and list(empty) == list(COLUMNS)


def test_cli_writes_csv_and_reports_bad_input(tmp_path: Path, capsys) -> None:
    src = tmp_path / "rec.csv"
    write_csv(make_table({"a": line(100, 10.0), "b": line(100, 5.0)}), src)
    out = tmp_path / "skill.csv"
    assert main(["skill", str(src), str(src), "-o", str(out), "--window", "2s", "-q"]) == 0
    text = out.read_text().splitlines()
    assert text[0] == ",".join(COLUMNS)
    assert len(text) == 1 + 2 * 2 * 2  # 2 recordings x 2 windows x 2 instruments
    assert text[1].startswith("rec,a,tip,0,2,,25,2,2,0,19.6,")
    assert any(line.startswith("rec#2,") for line in text)
    capsys.readouterr()
    assert main(["skill", str(tmp_path / "missing.csv"), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mistool: error: ") and err.count("\n") == 1
    before = out.read_text()
    nometric = tmp_path / "nometric.csv"
    nometric.write_text("frame,instrument,part\n0,a,shaft\n")
    assert main(["skill", str(nometric), "-o", str(out)]) == 1
    assert "metric 3D pose" in capsys.readouterr().err
    assert out.read_text() == before  # nothing partial written


def _by_truth_name(pred: TrackTable, truth: TrackTable, r: dict) -> dict[str, int]:
    mapping = match_instruments(pred, truth)
    return {mapping[str(name)]: i for i, name in enumerate(r["instrument"])}


def test_tracked_metrics_agree_with_truth_on_noisy_synth(tmp_path: Path) -> None:
    # 20 s of two tools at 10 fps with 1 px boundary jitter and specular holes; distinct
    # labels so that identity is given (this tests the metrics' robustness to mask noise)
    seq = tmp_path / "s"
    args = ["synth", str(seq), "--frames", "200", "--fps", "10", "--size", "360x288"]
    args += ["--focal", "300", "--instruments", "2", "--jitter", "1", "--holes", "1"]
    assert main([*args, "--seed", "3", "--distinct-labels", "-q"]) == 0
    pred_csv = tmp_path / "p.csv"
    assert main(["track", str(seq), "-o", str(pred_csv), "-q", "--workers", "2"]) == 0
    truth, pred = read_csv(seq / "truth.csv"), read_csv(pred_csv)
    rt, rp = skill(truth, num_frames=200), skill(pred, num_frames=200)
    assert len(rt["instrument"]) == len(rp["instrument"]) == 2
    index = _by_truth_name(pred, truth, rp)
    for i, name in enumerate(rt["instrument"]):
        j = index[str(name)]
        assert rp["path_length_mm"][j] == pytest.approx(rt["path_length_mm"][i], rel=0.10)
        assert rp["working_volume_cm3"][j] == pytest.approx(rt["working_volume_cm3"][i], rel=0.20)
        assert abs(rp["idle_fraction"][j] - rt["idle_fraction"][i]) <= 0.10
        assert rp["out_of_view_s"][j] == pytest.approx(rt["out_of_view_s"][i], abs=0.5)


def test_cli_tracks_a_sequence_source(tmp_path: Path) -> None:
    from mistool.synth import synthesize
    from mistool.synth.writer import SceneOptions

    seq = tmp_path / "seq"
    scene = SceneOptions(width=360, height=288, focal_px=300.0)
    synthesize(seq, frames=30, instruments=1, seed=1, fps=10.0, scene=scene)
    out = tmp_path / "skill.csv"
    assert main(["skill", str(seq), "-o", str(out), "-q"]) == 0
    lines = out.read_text().splitlines()
    assert len(lines) == 2 and lines[1].startswith("seq,")
    row = dict(zip(lines[0].split(","), lines[1].split(","), strict=True))
    assert float(row["duration_s"]) == pytest.approx(3.0)  # 30 frames at the toml's 10 fps
    assert float(row["path_length_mm"]) > 0
