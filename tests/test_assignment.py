"""The shared assignment solver's shortcuts for a few rows and columns (one each, or
enumeration): the same pairs as SciPy's solver, without importing it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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


def _solver_pairs(cost: np.ndarray, gate: float) -> list[tuple[int, int]]:
    """``gated_assignment`` by SciPy's solver on the square problem, as it was for every
    size (commit ddfb117)."""
    n, m = cost.shape
    big = 2.0 * gate * (n + m) + 1.0
    gated = np.where(np.isfinite(cost) & (cost <= gate), cost, big)
    full = np.full((n + m, m + n), big)
    full[:n, :m] = gated
    full[:n, m:][np.diag_indices(n)] = gate
    full[n:, :m][np.diag_indices(m)] = gate
    full[n:, m:] = 0.0
    rows, cols = assignment.linear_sum_assignment(full)
    return sorted(
        (int(r), int(k))
        for r, k in zip(rows, cols, strict=True)
        if r < n and k < m and gated[r, k] < big
    )


def _total(cost: np.ndarray, gate: float, pairs: list[tuple[int, int]]) -> float:
    n, m = cost.shape
    return sum(float(cost[r, k]) for r, k in pairs) + gate * (n + m - 2 * len(pairs))


def _all_totals(cost: np.ndarray, gate: float) -> list[float]:
    """The total of every valid set of pairs (brute force over column choices)."""
    import itertools

    n, m = cost.shape
    out = []
    for choice in itertools.product(range(-1, m), repeat=n):
        cols = [k for k in choice if k >= 0]
        if len(cols) != len(set(cols)):
            continue
        pairs = [(r, k) for r, k in enumerate(choice) if k >= 0]
        if all(np.isfinite(cost[r, k]) and cost[r, k] <= gate for r, k in pairs):
            out.append(_total(cost, gate, pairs))
    return sorted(out)


@settings(max_examples=400, deadline=None)
@given(
    st.integers(1, assignment.ENUMERATE_MAX),
    st.integers(1, assignment.ENUMERATE_MAX),
    st.integers(0, 2**32 - 1),
    st.sampled_from([0.5, 3.0, 10.0]),
)
def test_small_problems_give_the_solvers_pairs_without_scipy(n, m, seed, gate):
    rng = np.random.default_rng(seed)
    cost = rng.uniform(-1.0, 2.0 * gate, (n, m))
    odd = rng.random((n, m))
    cost[odd < 0.1] = np.inf
    cost[(odd >= 0.1) & (odd < 0.15)] = np.nan
    cost[(odd >= 0.15) & (odd < 0.2)] = gate  # on the gate: allowed
    got = assignment.gated_assignment(cost, gate)
    want = _solver_pairs(cost, gate)
    totals = _all_totals(cost, gate)
    assert _total(cost, gate, got) == pytest.approx(totals[0], abs=1e-12)
    if len(totals) == 1 or totals[1] - totals[0] > 1e-9:  # one best: the solver's
        assert got == want


def test_a_few_tracks_do_not_import_scipy() -> None:
    code = (
        "import sys, numpy as np\n"
        "from mistool.assignment import gated_assignment\n"
        "c = np.array([[0.1, 2.0, np.inf], [1.5, 0.2, 9.0], [np.nan, 2.9, 0.3]])\n"
        "assert gated_assignment(c, 3.0) == [(0, 0), (1, 1), (2, 2)]\n"
        "assert gated_assignment(c[:2], 3.0) == [(0, 0), (1, 1)]\n"
        "print('scipy.optimize' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _enumerated_before(cost: list[list[float]], max_cost: float) -> list[tuple[int, int]]:
    """``assignment._enumerated`` as it was (commit 7cc3df9): a recursive walk over the
    rows, each unmatched first, then each free column in order."""
    import math

    n, m = len(cost), len(cost[0])
    ok = [[math.isfinite(x) and x <= max_cost for x in row] for row in cost]
    best: list[tuple[int, int]] = []
    best_total = math.inf
    pairs: list[tuple[int, int]] = []

    def walk(r: int, used: int, total_cost: float) -> None:
        nonlocal best, best_total
        if r == n:
            total = total_cost + max_cost * (n + m - 2 * len(pairs))
            if total < best_total:
                best, best_total = list(pairs), total
            return
        walk(r + 1, used, total_cost)
        for k in range(m):
            if ok[r][k] and not used >> k & 1:
                pairs.append((r, k))
                walk(r + 1, used | 1 << k, total_cost + cost[r][k])
                pairs.pop()

    walk(0, 0, 0.0)
    return best


@settings(max_examples=500, deadline=None)
@given(
    st.integers(1, assignment.ENUMERATE_MAX),
    st.integers(1, assignment.ENUMERATE_MAX),
    st.integers(0, 2**32 - 1),
    st.booleans(),
)
def test_the_enumeration_over_listed_matchings_is_the_former_walk(n, m, seed, ties):
    """The small problems' matchings tried from a list made once per shape give the
    former recursive walk's pairs, ties (the first of equal totals) and the gate's
    infinities and NaNs included."""
    rng = np.random.default_rng(seed)
    gate = 3.0
    cost = rng.integers(0, 4, (n, m)).astype(np.float64) if ties else rng.uniform(-1, 7, (n, m))
    odd = rng.random((n, m))
    cost[odd < 0.1] = np.inf
    cost[(odd >= 0.1) & (odd < 0.15)] = np.nan
    rows = cost.tolist()
    assert assignment._enumerated(rows, gate) == _enumerated_before(rows, gate)
