"""Property-based tests (hypothesis) of the one-line contract: any ``mistool.toml`` value
or type, any header-level PNG corruption and any motion-table row either works or ends
as one :class:`~mistool.errors.MistoolError` -- never another exception, never a hang.

Examples are bounded and derandomized (a fixed sequence of examples, the same on every
run and in CI) so the suite stays fast and reproducible.
"""

from __future__ import annotations

import csv
import io
import struct
import zlib
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mistool import api
from mistool.cli import main
from mistool.config import config_from_dict
from mistool.errors import MistoolError
from mistool.export import check_table_limits, read_csv, table_to_csv_text
from mistool.sequence import read_label_image

FUZZ = settings(
    max_examples=60,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

H, W = 64, 96


def _frame(shift: int) -> np.ndarray:
    img = np.zeros((H, W), np.uint8)
    img[26:36, 8 + shift : 50 + shift] = 160
    img[24:38, 50 + shift : 62 + shift] = 70
    return img


FRAMES = [_frame(i) for i in range(3)]

# --- mistool.toml values and types ----------------------------------------------------

_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e308, -1e308, 1e-308, 5e-324, 0.0, -0.0, 1e6, 1e-3, 25.0]),
)
_ints = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.sampled_from([0, 1, 70, 160, 255, 65535, 65536, -1]),
)
_scalars = st.one_of(
    _floats,
    _ints,
    st.booleans(),
    st.text(max_size=12),
    st.sampled_from(["endovis15", "endovis17", "ternaus", "#ff0000", "video.avi", ""]),
)
_values = st.recursive(
    _scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=8,
)
_TOP = ["fps", "labels", "min_area_px", "shaft_diameter_mm", "clasper_length_mm", "max_pixels"]
_CAMERA = ["fx", "fy", "cx", "cy"]
_PARTS = ["shaft", "wrist", "clasper"]
#: Values inside the documented ranges, edges included: these must track without error.
_VALID: dict[str, st.SearchStrategy[Any]] = {
    "fps": st.floats(0.01, 10_000.0),
    "labels": st.sampled_from(["endovis15", "endovis17", "ternaus"]),
    "min_area_px": st.integers(0, 10**9),
    "shaft_diameter_mm": st.floats(0.01, 1000.0),
    "clasper_length_mm": st.floats(0.01, 1000.0),
    "max_pixels": st.integers(H * W, 2**31 - 1),
    "fx": st.floats(1e-3, 1e6),
    "fy": st.floats(1e-3, 1e6),
    "cx": st.floats(-1e6, 1e6),
    "cy": st.floats(-1e6, 1e6),
}


@st.composite
def _configs(draw: st.DrawFn) -> dict[str, Any]:
    """Mostly valid configs with at most one hostile value (any type, any size), so both
    the validation and the tracking behind it are exercised."""
    hostile = draw(st.sampled_from([*_TOP, *_CAMERA, "parts", "instrument", "extra", None]))

    def value(key: str) -> Any:
        return draw(_values) if key == hostile else draw(_VALID[key])

    data: dict[str, Any] = {k: value(k) for k in _TOP if k == hostile or draw(st.booleans())}
    if hostile in _CAMERA or draw(st.booleans()):
        data["camera"] = {k: value(k) for k in _CAMERA}
    if hostile == "parts":
        data["parts"] = {k: draw(_values) for k in draw(st.lists(st.sampled_from(_PARTS)))}
    if hostile == "instrument":
        data["instrument"] = [
            {
                "shaft": draw(st.one_of(_ints, st.lists(_ints, min_size=2, max_size=2))),
                "shaft_diameter_mm": draw(st.one_of(_floats, _ints)),
            }
            for _ in range(draw(st.integers(0, 2)))
        ]
    if hostile == "extra":
        data[draw(st.text(max_size=6))] = draw(_scalars)
    return data


@FUZZ
@given(data=_configs())
def test_any_config_values_validate_or_fail_as_one_config_error(data: dict[str, Any]) -> None:
    """Validation never raises anything but MistoolError, and a config it accepts can
    track real frames (the metric pose included) without an exception."""
    try:
        config = config_from_dict(data)
    except MistoolError as exc:
        assert "\n" not in str(exc)
        return
    table = api.track(FRAMES, config, metric=True)
    assert table.num_rows >= 0
    times = np.asarray(table["time_s"], dtype=float)
    assert np.all(np.isfinite(times))


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if value != value:
            return "nan"
        if value in (float("inf"), float("-inf")):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    return '"' + value.encode("unicode_escape").decode().replace('"', '\\"') + '"'


@settings(FUZZ, max_examples=15)
@given(
    key=st.sampled_from(_TOP + [f"camera.{k}" for k in _CAMERA]),
    value=st.one_of(_floats, _ints, st.booleans(), st.text(max_size=8)),
)
def test_cli_reports_any_toml_value_as_one_line(
    tmp_path_factory: pytest.TempPathFactory, key: str, value: Any
) -> None:
    """End to end through the command line: exit 0, or exit 1 with one error line."""
    seq = tmp_path_factory.mktemp("fuzz") / "seq"
    seq.mkdir()
    for i, img in enumerate(FRAMES):
        cv2.imwrite(str(seq / f"{i}.png"), img)
    if key.startswith("camera."):
        cam = {"fx": 500.0, "fy": 500.0, "cx": 48.0, "cy": 32.0, key[7:]: value}
        text = "[camera]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in cam.items())
    else:
        text = f"{key} = {_toml(value)}\n"
    (seq / "mistool.toml").write_text(text, encoding="utf-8")
    out = seq.parent / "o.csv"
    with pytest.MonkeyPatch.context() as mp:
        err = io.StringIO()
        mp.setattr("sys.stderr", err)
        code = main(["track", str(seq), "-o", str(out), "-q"])
    lines = err.getvalue().splitlines()
    if code == 0:
        assert out.exists()
    else:
        assert code == 1 and len(lines) == 1, lines
        assert lines[0].startswith("mistool: error: ") and "internal error" not in lines[0]
        assert not out.exists()


# --- header-level PNG corruption ------------------------------------------------------


def _good_png() -> bytes:
    ok, buf = cv2.imencode(".png", FRAMES[0])
    assert ok
    return buf.tobytes()


GOOD_PNG = _good_png()


@FUZZ
@given(
    edits=st.lists(st.tuples(st.integers(0, 60), st.integers(0, 255)), min_size=1, max_size=6),
    fix_crc=st.booleans(),
    cut=st.one_of(st.none(), st.integers(0, len(GOOD_PNG))),
)
def test_corrupt_png_headers_decode_or_fail_as_one_mask_error(
    tmp_path_factory: pytest.TempPathFactory,
    edits: list[tuple[int, int]],
    fix_crc: bool,
    cut: int | None,
) -> None:
    data = bytearray(GOOD_PNG)
    for pos, byte in edits:  # the signature, IHDR (size, depth, colour type...) and CRC
        data[pos] = byte
    if fix_crc:  # corrupt but self-consistent: only the decoder can tell
        data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    if cut is not None:
        data = data[:cut]
    path = tmp_path_factory.mktemp("png") / "f.png"
    path.write_bytes(bytes(data))
    try:
        labels = read_label_image(path)
    except MistoolError as exc:
        assert "\n" not in str(exc)
        return
    assert labels.ndim == 2 and labels.size <= 50_000_000


# --- motion table rows ----------------------------------------------------------------

_cells = st.one_of(
    st.sampled_from(
        ["", "0", "1", "-1", "2000000000", "1e300", "nan", "inf", "-inf", "3.5", "x", "1e-308"]
    ),
    st.integers(-(2**40), 2**40).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=6),
)
_TABLE_COLUMNS = ["frame", "instrument", "part", "cx_px", "cy_px", "length_px", "width_px"]


@FUZZ
@given(
    rows=st.lists(
        st.fixed_dictionaries({c: _cells for c in _TABLE_COLUMNS}), min_size=0, max_size=5
    ),
    parts=st.lists(st.sampled_from(["shaft", "clasper", "wrist", "tip"]), min_size=5, max_size=5),
)
def test_motion_table_rows_load_or_fail_as_one_table_error(
    tmp_path_factory: pytest.TempPathFactory, rows: list[dict[str, str]], parts: list[str]
) -> None:
    """Any rows read by the viewer: the table loads and builds a replay, or one error."""
    from mistool.config import Config
    from mistool.viewer.replay import build_replay

    for row, part in zip(rows, parts, strict=False):
        if row["part"] not in ("shaft", "clasper", "wrist"):
            row["part"] = part
    buf = io.StringIO()
    writer = csv.DictWriter(buf, _TABLE_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    path = tmp_path_factory.mktemp("table") / "t.csv"
    path.write_text(buf.getvalue(), encoding="utf-8")
    try:
        table = read_csv(path)
        check_table_limits(table, str(path))
        replay = build_replay(table, Config())
    except MistoolError as exc:
        assert "\n" not in str(exc)
        return
    assert replay.num_frames >= 1
    assert table_to_csv_text(table).startswith("frame,")
