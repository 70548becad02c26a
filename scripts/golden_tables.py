"""Refactoring check: full motion tables of a few synth sequences, saved, then compared.

Renders 4 seeded ``mistool synth`` sequences (60 frames; 2-4 instruments; endovis15,
endovis17 and ternaus labels; jitter, holes, occluders, bias, speckle, hidden claspers) into
a folder (kept, so both runs see the same files), tracks each three ways (raw
``iter_track`` rows with the ``aux_*`` columns, ``track(smoothing="none")`` and
``track()``), and saves every column (``save``) or compares them with a saved file
(``check``: same columns, same shapes, same NaN pattern, worst absolute difference; fails
above ``--tol``). Run ``save`` before a refactor and ``check`` after it::

    python scripts/golden_tables.py save /tmp/golden.npz --seqs /tmp/golden_seqs
    python scripts/golden_tables.py check /tmp/golden.npz --seqs /tmp/golden_seqs
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mistool import api
from mistool.model import TrackTable
from mistool.synth import synthesize
from mistool.synth.corrupt import Corruptions

CASES = [
    {"seed": 1, "instruments": 2, "preset": "endovis15"},
    {"seed": 2, "instruments": 3, "preset": "endovis17"},
    {
        "seed": 3,
        "instruments": 4,
        "preset": "endovis15",
        "corruptions": Corruptions(jitter_px=1.0, holes=2.0, occluders=1, bias_px=0.5),
    },
    {
        "seed": 4,
        "instruments": 2,
        "preset": "ternaus",
        "corruptions": Corruptions(hide_clasper=0.3, speckle=0.5),
    },
]


def tables(root: Path) -> dict[str, np.ndarray]:
    """Every column of every table, keyed ``"<case>/<kind>/<column>"``."""
    out = {}
    for i, case in enumerate(CASES):
        folder = root / f"s{i}"
        if not folder.exists():
            synthesize(folder, frames=60, **case)
        raw = TrackTable.concat(list(api.iter_track(folder)))
        none = api.track(folder, smoothing="none", workers=1)
        offline = api.track(folder, workers=1)
        for kind, table in (("raw", raw), ("none", none), ("offline", offline)):
            for column in table:
                out[f"{i}/{kind}/{column}"] = np.asarray(table[column])
    return out


def compare(ref: dict[str, np.ndarray], got: dict[str, np.ndarray]) -> float:
    """Worst absolute difference of the float columns; AssertionError on any other
    difference (columns, shapes, NaN pattern, non-float values)."""
    assert set(ref) == set(got), sorted(set(ref) ^ set(got))
    worst = 0.0
    for key, a in ref.items():
        b = got[key]
        assert a.shape == b.shape, key
        if a.dtype.kind != "f":
            assert np.array_equal(a, b), key
            continue
        assert np.array_equal(np.isnan(a), np.isnan(b)), key
        ok = ~np.isnan(a)
        if ok.any():
            worst = max(worst, float(np.abs(a[ok] - b[ok]).max()))
    return worst


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=("save", "check"))
    parser.add_argument("file", type=Path, help="the .npz of saved columns")
    parser.add_argument("--seqs", type=Path, required=True, help="folder of the sequences")
    parser.add_argument("--tol", type=float, default=1e-9)
    args = parser.parse_args(argv)
    got = tables(args.seqs)
    if args.mode == "save":
        np.savez(args.file, **got)
        print(f"{len(got)} columns saved to {args.file}")
        return 0
    with np.load(args.file, allow_pickle=True) as saved:
        ref = {k: saved[k] for k in saved.files}
    worst = compare(ref, got)
    print(f"{len(ref)} columns compared; worst absolute difference {worst:.3g}")
    return 0 if worst <= args.tol else 1


if __name__ == "__main__":
    raise SystemExit(main())
