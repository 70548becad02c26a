"""Dask: the same work on a real ``distributed.LocalCluster`` of 2 worker processes gives
the same tables as a local run: a long sequence split into chunks of frames across the
workers (identity stitched in the client), and a whole dataset through the CLI."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import distributed
import numpy as np
import pytest

from mistool import parallel
from mistool.api import track
from mistool.cli import main
from mistool.errors import MaskFormatError
from mistool.model import TrackTable
from mistool.synth import synthesize


def assert_same(a: TrackTable, b: TrackTable) -> None:
    assert a.columns == b.columns and a.num_rows == b.num_rows
    for c in a.columns:
        if a[c].dtype == object:
            assert a[c].tolist() == b[c].tolist(), c
        else:
            np.testing.assert_array_equal(a[c], b[c], err_msg=c)


@pytest.fixture(scope="module")
def cluster() -> Iterator[object]:
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as c:
        yield c


def test_a_sequence_in_chunks_across_dask_workers_equals_local(
    cluster: object, tmp_path: Path
) -> None:
    seq = tmp_path / "seq"
    synthesize(seq, frames=60, instruments=2, seed=3)  # crossing: the split path is taken
    with distributed.Client(cluster) as client:
        pool = parallel.DaskPool(client=client, batch_frames=8)  # 8 chunks over 2 workers
        assert pool.workers == 2
        on_dask = track(seq, pool=pool)
        assert len(client.run(lambda: 1)) == 2
    assert_same(on_dask, track(seq, workers=1))


def test_dataset_on_dask_equals_local_and_a_bad_frame_is_one_line(
    cluster: object, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = tmp_path / "data"
    synthesize(root / "a", frames=30, instruments=1, seed=0)
    synthesize(root / "b", frames=30, instruments=2, seed=3)
    local, remote = tmp_path / "local", tmp_path / "remote"
    assert main(["track", str(root), "-o", str(local), "-q", "--workers", "1"]) == 0
    address = cluster.scheduler_address  # type: ignore[attr-defined]
    assert main(["track", str(root), "-o", str(remote), "-q", "--dask", address]) == 0
    for name in ("a_motion.csv", "b_motion.csv"):
        assert (local / name).read_bytes() == (remote / name).read_bytes()
    (root / "b" / "000004.png").write_bytes(b"broken")
    with distributed.Client(address) as client:
        with pytest.raises(MaskFormatError, match=r"000004\.png: cannot decode"):
            track(root / "b", pool=parallel.DaskPool(client=client))
    capsys.readouterr()
    assert main(["track", str(root / "b"), "-o", str(tmp_path / "b.csv"), "--dask", address]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("mistool: error: ") and "000004.png: cannot decode" in err[-1]
    assert not (tmp_path / "b.csv").exists()


def test_unreachable_scheduler_is_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(parallel, "DASK_CONNECT_TIMEOUT_S", 1.0)
    seq = tmp_path / "s"
    synthesize(seq, frames=3, instruments=1, seed=0)
    assert (
        main(["track", str(seq), "--dask", "tcp://127.0.0.1:9", "-o", str(tmp_path / "o.csv")]) == 1
    )
    err = capsys.readouterr().err.strip()
    assert err.startswith(
        "mistool: error: --dask tcp://127.0.0.1:9: cannot reach the Dask scheduler"
    )
    assert "\n" not in err
