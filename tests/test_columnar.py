"""Columnar tables (.npz, .parquet): exact round trips, the same columns as the CSV,
empty tables, bad files as one-line errors, and ``mistool track -o motion.npz``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mistool.api import track
from mistool.cli import main
from mistool.columnar import read_table, write_table
from mistool.errors import ConfigError, InputPathError, TableError
from mistool.export import read_csv, table_to_csv_text
from mistool.model import TrackTable, empty_table
from mistool.synth import synthesize


@pytest.fixture(scope="module")
def table(tmp_path_factory: pytest.TempPathFactory) -> TrackTable:
    seq = tmp_path_factory.mktemp("col") / "seq"
    synthesize(seq, frames=20, instruments=2, seed=3)
    return track(seq, workers=1)


def _exact(a: TrackTable, b: TrackTable) -> None:
    assert a.columns == b.columns and a.num_rows == b.num_rows
    for c in a.columns:
        if a[c].dtype == object or b[c].dtype == object:
            assert a[c].dtype == b[c].dtype == object, c
            assert a[c].tolist() == b[c].tolist(), c
        else:
            assert a[c].dtype == b[c].dtype, c
            np.testing.assert_array_equal(a[c], b[c], err_msg=c)


@pytest.mark.parametrize("suffix", [".npz", ".parquet"])
def test_round_trip_is_exact_with_the_csv_columns(
    table: TrackTable, tmp_path: Path, suffix: str
) -> None:
    path = write_table(table, tmp_path / f"m{suffix}")
    back = read_table(path)
    _exact(back, table.full())
    assert np.isnan(back["dx_px"]).any()  # NaN stays NaN (an unknown estimate)
    csv_path = write_table(table, tmp_path / "m.csv")
    assert table_to_csv_text(back) == csv_path.read_text()
    _exact(read_table(csv_path), read_csv(csv_path))


@pytest.mark.parametrize("suffix", [".npz", ".parquet"])
def test_empty_table_round_trip(tmp_path: Path, suffix: str) -> None:
    back = read_table(write_table(empty_table(), tmp_path / f"e{suffix}"))
    assert back.num_rows == 0 and back.columns == empty_table().columns


def test_bad_files_and_suffixes(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"m\.xlsx: unknown table format '\.xlsx'"):
        write_table(empty_table(), tmp_path / "m.xlsx")
    with pytest.raises(InputPathError, match="no such file"):
        read_table(tmp_path / "none.npz")
    for name in ("bad.npz", "bad.parquet"):
        (tmp_path / name).write_bytes(b"this is not a table")
        with pytest.raises(TableError, match=name.replace(".", r"\.") + ": cannot read") as exc:
            read_table(tmp_path / name)
        assert "\n" not in str(exc.value)
    np.savez(tmp_path / "other.npz", x=np.arange(3))
    with pytest.raises(TableError, match="missing column"):
        read_table(tmp_path / "other.npz")


@pytest.mark.parametrize("suffix", [".npz", ".parquet"])
def test_cli_writes_the_format_of_the_suffix(
    table: TrackTable, tmp_path: Path, suffix: str
) -> None:
    seq = tmp_path / "seq"
    synthesize(seq, frames=20, instruments=2, seed=3)
    out = tmp_path / f"motion{suffix}"
    assert main(["track", str(seq), "-o", str(out), "-q", "--workers", "1"]) == 0
    _exact(read_table(out), table.full())
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["seq", out.name])


def test_eval_reads_columnar_predictions(
    table: TrackTable, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = tmp_path / "truth.csv"
    write_table(table, truth)
    reports = []
    for suffix in (".csv", ".npz", ".parquet"):
        pred = write_table(table, tmp_path / f"pred{suffix}")
        capsys.readouterr()
        assert main(["eval", str(pred), str(truth)]) == 0
        reports.append(capsys.readouterr().out)
    assert reports[0] and reports[0] == reports[1] == reports[2]
