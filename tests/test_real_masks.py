"""Real-looking synthetic masks (``Corruptions.real``, ``mistool synth --real``): they
fragment instruments like a network does, and tracking still measures each as one."""

from __future__ import annotations

import collections

import cv2
import numpy as np
import pytest

from mistool.api import track
from mistool.cli import main
from mistool.config import load_config
from mistool.evaluation import evaluate
from mistool.synth import Corruptions, synthesize
from mistool.synth.corrupt import Corruptor
from mistool.tracking import observe_frame


def _pieces(labels: np.ndarray, value: int) -> int:
    n, _, stats, _ = cv2.connectedComponentsWithStats((labels == value).astype(np.uint8))
    return int(np.count_nonzero(stats[1:, cv2.CC_STAT_AREA] >= 20))


@pytest.fixture(scope="module")
def fragmented(tmp_path_factory):
    out = tmp_path_factory.mktemp("real") / "frag"
    clean = synthesize(out.with_name("clean"), frames=24, instruments=1, seed=4, preset="endovis17")
    frag = synthesize(
        out,
        frames=24,
        instruments=1,
        seed=4,
        preset="endovis17",
        corruptions=Corruptions(fragments=3.0),
    )
    return clean, frag


def test_fragments_cut_instruments_apart(fragmented):
    """With fragments on, the one instrument's shaft comes in several pieces in many
    frames (one piece in the clean render)."""
    clean, frag = fragmented
    n_clean = [_pieces(cv2.imread(str(f), 0), 10) for f in sorted(clean.path.glob("*.png"))]
    n_frag = [_pieces(cv2.imread(str(f), 0), 10) for f in sorted(frag.path.glob("*.png"))]
    assert max(n_clean) <= 1
    assert sum(n > 1 for n in n_frag) >= 5


def test_fragmented_instrument_is_observed_as_one(fragmented):
    """Every frame of the fragmented single instrument is one instance (shaft stubs cut
    apart, as wide as long, are joined end to end: tracking.instances._end_to_end; this
    seed's frame 6 came out as three instances before), and its 3D meets the mild-noise
    targets against exact truth."""
    _, frag = fragmented
    cfg = load_config(frag.path)
    counts = [
        len(observe_frame(cv2.imread(str(f), 0), cfg)) for f in sorted(frag.path.glob("*.png"))
    ]
    assert max(counts) == 1 and sum(counts) >= 15
    # per-frame poses (smoothing="none"): the subject is the fragments, and the offline
    # smoother lags this tool's fast entry (frames 6-8: 0.0-0.4 mm per frame, 4-7 mm
    # smoothed)
    table = track(frag.path, smoothing="none")
    names = collections.Counter(table["instrument"].tolist())
    assert max(names.values()) >= 0.9 * table.num_rows, names
    parts = evaluate({"m": table}, frag.truth).methods[0].parts
    # measured 78% (14 of 18 frames): the rest are honest reasons (a cut at the joint
    # reads as an occluder's cut: "occluded"; the tracker's blob split in one frame), and
    # no row is taken for two tools touching ("merged")
    assert parts["shaft"]["metric_coverage"] >= 0.75
    shaft = table["part"] == "shaft"
    assert "merged" not in set(table["pose_status"][shaft].tolist())
    assert parts["shaft"]["end_mm"]["median"] <= 1.0
    # known weak spot: a cut across the shaft a few px before the junction shifts J along
    # the axis by ~4 mm (frames 12 and 17 of this sequence); no other frame beyond 3 mm
    j = table[shaft]
    truth = frag.truth[frag.truth["part"] == "shaft"]
    by_frame = {int(f): k for k, f in enumerate(truth["frame"])}
    errors = [
        float(
            np.linalg.norm(
                [
                    j[c][i] - truth[c][by_frame[int(j["frame"][i])]]
                    for c in ("end_x_mm", "end_y_mm", "end_z_mm")
                ]
            )
        )
        for i in range(j.num_rows)
        if j["pose_status"][i] == "ok" and int(j["frame"][i]) in by_frame
    ]
    assert len(errors) >= 14 and sum(e > 3.0 for e in errors) <= 2, errors


def test_real_corruptions_are_seeded_and_each_visible():
    """Each real-looking corruption changes the masks; the same seed gives the same masks."""
    shape = (120, 160)
    labels = np.zeros(shape, np.uint8)
    cv2.line(labels, (0, 60), (110, 60), 10, 16)
    cv2.circle(labels, (118, 60), 9, 20, -1)
    cv2.line(labels, (0, 0), (40, 30), 10, 12)  # into a dark corner
    instance = (labels > 0).astype(np.uint8)
    part = np.where(labels == 10, 1, np.where(labels == 20, 2, 0)).astype(np.uint8)
    for field in ("fragments", "rough_px", "missed", "spurious", "vignette"):
        corr = Corruptions(**{field: 3.0 if field != "vignette" else 0.05})
        a = Corruptor(corr, shape, 1, 1, 25.0, seed=1).apply(labels, instance, part, 0, [10, 20])
        b = Corruptor(corr, shape, 1, 1, 25.0, seed=1).apply(labels, instance, part, 0, [10, 20])
        assert np.array_equal(a, b), field
        assert not np.array_equal(a, labels), field
    with pytest.raises(ValueError, match="fragments must be"):
        Corruptions(fragments=-1.0)


def test_cli_real_option(tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["synth", str(out), "--frames", "3", "--real", "--preset", "endovis17", "-q"]) == 0
    import json

    opts = json.loads((out / "synth.json").read_text())["corruptions"]
    assert opts["fragments"] == Corruptions.real().fragments and opts["vignette"] > 0
    counts = collections.Counter(track(out)["part"].tolist())
    assert counts["shaft"] >= 3
