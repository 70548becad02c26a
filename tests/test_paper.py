"""Algorithm 2 (paper.py): each equation on hand-computed cases, the open cases, and the
degeneracies DESIGN.md lists (shown here, not taken on trust).

Every expected number below was worked out by hand (shown in the comments), not by the
code under test.
"""

from __future__ import annotations

import math
import warnings

import cv2
import numpy as np
import pytest

from mistool.errors import TableError
from mistool.model import RotatedBox, TrackTable
from mistool.paper import (
    PAPER_COLUMNS,
    area_eq1,
    internal_angles_eq2,
    paper_matrices,
    paper_motion,
    paper_quantities,
    slopes_eq4,
)

# Box 1: corners (3,3) (3,1) (7,1) (7,3): a 4 x 2 axis-aligned box in boxPoints order.
B1 = [(3.0, 3.0), (3.0, 1.0), (7.0, 1.0), (7.0, 3.0)]
# Box 2: (4,5) (4,2) (10,2) (10,5): 6 x 3, centre (7, 3.5).
B2 = [(4.0, 5.0), (4.0, 2.0), (10.0, 2.0), (10.0, 5.0)]
# A general quadrilateral with finite slopes: (0,0) (4,1) (3,3) (1,2).
Q = [(0.0, 0.0), (4.0, 1.0), (3.0, 3.0), (1.0, 2.0)]


def xy(corners):
    c = np.asarray(corners, dtype=np.float64)
    return c[:, 0], c[:, 1]


def table(rows):
    """rows: (frame, instrument, part, corners)."""
    cols = {
        "frame": [r[0] for r in rows],
        "instrument": [r[1] for r in rows],
        "part": [r[2] for r in rows],
    }
    for i in range(4):
        cols[f"x{i + 1}_px"] = [float(r[3][i][0]) for r in rows]
        cols[f"y{i + 1}_px"] = [float(r[3][i][1]) for r in rows]
    return TrackTable(cols)


def cv_corners(box: RotatedBox):
    return cv2.boxPoints(((box.cx, box.cy), (box.length, box.width), box.angle_deg))


# Eq. (1) -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "corners, paper, shoelace",
    [
        # B1: sum_{i=1..3} x_i y_{i+1} = 3*1 + 3*1 + 7*3 = 27; sum x_{i+1} y_i = 3*3 + 7*1 + 7*1
        #     = 23 -> A = (27 - 23)/2 = 2. The i = 4 term x4*y1 - x1*y4 = 21 - 9 = 12 -> 8 = 4*2.
        (B1, 2.0, 8.0),
        # B2: 4*2 + 4*2 + 10*5 = 66; 4*5 + 10*2 + 10*2 = 60 -> 3. i = 4: 50 - 20 = 30 -> 18.
        (B2, 3.0, 18.0),
        # Q: 0*1 + 4*3 + 3*2 = 18; 4*0 + 3*1 + 1*3 = 6 -> 6; i = 4: 1*0 - 0*2 = 0 -> 6 too.
        (Q, 6.0, 6.0),
    ],
)
def test_eq1_area_as_printed(corners, paper, shoelace):
    x, y = xy(corners)
    assert area_eq1(x, y) == pytest.approx(paper)
    assert area_eq1(x, y, full=True) == pytest.approx(shoelace)


def test_eq1_depends_on_position_and_can_be_negative():
    """Eq. (1)'s missing i = 4 term makes the 'area' change with pure translation."""
    x, y = xy(B1)
    # shifted by (+10, 0): 13*1 + 13*1 + 17*3 = 77; 13*3 + 17*1 + 17*1 = 73 -> 2 (same);
    # shifted by (0, +10): 3*11 + 3*11 + 7*13 = 157; 3*13 + 7*11 + 7*11 = 193 -> -18.
    assert area_eq1(x + 10, y) == pytest.approx(2.0)
    assert area_eq1(x, y + 10) == pytest.approx(-18.0)
    assert area_eq1(x, y + 10, full=True) == pytest.approx(8.0)


# Eq. (4), Eq. (2), e_r, e_p, e_y, Eq. (6) ------------------------------------------------


def test_general_quadrilateral_by_hand():
    q = paper_quantities(*[v[None] for v in xy(Q)])
    # Eq. 4: (0,0)->(4,1): 1/4; (4,1)->(3,3): 2/-1 = -2; (3,3)->(1,2): -1/-2 = 0.5;
    #        (1,2)->(0,0): -2/-1 = 2
    np.testing.assert_allclose(q["m"][0], [0.25, -2.0, 0.5, 2.0])
    # Eq. 2: a1 = atan((-2 - 0.25)/(1 - 0.5)) = atan(-4.5) = -77.4711923 deg
    #        a2 = atan((0.5 + 2)/(1 - 1)) = atan(+inf) = 90
    #        a3 = atan((2 - 0.5)/(1 + 1)) = atan(0.75) = 36.8698976
    #        a4 = atan((0.25 - 2)/(1 + 0.5)) = atan(-7/6) = -49.3987054
    np.testing.assert_allclose(q["a"][0], [-77.4711923, 90.0, 36.8698976, -49.3987054], atol=1e-6)
    # e_r = a1 + a4 - a2 - a3 = -77.4711923 - 49.3987054 - 90 - 36.8698976 = -253.7397953
    # e_p = a3 + a4 - a1 - a2 = 36.8698976 - 49.3987054 + 77.4711923 - 90 = -25.0576155
    # e_y = (180 - (14.0362435 - 63.4349488 + 26.5650512 + 63.4349488)) / 4
    #     = (180 - 40.6012947) / 4 = 34.8496763
    assert q["e_r"][0] == pytest.approx(-253.7397953, abs=1e-6)
    assert q["e_p"][0] == pytest.approx(-25.0576155, abs=1e-6)
    assert q["e_y"][0] == pytest.approx(34.8496763, abs=1e-6)
    # Eq. 6: ((0+4+3+1)/4, (0+1+3+2)/4) = (2, 1.5)
    assert (q["cx"][0], q["cy"][0]) == pytest.approx((2.0, 1.5))


def test_vertical_edges_take_the_limit_without_warnings():
    x, y = xy(B1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m = slopes_eq4(x, y)
        a = internal_angles_eq2(m[None])[0]
        q = paper_quantities(x[None], y[None])
    # edges: (3,3)->(3,1): dy = -2 over dx = 0 -> -inf; (3,1)->(7,1): 0; (7,1)->(7,3): +inf;
    # (7,3)->(3,3): 0 / -4 = -0.0
    assert m[0] == -np.inf and m[1] == 0 and m[2] == np.inf and m[3] == 0
    # a1: m1 -> -inf, m2 = 0: (0 - m1)/(1 + 0) -> +inf -> +90
    # a2: m2 = 0, m3 -> +inf: (m3 - 0)/(1 + 0) -> +inf -> +90
    # a3: m3 -> +inf, m4 = 0: (0 - m3)/1 -> -inf -> -90
    # a4: m4 = 0, m1 -> -inf: (m1 - 0)/1 -> -inf -> -90
    np.testing.assert_array_equal(a, [90.0, 90.0, -90.0, -90.0])
    # e_r = 90 - 90 - 90 + 90 = 0; e_p = -90 - 90 - 90 - 90 = -360;
    # e_y = (180 - (-90 + 0 + 90 + 0)) / 4 = 45
    assert (q["e_r"][0], q["e_p"][0], q["e_y"][0]) == (0.0, -360.0, 45.0)


def test_eq2_limits_with_one_infinite_slope():
    # m1 = inf, m2 = 2: limit -1/m2 = -0.5 -> atan = -26.5650512
    # m2 = inf, m1 = 2 (second pair): limit 1/m1 = 0.5 -> 26.5650512
    a = internal_angles_eq2(np.array([[np.inf, 2.0, np.inf, 2.0]]))[0]
    np.testing.assert_allclose(a, [-26.5650512, 26.5650512, -26.5650512, 26.5650512], atol=1e-6)
    both = internal_angles_eq2(np.array([[np.inf, -np.inf, 0.0, 1.0]]))[0]
    assert both[0] == 0.0  # two vertical edges are parallel


# frame to frame: S, z (Eq. 5), dx, dy, dz, T, R ---------------------------------------


def test_two_frames_by_hand():
    t = paper_motion(table([(0, "1", "shaft", B1), (1, "1", "shaft", B2)]), focal_px=2.0)
    # frame 0: S = 1 (first frame), A = 2 -> z = sqrt(4 * 1 / 2) = sqrt(2) = 1.4142136
    # frame 1: S = 3/2, A = 3 -> z = sqrt(4 * 2.25 / 3) = sqrt(3) = 1.7320508
    np.testing.assert_allclose(t["paper_z"], [1.4142136, 1.7320508], atol=1e-7)
    assert np.isnan(t["dz"][0]) and np.isnan(t["dx_px"][0]) and np.isnan(t["droll_deg"][0])
    # centroids (5, 2) -> (7, 3.5): dx = 2, dy = 1.5; dz = 1.7320508 - 1.4142136 = 0.3178372
    assert t["dx_px"][1] == pytest.approx(2.0)
    assert t["dy_px"][1] == pytest.approx(1.5)
    assert t["dz"][1] == pytest.approx(0.3178372, abs=1e-7)
    np.testing.assert_allclose(t["paper_x_px"], [5.0, 7.0])
    np.testing.assert_allclose(t["paper_y_px"], [2.0, 3.5])
    # both boxes have the same edge pattern: e's equal, deltas 0
    assert (t["droll_deg"][1], t["dpitch_deg"][1], t["dyaw_deg"][1]) == (0.0, 0.0, 0.0)
    # with the full shoelace: A = 8 then 18, S = 2.25: z = sqrt(4/8) = 0.7071068,
    # sqrt(4 * 5.0625 / 18) = sqrt(1.125) = 1.0606602
    s = paper_motion(table([(0, "1", "shaft", B1), (1, "1", "shaft", B2)]), 2.0, area="shoelace")
    np.testing.assert_allclose(s["paper_z"], [0.7071068, 1.0606602], atol=1e-7)
    # Eq. 7: T = [[1, 0, dx], [0, 1, dy], [0, 0, dz]]
    T, R = paper_matrices(t)
    np.testing.assert_allclose(T[1], [[1, 0, 2.0], [0, 1, 1.5], [0, 0, 0.3178372]], atol=1e-7)
    np.testing.assert_allclose(R[1], np.eye(3), atol=1e-12)
    assert np.isnan(T[0]).any() and np.isnan(R[0]).any()


@pytest.mark.parametrize(
    "droll, dpitch, dyaw, expected",
    [
        # R_X(90): [[1,0,0],[0,cos,-sin],[0,sin,cos]] = [[1,0,0],[0,0,-1],[0,1,0]]
        (90.0, 0.0, 0.0, [[1, 0, 0], [0, 0, -1], [0, 1, 0]]),
        # R_Y(90): [[cos,0,sin],[0,1,0],[-sin,0,cos]] = [[0,0,1],[0,1,0],[-1,0,0]]
        (0.0, 90.0, 0.0, [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
        # R_Z(90) R_Y(90) = [[0,-1,0],[1,0,0],[0,0,1]] @ [[0,0,1],[0,1,0],[-1,0,0]]
        #                 = [[0,-1,0],[0,0,1],[-1,0,0]]
        (0.0, 90.0, 90.0, [[0, -1, 0], [0, 0, 1], [-1, 0, 0]]),
        # R_Z(180) = diag(-1, -1, 1)
        (0.0, 0.0, 180.0, [[-1, 0, 0], [0, -1, 0], [0, 0, 1]]),
    ],
)
def test_eq3_rotation_order(droll, dpitch, dyaw, expected):
    t = TrackTable(
        {
            "frame": [0],
            "instrument": ["1"],
            "part": ["shaft"],
            "dx_px": [0.0],
            "dy_px": [0.0],
            "dz": [0.0],
            "droll_deg": [droll],
            "dpitch_deg": [dpitch],
            "dyaw_deg": [dyaw],
        }
    )
    _, R = paper_matrices(t)
    np.testing.assert_allclose(R[0], expected, atol=1e-12)


def test_consecutive_frames_only_and_groups():
    rows = [
        (5, "2", "clasper", B2),
        (0, "1", "shaft", B1),
        (1, "1", "shaft", B2),
        (3, "1", "shaft", B1),  # frame 2 missing: a new run starts
        (4, "1", "shaft", B2),
        (4, "2", "clasper", B1),
        (1, "1", "clasper", B1),
    ]
    t = paper_motion(table(rows), focal_px=2.0)
    has_delta = ~np.isnan(t["dx_px"])
    # with a previous frame: (1,"1",shaft), (4,"1",shaft), (5,"2",clasper)
    assert has_delta.tolist() == [True, False, True, False, True, False, False]
    # after the gap S = 1 again: frame 3's z = sqrt(4/2), like frame 0's
    assert t["paper_z"][3] == pytest.approx(math.sqrt(2.0))
    # (5,"2",clasper) follows (4,"2",clasper): B1 -> B2, dx = 2
    assert t["dx_px"][0] == pytest.approx(2.0)
    # same result whatever the row order
    perm = [6, 3, 0, 5, 1, 4, 2]
    tp = paper_motion(table([rows[i] for i in perm]), focal_px=2.0)
    for c in PAPER_COLUMNS:
        np.testing.assert_array_equal(tp[c], t[c][perm])


def test_zero_area_and_degenerate_boxes():
    point = [(5.0, 5.0)] * 4  # a one-pixel part fitted to its pixel centre: 0 x 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t = paper_motion(
            table([(0, "1", "shaft", B1), (1, "1", "shaft", point), (2, "1", "shaft", B1)])
        )
    assert np.isnan(t["paper_z"][1])  # A = 0
    assert np.isnan(t["paper_z"][2])  # S = A / 0 is not finite
    assert np.isnan(t["paper_roll_deg"][1])  # zero-length edges have no slope
    assert t["dx_px"][1] == pytest.approx(0.0)  # centroid (5, 5) vs (5, 2): dx 0, dy 3
    assert t["dy_px"][1] == pytest.approx(3.0)


def test_negative_eq1_area_gives_no_z():
    shifted = [(x, y + 10) for x, y in B1]  # Eq. 1 gives -18 here (see above)
    t = paper_motion(table([(0, "1", "shaft", shifted)]))
    assert np.isnan(t["paper_z"][0])
    s = paper_motion(table([(0, "1", "shaft", shifted)]), area="shoelace")
    assert s["paper_z"][0] == pytest.approx(1 / math.sqrt(8.0))


def test_empty_and_missing_columns():
    out = paper_motion(table([]))
    assert out.num_rows == 0 and all(c in out for c in PAPER_COLUMNS)
    with pytest.raises(TableError, match="x1_px"):
        paper_motion(TrackTable({"frame": [0], "instrument": ["1"], "part": ["shaft"]}))
    with pytest.raises(ValueError, match="area"):
        paper_motion(table([(0, "1", "shaft", B1)]), area="exact")


# the degeneracies, verified ----------------------------------------------------------

ANGLES = [
    0.0,
    5.0,
    17.0,
    30.0,
    44.0,
    45.0,
    46.0,
    60.0,
    89.0,
    90.0,
    91.0,
    120.0,
    135.0,
    150.0,
    179.0,
]


def rect_table(angles, centre=(351.3, 270.2), size=(150.0, 20.0)):
    boxes = [RotatedBox(*centre, *size, a) for a in angles]
    return table([(k, "1", "shaft", cv_corners(b)) for k, b in enumerate(boxes)])


def test_rectangle_internal_angles_are_all_plus_minus_90():
    rng = np.random.default_rng(3)
    angles = list(rng.uniform(0, 180, 200)) + ANGLES
    boxes = [
        RotatedBox(
            rng.uniform(50, 650), rng.uniform(50, 500), rng.uniform(20, 300), rng.uniform(5, 20), a
        )
        for a in angles
    ]
    c = np.array([cv_corners(b) for b in boxes], dtype=np.float64)
    q = paper_quantities(c[..., 0], c[..., 1])
    np.testing.assert_allclose(np.abs(q["a"]), 90.0, atol=1e-3)
    # so e_r and e_p, and every roll / pitch change, are multiples of 180 deg
    for e in (q["e_r"], q["e_p"]):
        assert np.allclose(np.round(e / 180.0) * 180.0, e, atol=5e-3)
    t = paper_motion(rect_table(angles))
    for col in ("droll_deg", "dpitch_deg"):
        d = t[col][1:]
        assert np.allclose(np.round(d / 180.0) * 180.0, d, atol=5e-3)


@pytest.mark.parametrize("angle", ANGLES)
def test_yaw_term_is_the_box_angle_modulo_90(angle):
    q = paper_quantities(
        *[v[None] for v in xy(cv_corners(RotatedBox(351.3, 270.2, 150.0, 20.0, angle)))]
    )
    r = angle % 90.0
    # slopes' angles are theta and theta - 90 reduced to (-90, 90]: their sum is
    # 4 (theta mod 90) - 180, so e_y = (180 - that) / 4 = 90 - (theta mod 90);
    # on an axis one edge pair is vertical (+90 and -90): e_y = (180 - 0) / 4 = 45
    expected = 45.0 if r == 0 else 90.0 - r
    assert q["e_y"][0] == pytest.approx(expected, abs=1e-3)


def test_yaw_change_jumps_by_90_when_crossing_an_axis():
    t = paper_motion(rect_table([88.0, 89.0, 91.0, 92.0]))
    # e_y: 2, 1, 89, 88 -> dyaw: -1, +88, -1 (a 2 deg rotation reads as 88 deg)
    np.testing.assert_allclose(t["dyaw_deg"][1:], [-1.0, 88.0, -1.0], atol=1e-3)


def test_z_follows_visible_size_not_depth():
    """A shaft at constant depth sliding into view: z changes with the visible length."""
    lengths = [60.0, 120.0, 180.0, 240.0]
    boxes = [RotatedBox(L / 2, 300.0, L, 20.0, 0.0) for L in lengths]  # entering from x=0
    t = paper_motion(
        table([(k, "1", "shaft", cv_corners(b)) for k, b in enumerate(boxes)]),
        focal_px=500.0,
        area="shoelace",
    )
    z = t["paper_z"]
    # frame 0: S = 1, A = 1200: z = 500 / sqrt(1200) = 14.4337567
    # frame k: S = A_k / A_{k-1} = L_k / L_{k-1}, z = 500 S / sqrt(20 L_k):
    #   k=1: 500 * 2 / sqrt(2400) = 20.4124145; k=2: 500 * 1.5 / sqrt(3600) = 12.5;
    #   k=3: 500 * 4/3 / sqrt(4800) = 9.6225045
    np.testing.assert_allclose(z, [14.4337567, 20.4124145, 12.5, 9.6225045], atol=1e-6)
    # a box of constant size gives constant z wherever it is; the same box twice as
    # long (no depth change) gives z / sqrt(2)
    same = [RotatedBox(100.0 + 50 * k, 300.0, 100.0, 20.0, 30.0) for k in range(3)]
    s = paper_motion(
        table([(k, "1", "shaft", cv_corners(b)) for k, b in enumerate(same)]),
        focal_px=500.0,
        area="shoelace",
    )
    np.testing.assert_allclose(s["paper_z"], 500 / math.sqrt(2000.0), rtol=1e-5)
    np.testing.assert_allclose(s["dz"][1:], 0.0, atol=1e-6)


def test_observed_translation_gives_dx_dy():
    """Algorithm 1 then 2 on a drawn bar moving 3 px right and 2 px down per frame."""
    from mistool.config import Config
    from mistool.tracking import observe_frame

    rows = []
    for k in range(5):
        img = np.zeros((200, 300), np.uint8)
        img[50 + 2 * k : 70 + 2 * k, 40 + 3 * k : 160 + 3 * k] = 160  # 120 x 20 shaft
        (inst,) = observe_frame(img, Config())
        rows.append((k, "1", "shaft", inst.parts["shaft"].corners))
    t = paper_motion(table(rows), focal_px=1.0, area="shoelace")
    np.testing.assert_allclose(t["dx_px"][1:], 3.0, atol=1e-9)
    np.testing.assert_allclose(t["dy_px"][1:], 2.0, atol=1e-9)
    np.testing.assert_allclose(t["dz"][1:], 0.0, atol=1e-12)  # same area: S = 1
    # A = 120 * 20 = 2400 px^2 (pixel-edge box): z = 1 / sqrt(2400) = 0.0204124
    np.testing.assert_allclose(t["paper_z"], 0.0204124, atol=1e-7)
