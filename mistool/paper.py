"""Algorithm 2 of the paper: frame-to-frame 3D motion from the four box corners.

Reproduced as printed (Eqs. 1-7 and the Algorithm 2 listing), vectorised with numpy over
every row of a track table, so that users can compare against the paper's own method.
Inputs are the corners ``(x_i, y_i)``, ``i = 1..4``, in ``cv2.boxPoints`` order (table
columns ``x1_px .. y4_px``); indices below are the paper's, 1-based, ``i%4+1`` the next
corner. For each (instrument, part), in frame order:

- Eq. (1) area, **exactly as printed, with the sums over i = 1..3 only**:
  ``A = 1/2 (sum_{i=1..3} x_i y_{i%4+1} - sum_{i=1..3} x_{i%4+1} y_i)``. The missing
  ``i = 4`` term (``x_4 y_1 - x_1 y_4``) makes this the shoelace area plus a term that
  depends on where the box is in the image: it changes with pure translation and is
  negative for many boxes. ``paper_motion(..., area="shoelace")`` uses the full 4-term
  shoelace instead (for boxPoints order, a positive area in image coordinates).
- Scale ``S^n = A^n / A^{n-1}``; Eq. (5) ``z^n = sqrt(f^2 (S^n)^2 / A^n)`` with ``f`` the
  focal length in px (the camera's ``fx`` when known, else 1.0: the caller passes it).
- Eq. (6) centroid ``C = (mean x_i, mean y_i)``; ``dx``, ``dy``, ``dz`` its and z's change.
- Eq. (4) edge slopes ``m_i = (y_{i%4+1} - y_i) / (x_{i%4+1} - x_i)``; Eq. (2) internal
  angles ``a_i = arctan((m_{i%4+1} - m_i) / (1 + m_{i%4+1} m_i))``, in degrees.
- The listing's ``e_r = a_1 + a_4 - a_2 - a_3``, ``e_p = a_3 + a_4 - a_1 - a_2`` and
  ``e_y = (180 - sum_i arctan(m_i)) / 4`` (degrees); ``droll, dpitch, dyaw`` their changes.
  (The paper's prose pairs the angles differently, roll from ``(a_1 + a_2) - (a_3 + a_4)``
  and pitch from ``(a_1 + a_4) - (a_2 + a_3)``, and says yaw subtracts the *average*
  slope angle from 180; the listing is followed. The yaw change is the same either way.)
- Eqs. (7) and (3): ``T = T_Z(dz) T_Y(dy) T_X(dx)`` and
  ``R = R_Z(dyaw) R_Y(dpitch) R_X(droll)``, from :func:`paper_matrices`.

What the paper leaves open, as mistool defines it:

- Consecutive frames only: the "previous frame" of a row is the same instrument and part
  in frame ``n - 1``. On a part's first frame, and on the first frame after it was absent,
  ``S = 1`` (no scale change yet, so ``z`` is defined) and every delta is NaN.
- A vertical edge has slope ``+-inf`` (IEEE division, the sign of its ``dy``); ``arctan``
  of ``+-inf`` is ``+-90`` deg. Eq. (2) with an infinite slope takes its limit
  (``-1/m_{i%4+1}`` or ``1/m_i``, two vertical edges give 0); no NaN and no warning. A
  zero-length edge (a degenerate box) has an undefined slope: its angles are NaN.
- ``z`` is NaN where ``A <= 0`` (zero area, or Eq. (1)'s truncated sum going negative) or
  where ``S`` is not finite (previous area 0).

What it implies (shown by ``tests/test_paper.py``):

- ``cv2.boxPoints`` returns an exact rectangle, so consecutive slopes satisfy
  ``m_i m_{i%4+1} = -1``: every ``a_i`` is +-90 deg (its sign set by rounding), ``e_r``
  and ``e_p`` are multiples of 180 deg, and so are ``droll`` and ``dpitch``: they are
  not rotations.
- The slope angles of a rectangle are ``theta`` and ``theta - 90`` reduced to
  ``(-90, 90]``, so ``e_y = 90 - (theta mod 90)`` for a box at angle ``theta`` (45 at
  exact multiples of 90): the yaw term is the box angle modulo 90 deg, and ``dyaw`` jumps
  by 90 when the box crosses an axis.
- ``z`` falls as the visible area grows: it follows how much of the part is inside the
  image (e.g. a shaft sliding in from the border) as much as its depth, and has no unit.
"""

from __future__ import annotations

import numpy as np

from mistool.model import TrackTable, require_columns

CORNER_COLUMNS: tuple[str, ...] = (
    "x1_px",
    "y1_px",
    "x2_px",
    "y2_px",
    "x3_px",
    "y3_px",
    "x4_px",
    "y4_px",
)

#: The columns :func:`paper_motion` fills.
PAPER_COLUMNS: tuple[str, ...] = (
    "dx_px",
    "dy_px",
    "dz",
    "droll_deg",
    "dpitch_deg",
    "dyaw_deg",
    "paper_x_px",
    "paper_y_px",
    "paper_z",
    "paper_roll_deg",
    "paper_pitch_deg",
    "paper_yaw_deg",
)

_NEXT = np.array([1, 2, 3, 0])  # 0-based index of the paper's corner i%4+1


def area_eq1(x: np.ndarray, y: np.ndarray, *, full: bool = False) -> np.ndarray:
    """Eq. (1): the box area from its corners.

    Args:
        x, y: (..., 4) corner coordinates, px, boxPoints order.
        full: False (the paper as printed) sums i = 1..3; True sums i = 1..4 (the
            shoelace formula).

    Returns:
        (...) area, px^2 (signed).
    """
    return _area(*_rows(x, y), full=full)


def slopes_eq4(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Eq. (4): slope of each edge ``i -> i%4+1``.

    Args:
        x, y: (..., 4) corner coordinates, px.

    Returns:
        (..., 4) slopes; ``+-inf`` for a vertical edge (sign of its dy), NaN for a
        zero-length edge.
    """
    return np.moveaxis(_slopes(*_rows(x, y)), 0, -1)


def internal_angles_eq2(m: np.ndarray) -> np.ndarray:
    """Eq. (2): ``a_i = arctan((m_{i%4+1} - m_i) / (1 + m_{i%4+1} m_i))``, degrees.

    Args:
        m: (..., 4) edge slopes (Eq. 4), possibly infinite.

    Returns:
        (..., 4) angles in degrees, in ``[-90, 90]``. An infinite slope takes the
        formula's limit; NaN only where a slope is NaN.
    """
    return np.moveaxis(_angles(np.moveaxis(np.asarray(m, dtype=np.float64), -1, 0)), 0, -1)


# Internals work on corner-major arrays, (4, ...): row i is the paper's corner i + 1.
def _rows(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.moveaxis(np.asarray(x, dtype=np.float64), -1, 0),
        np.moveaxis(np.asarray(y, dtype=np.float64), -1, 0),
    )


def _area(X: np.ndarray, Y: np.ndarray, *, full: bool) -> np.ndarray:
    s = X[0] * Y[1] + X[1] * Y[2] + X[2] * Y[3] - X[1] * Y[0] - X[2] * Y[1] - X[3] * Y[2]
    if full:
        s = s + X[3] * Y[0] - X[0] * Y[3]
    return 0.5 * s


def _slopes(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return (Y[_NEXT] - Y) / (X[_NEXT] - X)


def _angles(m1: np.ndarray) -> np.ndarray:
    m2 = m1[_NEXT]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = (m2 - m1) / (1.0 + m2 * m1)
        inf1, inf2 = np.isinf(m1), np.isinf(m2)
        if inf1.any() or inf2.any():  # vertical edges: the formula's limits
            # m1 -> +-inf: (m2 - m1) / (1 + m1 m2) -> -1/m2 (-sign(m1) inf when m2 == 0)
            lim1 = np.where(m2 == 0, -np.sign(m1) * np.inf, -1.0 / m2)
            # m2 -> +-inf: -> 1/m1 (sign(m2) inf when m1 == 0)
            lim2 = np.where(m1 == 0, np.sign(m2) * np.inf, 1.0 / m1)
            t = np.where(inf1 & ~inf2, lim1, t)
            t = np.where(inf2 & ~inf1, lim2, t)
            t = np.where(inf1 & inf2, 0.0, t)  # two vertical edges are parallel
    return np.degrees(np.arctan(t, out=t), out=t)


def paper_quantities(x: np.ndarray, y: np.ndarray, *, area: str = "paper") -> dict[str, np.ndarray]:
    """Algorithm 2's per-frame quantities from the corners (no frame-to-frame step).

    Args:
        x, y: (N, 4) corner coordinates, px, boxPoints order.
        area: ``"paper"`` (Eq. 1 as printed, i = 1..3) or ``"shoelace"`` (i = 1..4).

    Returns:
        ``A`` (N,) Eq. 1; ``cx``, ``cy`` (N,) Eq. 6; ``m`` (N, 4) Eq. 4; ``a`` (N, 4)
        Eq. 2 (deg); ``e_r``, ``e_p``, ``e_y`` (N,) deg.
    """
    q = _quantities(*_rows(x, y), area=area)
    q["m"] = np.moveaxis(q["m"], 0, -1)
    q["a"] = np.moveaxis(q["a"], 0, -1)
    return q


def _quantities(X: np.ndarray, Y: np.ndarray, *, area: str) -> dict[str, np.ndarray]:
    if area not in ("paper", "shoelace"):
        raise ValueError(f"area must be 'paper' or 'shoelace', got {area!r}")
    m = _slopes(X, Y)
    a = _angles(m)
    slope_deg = np.degrees(np.arctan(m))
    return {
        "A": _area(X, Y, full=area == "shoelace"),
        "cx": (X[0] + X[1] + X[2] + X[3]) / 4.0,
        "cy": (Y[0] + Y[1] + Y[2] + Y[3]) / 4.0,
        "m": m,
        "a": a,
        "e_r": a[0] + a[3] - a[1] - a[2],
        "e_p": a[2] + a[3] - a[0] - a[1],
        "e_y": (180.0 - (slope_deg[0] + slope_deg[1] + slope_deg[2] + slope_deg[3])) / 4.0,
    }


def previous_rows(table: TrackTable) -> np.ndarray:
    """For each row, the row index of the same (instrument, part) in the previous frame.

    Args:
        table: a track table (any row order).

    Returns:
        (N,) int64 row indices, -1 where that part was not observed in frame ``n - 1``.
    """
    n = table.num_rows
    prev = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return prev
    frame = np.asarray(table["frame"], dtype=np.int64)
    inst = _codes(np.asarray(table["instrument"]))
    part = _codes(np.asarray(table["part"]))
    order = np.lexsort((frame, part, inst))
    f, i, p = frame[order], inst[order], part[order]
    ok = (i[1:] == i[:-1]) & (p[1:] == p[:-1]) & (f[1:] == f[:-1] + 1)
    prev[order[1:][ok]] = order[:-1][ok]
    return prev


def _codes(values: np.ndarray) -> np.ndarray:
    """Integer codes of a column's distinct values (any order)."""
    lst = values.tolist()
    distinct = list(dict.fromkeys(lst))
    if len(distinct) <= 16:  # a few parts / instruments: vectorised comparisons
        codes = np.zeros(len(lst), dtype=np.int64)
        for k, v in enumerate(distinct[1:], 1):
            codes[values == v] = k
        return codes
    index = {v: k for k, v in enumerate(distinct)}
    return np.fromiter((index[v] for v in lst), dtype=np.int64, count=len(lst))


def paper_motion(table: TrackTable, focal_px: float = 1.0, *, area: str = "paper") -> TrackTable:
    """Algorithm 2 over a whole track table, vectorised.

    Args:
        table: rows with ``frame``, ``instrument``, ``part`` and the corner columns
            ``x1_px .. y4_px`` (boxPoints order).
        focal_px: ``f`` of Eq. (5), px (camera ``fx`` when known, else 1.0).
        area: ``"paper"`` (Eq. 1 as printed) or ``"shoelace"`` (full 4-term sum).

    Returns:
        The table with :data:`PAPER_COLUMNS` filled (same row order). Deltas are NaN on
        a part's first frame and after a gap; see the module docstring for every case.

    Raises:
        TableError: if a required column is missing.
    """
    require_columns(table, ("frame", "instrument", "part", *CORNER_COLUMNS), "paper_motion")
    n = table.num_rows
    if n == 0:
        return table.with_columns(**{c: np.empty(0) for c in PAPER_COLUMNS})
    X = np.stack([np.asarray(table[f"x{i}_px"], dtype=np.float64) for i in range(1, 5)])
    Y = np.stack([np.asarray(table[f"y{i}_px"], dtype=np.float64) for i in range(1, 5)])
    q = _quantities(X, Y, area=area)
    prev = previous_rows(table)
    has = prev >= 0
    j = np.where(has, prev, 0)

    def delta(v: np.ndarray) -> np.ndarray:
        return np.where(has, v - v[j], np.nan)

    A = q["A"]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        S = np.where(has, A / A[j], 1.0)  # S = 1 on a part's first frame (no change yet)
        z = np.sqrt(focal_px**2 * S**2 / A)
    z = np.where((A > 0) & np.isfinite(S) & np.isfinite(z), z, np.nan)
    return table.with_columns(
        dx_px=delta(q["cx"]),
        dy_px=delta(q["cy"]),
        dz=delta(z),
        droll_deg=delta(q["e_r"]),
        dpitch_deg=delta(q["e_p"]),
        dyaw_deg=delta(q["e_y"]),
        paper_x_px=q["cx"],
        paper_y_px=q["cy"],
        paper_z=z,
        paper_roll_deg=q["e_r"],
        paper_pitch_deg=q["e_p"],
        paper_yaw_deg=q["e_y"],
    )


def paper_matrices(table: TrackTable) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. (7) and (3): the translation and rotation matrices of every row.

    ``T = T_Z(dz) T_Y(dy) T_X(dx) = [[1, 0, dx], [0, 1, dy], [0, 0, dz]]`` (the paper's
    3x3 forms, multiplied out) and ``R = R_Z(dyaw) R_Y(dpitch) R_X(droll)``.

    Args:
        table: a table with the delta columns (:func:`paper_motion`'s output).

    Returns:
        ``(T, R)``, each (N, 3, 3) float64; NaN where the deltas are NaN.
    """
    require_columns(table, PAPER_COLUMNS[:6], "paper_matrices")
    n = table.num_rows
    dx, dy, dz = (np.asarray(table[c], dtype=np.float64) for c in ("dx_px", "dy_px", "dz"))
    T = np.zeros((n, 3, 3))
    T[:, 0, 0] = T[:, 1, 1] = 1.0
    T[:, 0, 2], T[:, 1, 2], T[:, 2, 2] = dx, dy, dz
    phi, theta, psi = (
        np.radians(np.asarray(table[c], dtype=np.float64))
        for c in ("droll_deg", "dpitch_deg", "dyaw_deg")
    )
    R = rot_z(psi) @ rot_y(theta) @ rot_x(phi)
    return T, R


def rot_x(phi: np.ndarray) -> np.ndarray:
    """``R_X``: (N,) radians -> (N, 3, 3)."""
    c, s = np.cos(phi), np.sin(phi)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def rot_y(theta: np.ndarray) -> np.ndarray:
    """``R_Y``: (N,) radians -> (N, 3, 3)."""
    c, s = np.cos(theta), np.sin(theta)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack(
        [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2
    )


def rot_z(psi: np.ndarray) -> np.ndarray:
    """``R_Z``: (N,) radians -> (N, 3, 3)."""
    c, s = np.cos(psi), np.sin(psi)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )
