"""``mistool track DATASET/ -o OUT/``: one table per sequence (the same as tracking it
alone), the summary, a broken sequence that stops nothing, resume, root defaults."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool import dataset
from mistool.cli import main
from mistool.columnar import read_table
from mistool.export import read_csv
from mistool.synth import synthesize


def _summary(out: Path) -> list[dict[str, str]]:
    with (out / "summary.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _simple(folder: Path, n: int = 12) -> Path:
    """A sequence without its own mistool.toml: one moving bar (shaft 160, clasper 70)."""
    folder.mkdir(parents=True)
    for i in range(n):
        img = np.zeros((60, 90), np.uint8)
        img[25:35, 5 + i : 50 + i] = 160
        img[23:37, 50 + i : 60 + i] = 70
        cv2.imwrite(str(folder / f"{i}.png"), img)
    return folder


@pytest.fixture()
def data(tmp_path: Path) -> Path:
    root = tmp_path / "data"
    synthesize(root / "seq1", frames=24, instruments=2, seed=3)  # own toml, camera
    _simple(root / "seq2")  # uses the root's defaults
    bad = _simple(root / "seq10")  # natural order: after seq2
    (bad / "5.png").write_bytes(b"not a png")
    (root / "notes.txt").write_text("ignored")
    (root / "mistool.toml").write_text("fps = 10.0\n")
    return root


def test_dataset_tables_summary_and_a_broken_sequence(
    data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["track", str(data), "-o", str(out), "--workers", "2"]) == 1
    err = capsys.readouterr().err.splitlines()
    errors = [line for line in err if line.startswith("mistool: error:")]
    assert errors == [
        f"mistool: error: {data / 'seq10' / '5.png'}: cannot decode as an image "
        "(corrupt, truncated or not an image file)"
    ]
    assert sorted(p.name for p in out.iterdir()) == [
        ".mistool-dataset.json",
        "seq1_motion.csv",
        "seq2_motion.csv",
        "summary.csv",
    ]  # nothing for the broken sequence, no temporary file left
    rows = _summary(out)
    assert [r["sequence"] for r in rows] == ["seq1", "seq2", "seq10"]
    assert [r["status"] for r in rows] == ["ok", "ok", "error"]
    assert rows[0]["frames"] == "24" and rows[0]["instruments"] == "2"
    assert rows[1]["frames"] == "12" and rows[1]["instruments"] == "1"
    assert float(rows[0]["seconds"]) > 0 and rows[0]["error"] == ""
    assert "5.png: cannot decode" in rows[2]["error"]
    # each table is what tracking the sequence alone gives (seq1 has its own toml)
    alone = tmp_path / "alone.csv"
    assert main(["track", str(data / "seq1"), "-o", str(alone), "-q", "--workers", "1"]) == 0
    assert alone.read_bytes() == (out / "seq1_motion.csv").read_bytes()
    # seq2 has no toml: the root's fps applies
    np.testing.assert_allclose(read_csv(out / "seq2_motion.csv")["time_s"][::2], np.arange(12) / 10)


def test_resume_skips_up_to_date_outputs_and_redoes_changed_ones(
    data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    real = dataset._track_one
    calls: list[str] = []

    def interrupted_on_seq2(entry, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(entry.name)
        if entry.name == "seq2":
            raise KeyboardInterrupt  # Ctrl+C while seq2 is being tracked
        return real(entry, *args, **kwargs)

    monkeypatch.setattr(dataset, "_track_one", interrupted_on_seq2)
    with pytest.raises(KeyboardInterrupt):
        dataset.track_dataset(data, out)
    assert sorted(p.name for p in out.iterdir()) == [".mistool-dataset.json", "seq1_motion.csv"]
    first = (out / "seq1_motion.csv").stat().st_mtime_ns

    calls.clear()

    def counting(entry, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(entry.name)
        return real(entry, *args, **kwargs)

    monkeypatch.setattr(dataset, "_track_one", counting)
    outcomes = dataset.track_dataset(data, out)
    assert calls == ["seq2", "seq10"]  # seq1 was complete: skipped
    assert [o.status for o in outcomes] == ["up to date", "ok", "error"]
    assert outcomes[0].frames == 24 and outcomes[0].instruments == 2
    assert (out / "seq1_motion.csv").stat().st_mtime_ns == first

    calls.clear()
    assert [o.status for o in dataset.track_dataset(data, out)] == ["up to date"] * 2 + ["error"]
    assert calls == ["seq10"]  # a broken sequence is tried again

    # a changed input frame, a changed option: tracked again
    frame = data / "seq2" / "3.png"
    os.utime(frame, ns=(frame.stat().st_atime_ns, frame.stat().st_mtime_ns + 10**9))
    calls.clear()
    dataset.track_dataset(data, out)
    assert calls == ["seq2", "seq10"]
    calls.clear()
    dataset.track_dataset(data, out, dataset.Options(metric=False))
    assert calls == ["seq1", "seq2", "seq10"]


def test_root_defaults_are_overridden_key_by_key(tmp_path: Path) -> None:
    root = tmp_path / "d"
    own = _simple(root / "own")
    (own / "mistool.toml").write_text("min_area_px = 5\n")
    (root / "mistool.toml").write_text('fps = 10.0\nlabels = "endovis15"\nmin_area_px = 30\n')
    entry = dataset.Entry("own", own)
    cfg = dataset.sequence_config(entry, root)
    assert cfg.fps == 10.0 and cfg.min_area_px == 5
    (own / "mistool.toml").write_text("fps = [1\n")
    out = tmp_path / "out"
    outcomes = dataset.track_dataset(root, out)
    assert outcomes[0].status == "error" and "invalid TOML" in outcomes[0].error
    assert "\n" not in outcomes[0].error


def test_columnar_dataset_and_bad_output_folder(
    data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["track", str(data), "-o", str(out), "--format", "npz", "-q"]) == 1
    capsys.readouterr()
    table = read_table(out / "seq2_motion.npz")
    assert table.num_rows == 24 and table["instrument"].tolist()[0] == "1"
    file_out = tmp_path / "file.csv"
    file_out.write_text("x")
    assert main(["track", str(data), "-o", str(file_out)]) == 1
    err = capsys.readouterr().err.strip()
    assert (
        err == f"mistool: error: {file_out}: is a file; a dataset needs an output folder (-o OUT/)"
    )
