"""The shared assignment solver's shortcut for one row and one column: the same pairs as
SciPy's solver, without importing it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from mistool import assignment


@pytest.mark.parametrize(
    "value", [0.0, 0.5, 2.999, 3.0, 3.0000001, 7.0, np.inf, -np.inf, np.nan, -1.0]
)
def test_one_by_one_gives_the_solvers_pairs(value: float) -> None:
    cost = np.array([[value]])
    gate = 3.0
    c = np.where(np.isfinite(cost) & (cost <= gate), cost, 2.0 * gate * 2 + 1.0)
    full = np.array([[c[0, 0], gate], [gate, 0.0]])
    rows, cols = assignment.linear_sum_assignment(full)
    solver = [(0, 0)] if (rows[0], cols[0]) == (0, 0) and c[0, 0] <= gate else []
    assert assignment.gated_assignment(cost, gate) == solver


def test_one_track_one_instance_does_not_import_scipy() -> None:
    code = (
        "import sys, numpy as np\n"
        "from mistool.assignment import gated_assignment\n"
        "assert gated_assignment(np.array([[1.0]]), 2.0) == [(0, 0)]\n"
        "assert gated_assignment(np.array([[3.0]]), 2.0) == []\n"
        "print('scipy.optimize' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
