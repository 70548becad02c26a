"""Metric pose round trips: ``mistool synth`` -> ``mistool.track`` -> ``evaluate``.

Fixed seeds and few frames (fast, deterministic). Thresholds are the issue's accuracy
targets where the measured values leave a margin (see scripts/eval_metric.py for the
full table); each test names the value it measured when written.
"""

from __future__ import annotations

import pytest

from mistool.api import track
from mistool.evaluation import evaluate
from mistool.synth import Corruptions, synthesize

MILD = dict(jitter_px=1.0, holes=3.0, speckle=10.0)


def _scores(
    tmp_path,
    corr: Corruptions,
    smoothing: str,
    frames: int = 40,
    seed: int = 5,
    instruments: int = 1,
) -> dict:
    res = synthesize(
        tmp_path / "seq", frames=frames, instruments=instruments, seed=seed, corruptions=corr
    )
    table = track(tmp_path / "seq", smoothing=smoothing, workers=1)
    assert not any(c.startswith("aux_") for c in table.columns)
    return evaluate({"metric": table}, res.truth).methods[0].parts


def test_clean_render_is_near_exact(tmp_path):
    s = _scores(tmp_path, Corruptions(), "none")
    shaft = s["shaft"]
    assert shaft["metric_coverage"] >= 0.95
    assert shaft["end_mm"]["median"] <= 0.2  # measured 0.03-0.05
    assert shaft["axis_deg"]["median"] <= 0.3  # measured ~0.05
    assert s["clasper"]["end_mm"]["median"] <= 3.0


def test_mild_corruption_meets_targets(tmp_path):
    s = _scores(tmp_path, Corruptions(**MILD), "offline")
    shaft, clasper = s["shaft"], s["clasper"]
    assert shaft["metric_coverage"] >= 0.95
    assert shaft["end_mm"]["median"] <= 1.0
    assert shaft["end_mm"]["p90"] <= 2.0
    assert shaft["axis_deg"]["median"] <= 1.5
    assert clasper["metric_coverage"] >= 0.9
    assert clasper["end_mm"]["median"] <= 2.5


@pytest.mark.parametrize(
    "corr",
    [
        Corruptions(occluders=3, **MILD),
        Corruptions(bias_px=1, **MILD),
    ],
    ids=["occluded", "dilated-1px"],
)
def test_bias_or_occlusion_joint_within_2mm(tmp_path, corr):
    # (coverage is not asserted: an occluder that cuts a tool in two can make the
    # identity tracker name the pieces differently, which the evaluation then counts)
    s = _scores(tmp_path, corr, "offline")
    assert s["shaft"]["end_mm"]["median"] <= 2.0


def test_quality_tracks_the_fit(tmp_path):
    """The re-render IoU is high on clean masks and lower under heavy corruption."""
    import numpy as np

    synthesize(tmp_path / "a", frames=12, instruments=1, seed=7)
    synthesize(
        tmp_path / "b",
        frames=12,
        instruments=1,
        seed=7,
        corruptions=Corruptions(jitter_px=3.0, bias_px=2, holes=10.0),
    )
    qa = track(tmp_path / "a", smoothing="none", workers=1)
    qb = track(tmp_path / "b", smoothing="none", workers=1)
    sa = np.nanmedian(qa["quality"][qa["part"] == "shaft"])
    sb = np.nanmedian(qb["quality"][qb["part"] == "shaft"])
    assert sa > 0.95
    assert sb < sa
