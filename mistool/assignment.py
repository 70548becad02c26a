"""Minimum-cost one-to-one assignment, shared by identity tracking and evaluation.

One solver (SciPy's ``linear_sum_assignment``, the Jonker-Volgenant algorithm) behind two
entry points: :func:`linear_assignment` (every row or column matched) and
:func:`gated_assignment` (a pair costlier than a gate is never made; leaving a row or a
column unmatched costs the gate; a few rows and columns: by enumeration, without SciPy).
"""

from __future__ import annotations

import functools
import math

import numpy as np

__all__ = ["gated_assignment", "linear_assignment"]

#: :func:`gated_assignment` tries every partial matching (in Python, no SciPy) when the
#: rows and the columns are at most this many (at most 34 matchings: a few tracks, a
#: few instances, the usual frame); SciPy's solver beyond.
ENUMERATE_MAX = 3


def linear_sum_assignment(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SciPy's ``linear_sum_assignment``, imported at the first call: ``scipy.optimize``
    takes ~0.3 s to import, and the worker processes (``mistool.parallel`` imports
    ``mistool.tracking``) never assign."""
    from scipy.optimize import linear_sum_assignment as solve

    rows, cols = solve(cost)
    return np.asarray(rows), np.asarray(cols)


def linear_assignment(cost: np.ndarray) -> list[tuple[int, int]]:
    """Minimum-cost one-to-one assignment.

    Args:
        cost: (n, m) finite costs.

    Returns:
        ``min(n, m)`` pairs ``(row, col)``, sorted by row.
    """
    c = np.asarray(cost, dtype=np.float64)
    if c.size == 0:
        return []
    rows, cols = linear_sum_assignment(c)
    return sorted(zip(rows.tolist(), cols.tolist(), strict=True))


def gated_assignment(
    cost: np.ndarray | list[list[float]], max_cost: float
) -> list[tuple[int, int]]:
    """Pairs ``(row, col)`` minimising the total cost, where a pair costing more than
    ``max_cost`` (or non-finite) is never made and each unmatched row or column costs
    ``max_cost``.

    Up to :data:`ENUMERATE_MAX` rows and columns, every set of pairs is tried (tens of
    microseconds, no SciPy); beyond, solved as one square problem: the (n, m) costs
    beside an (n, n) block of "row unmatched" costs and above an (m, m) block of
    "column unmatched" costs.

    Args:
        cost: (n, m) costs; ``inf`` where a pair is impossible. Also as rows of Python
            floats (a list of n lists of m): the same answer as their array, and a small
            problem is solved without making one.
        max_cost: the gate, > 0.

    Returns:
        The pairs made, sorted by row.
    """
    if isinstance(cost, list):
        n, m = len(cost), len(cost[0]) if cost else 0
        if n == 0 or m == 0:
            return []
        if n <= ENUMERATE_MAX and m <= ENUMERATE_MAX:
            return _enumerated(cost, max_cost)
    c = np.asarray(cost, dtype=np.float64)
    n, m = c.shape
    if n == 0 or m == 0:
        return []
    if n <= ENUMERATE_MAX and m <= ENUMERATE_MAX:
        # a few tracks and instances (the usual frame): without the solver (nor its
        # ~0.4 s import)
        return _enumerated(c.tolist(), max_cost)
    big = 2.0 * max_cost * (n + m) + 1.0  # never chosen over leaving both unmatched
    gated = np.where(np.isfinite(c) & (c <= max_cost), c, big)
    full = np.full((n + m, m + n), big)
    full[:n, :m] = gated
    full[:n, m:][np.diag_indices(n)] = max_cost
    full[n:, :m][np.diag_indices(m)] = max_cost
    full[n:, m:] = 0.0
    rows, cols = linear_sum_assignment(full)
    return sorted(
        (int(r), int(k))
        for r, k in zip(rows, cols, strict=True)
        if r < n and k < m and gated[r, k] < big
    )


def _enumerated(cost: list[list[float]], max_cost: float) -> list[tuple[int, int]]:
    """:func:`gated_assignment` of a small problem by trying every set of pairs (each
    row: no pair, or a free column whose cost is finite and at most ``max_cost``); the
    first of equal totals is kept. Sorted by row. (One row and one column: the pair
    costs at most ``max_cost``, leaving both unmatched ``2 max_cost``, so it is made
    exactly when it passes the gate.)

    The sets are tried in the order of a depth-first walk over the rows (each row
    unmatched first, then its columns in order; :func:`_matchings`), each total summed
    row by row from 0 as the walk did."""
    n, m = len(cost), len(cost[0])
    if n == 1 and m == 1:  # (the walk's answer: one track, one instance)
        x = cost[0][0]
        return [(0, 0)] if math.isfinite(x) and x <= max_cost else []
    ok = [[math.isfinite(x) and x <= max_cost for x in row] for row in cost]
    best: tuple[tuple[int, int], ...] = ()
    best_total = math.inf
    for pairs in _matchings(n, m):
        total = 0.0
        for r, k in pairs:
            if not ok[r][k]:
                break
            total += cost[r][k]
        else:
            total = total + max_cost * (n + m - 2 * len(pairs))
            if total < best_total:
                best, best_total = pairs, total
    return list(best)


@functools.cache
def _matchings(n: int, m: int) -> tuple[tuple[tuple[int, int], ...], ...]:
    """Every partial matching of ``n`` rows to ``m`` columns, as pairs sorted by row, in
    the order of a depth-first walk: row ``r`` unmatched first, then matched to each
    free column in order (computed once per shape)."""
    out: list[tuple[tuple[int, int], ...]] = []

    def walk(r: int, used: int, pairs: tuple[tuple[int, int], ...]) -> None:
        if r == n:
            out.append(pairs)
            return
        walk(r + 1, used, pairs)  # row r unmatched
        for k in range(m):
            if not used >> k & 1:
                walk(r + 1, used | 1 << k, (*pairs, (r, k)))

    walk(0, 0, ())
    return tuple(out)
