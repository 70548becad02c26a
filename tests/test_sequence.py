"""Reading mask sequences: folders (pixel formats, natural order), videos, arrays, errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.config import Config, config_from_dict
from mistool.errors import InputPathError, MaskFormatError
from mistool.sequence import (
    natural_key,
    natural_order,
    open_sequence,
    read_label_image,
    resolve,
    to_labels,
    widen_for_video,
)


def _labels(h: int = 24, w: int = 32, value: int = 160, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.uint8)
    y, x = rng.integers(0, h - 6), rng.integers(0, w - 6)
    img[y : y + 6, x : x + 6] = value
    img[0, 0] = 70
    return img


def _write(path: Path, img: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), img)
    return path


def test_natural_sort_orders_numbers_numerically(tmp_path: Path) -> None:
    names = ["frame10.png", "frame2.png", "frame1.png", "frame100.png", "Frame3.png"]
    for i, name in enumerate(names):
        _write(tmp_path / name, _labels(value=100 + i))
    order = [name for _, name, _ in open_sequence(tmp_path, Config())]
    assert order == ["frame1.png", "frame2.png", "Frame3.png", "frame10.png", "frame100.png"]
    assert sorted(["a10b2", "a2b10", "a2b9"], key=natural_key) == ["a2b9", "a2b10", "a10b2"]


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from(["f", "F", "a_", "v2_", ""]), st.integers(0, 10**4)),
        unique=True,
        max_size=30,
    ),
    st.sampled_from([0, 3, 5]),
    st.sampled_from([".png", ".PNG", "b1.png"]),
)
def test_natural_order_is_natural_keys_order(parts, width: int, suffix: str) -> None:
    """The fast path (names differing only in equally wide numbers: plain string order)
    and the general one sort as natural_key does."""
    names = list(dict.fromkeys(f"{p}{n:0{width}d}{suffix}" for p, n in parts))
    assert [names[i] for i in natural_order(names)] == sorted(names, key=natural_key)
    same = [f"x{n:05d}.png" for _, n in parts]  # one shape: the fast path
    same = list(dict.fromkeys(same))
    assert [same[i] for i in natural_order(same)] == sorted(same, key=natural_key)


def test_folder_ignores_non_image_files_and_reads_lazily(tmp_path: Path) -> None:
    for i in range(3):
        _write(tmp_path / f"{i:03d}.png", _labels(seed=i))
    (tmp_path / "mistool.toml").write_text("fps = 10.0\n")
    (tmp_path / "truth.csv").write_text("frame,instrument,part\n")
    (tmp_path / "README").write_text("hello")
    (tmp_path / "sub").mkdir()
    _write(tmp_path / "sub" / "999.png", _labels())
    (tmp_path / "003.png").write_bytes(b"not a png at all")  # bad, but last
    seq = open_sequence(tmp_path)
    assert seq.num_frames == 4 and seq.config.fps == 10.0
    it = iter(seq)
    idx, name, labels = next(it)  # the first frame decodes though the last one is bad
    assert (idx, name) == (0, "000.png")
    np.testing.assert_array_equal(labels, _labels(seed=0))
    next(it), next(it)
    with pytest.raises(MaskFormatError, match="003.png: cannot decode"):
        next(it)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_grey_png_8_and_16_bit(tmp_path: Path, dtype: type) -> None:
    img = _labels().astype(dtype)
    if dtype is np.uint16:
        img[img == 160] = 40000
    out = read_label_image(_write(tmp_path / "a.png", img))
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, img)


def test_grey_saved_as_rgb_reads_one_channel(tmp_path: Path) -> None:
    img = _labels()
    out = read_label_image(_write(tmp_path / "a.png", cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)))
    assert out.shape == img.shape
    np.testing.assert_array_equal(out, img)


def test_colour_pixels_without_colour_config_is_an_error(tmp_path: Path) -> None:
    img = np.zeros((8, 8, 3), np.uint8)
    img[2:4, 2:4] = (0, 0, 255)
    path = _write(tmp_path / "c.png", img)
    with pytest.raises(MaskFormatError, match=r"c\.png: colour pixels"):
        read_label_image(path)


def test_colour_masks_pack_rgb(tmp_path: Path) -> None:
    cfg = config_from_dict({"parts": {"shaft": "#ff8000", "clasper": "#0000ff"}})
    assert cfg.colour_masks
    bgr = np.zeros((8, 8, 3), np.uint8)
    bgr[1, 1] = (0, 128, 255)  # BGR of #ff8000
    out = read_label_image(_write(tmp_path / "c.png", bgr), colour=True)
    assert out.dtype == np.uint32
    assert out[1, 1] == cfg.parts["shaft"][0] == 0xFF8000 and out[0, 0] == 0
    rgb = bgr[..., ::-1]  # caller arrays are RGB
    assert to_labels(rgb, "x", colour=True, order="rgb")[1, 1] == 0xFF8000


def test_palette_png_reads_indices(tmp_path: Path) -> None:
    pil = pytest.importorskip("PIL.Image")
    idx = np.zeros((10, 12), np.uint8)
    idx[2:5, 3:9] = 1
    idx[6:8, 1:4] = 2
    img = pil.fromarray(idx, mode="P")
    palette = [0, 0, 0, 200, 10, 10, 10, 200, 10] + [0] * (256 * 3 - 9)
    img.putpalette(palette)
    path = tmp_path / "p.png"
    img.save(path)
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert decoded.ndim == 3  # OpenCV expands palettes: why mistool maps them back
    out = read_label_image(path)
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, idx)


def test_arrays_source_and_dtypes() -> None:
    frames = [_labels(seed=i).astype(np.int64) for i in range(3)]
    seq = open_sequence(frames)
    got = list(seq)
    assert [g[0] for g in got] == [0, 1, 2] and seq.shape == (24, 32)
    assert got[1][2].dtype == np.uint8
    np.testing.assert_array_equal(got[2][2], frames[2])
    gen = open_sequence(f for f in frames)  # generators work too (one pass)
    assert gen.num_frames is None and len(list(gen)) == 3


def test_one_array_is_not_a_sequence() -> None:
    for one in (np.zeros((4, 5), np.uint8), np.zeros((4, 5, 3), np.uint8)):
        with pytest.raises(MaskFormatError, match="pass a list of frames"):
            open_sequence(one)
    stack = np.zeros((3, 4, 5), np.uint8)  # (N, H, W): N frames
    assert [i for i, _, _ in open_sequence(stack)] == [0, 1, 2]


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.full((4, 4), -1), "0..65535"),
        (np.full((4, 4), 0.5), "non-integer"),
        (np.zeros((4, 4, 2), np.uint8), "shape"),
    ],
)
def test_bad_arrays(bad: np.ndarray, message: str) -> None:
    with pytest.raises(MaskFormatError, match=message):
        list(open_sequence([bad]))


def test_frame_size_change_names_the_frame(tmp_path: Path) -> None:
    _write(tmp_path / "0.png", _labels())
    _write(tmp_path / "1.png", _labels(h=30))
    with pytest.raises(MaskFormatError, match=r"1\.png: frame size changed.*32x30.*32x24"):
        list(open_sequence(tmp_path))


def test_path_errors(tmp_path: Path) -> None:
    with pytest.raises(InputPathError, match="no such file or folder"):
        resolve(tmp_path / "missing")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(InputPathError, match="no label images"):
        open_sequence(tmp_path)
    (tmp_path / "Segmentation.avi").write_bytes(b"junk")
    with pytest.raises(InputPathError, match="pass the file itself"):
        open_sequence(tmp_path)
    with pytest.raises(MaskFormatError, match="Segmentation.avi: cannot read as a video"):
        open_sequence(tmp_path / "Segmentation.avi")


def test_truncated_png_is_an_error(tmp_path: Path) -> None:
    img = np.zeros((64, 64), np.uint8)
    img[::2] = 160
    data = cv2.imencode(".png", img)[1].tobytes()
    (tmp_path / "t.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(MaskFormatError, match=r"t\.png: cannot decode"):
        read_label_image(tmp_path / "t.png")


def test_mask_video_widens_single_values(tmp_path: Path) -> None:
    path = tmp_path / "Segmentation.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (64, 48), False)
    assert writer.isOpened()
    frames = []
    for i in range(4):
        img = np.zeros((48, 64), np.uint8)
        img[10:30, 5 + i : 40 + i] = 160
        img[30:40, 30:45] = 70
        frames.append(img)
        writer.write(img)
    writer.release()
    (tmp_path / "mistool.toml").write_text("[parts]\nclasper = [50, 90]\n")
    seq = open_sequence(path)
    assert seq.kind == "video" and seq.num_frames == 4
    assert seq.config.parts["shaft"] == (145, 175)  # 160 +- 15
    assert seq.config.parts["clasper"] == (50, 90)  # ranges are kept
    got = list(seq)
    assert len(got) == 4 and got[0][2].shape == (48, 64) and got[0][2].dtype == np.uint8
    inside = (got[2][2] >= 145) & (got[2][2] <= 175)
    assert np.mean(inside == (frames[2] == 160)) > 0.98  # the lossy codec smears edges


def test_widening_never_overlaps() -> None:
    cfg = config_from_dict({"labels": "endovis17"})  # 10, 20, 30
    wide = widen_for_video(cfg)
    assert wide.parts == {"shaft": (6, 14), "wrist": (16, 24), "clasper": (26, 34)}
    cfg = config_from_dict({"instrument": [{"name": "a", "shaft": 100, "clasper": 110}]})
    assert widen_for_video(cfg).instruments[0].parts == {"shaft": (96, 104), "clasper": (106, 114)}


def test_odd_folder_names(tmp_path: Path) -> None:
    folder = tmp_path / "séquence 1 (copie)"
    folder.mkdir()
    _write(folder / "0.png", _labels())  # cv2.imwrite may not handle unicode: check it
    seq = open_sequence(folder)
    assert seq.name == "séquence 1 (copie)" and len(list(seq)) == 1


def _png(rows: np.ndarray, filters: list[int], *, depth: int = 8, ctype: int = 0) -> bytes:
    """A PNG written by hand: ``rows`` are the already *filtered* bytes of each row."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    h, w = rows.shape
    raw = b"".join(bytes([f]) + rows[i].tobytes() for i, f in enumerate(filters))
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def _fast_cases() -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    cases = [
        np.zeros((5, 7), np.uint8),
        np.full((3, 4), 255, np.uint8),
        rng.integers(0, 256, (40, 33)).astype(np.uint8),  # dense: every byte a step
        np.zeros((1, 1), np.uint8),
        np.full((1, 1), 9, np.uint8),
        np.zeros((6, 1), np.uint8),
        np.arange(256, dtype=np.uint8)[None, :],
    ]
    last = np.zeros((9, 11), np.uint8)
    last[-1, -1] = 200
    cases.append(last)
    for k in range(6):  # label-like: overlapping rectangles of a few values
        img = np.zeros((57 + k, 71), np.uint8)
        for _ in range(8):
            y, x = rng.integers(0, 50), rng.integers(0, 60)
            img[y : y + rng.integers(1, 30), x : x + rng.integers(1, 40)] = rng.choice(
                [0, 1, 70, 160, 255]
            )
        cases.append(img)
    return cases


@pytest.mark.parametrize("img", _fast_cases())
def test_fast_png_decoder_matches_opencv(tmp_path: Path, img: np.ndarray) -> None:
    from mistool.pngdecode import decode_png

    data = cv2.imencode(".png", img)[1].tobytes()
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED).reshape(img.shape)
    np.testing.assert_array_equal(ref, img)
    fast = decode_png(data, 10**8)
    assert fast is not None and fast.palette is None
    assert fast.pixels.dtype == np.uint8
    np.testing.assert_array_equal(fast.pixels, img)
    pil = pytest.importorskip("PIL.Image")
    pil.fromarray(img, mode="L").save(tmp_path / "pil.png")  # other encoders, other filters
    assert decode_png((tmp_path / "pil.png").read_bytes(), 10**8) is not None
    np.testing.assert_array_equal(read_label_image(tmp_path / "pil.png"), img)


def _filter_rows(img: np.ndarray, filters: list[int], bpp: int = 1) -> np.ndarray:
    """PNG-filter each row of an image's bytes (the encoder's side, by the spec; ``bpp``:
    bytes per pixel, the distance to the byte on the left)."""
    out = np.zeros_like(img)
    a16 = img.astype(np.int16)
    for y, f in enumerate(filters):
        x = a16[y]
        up = a16[y - 1] if y else np.zeros_like(x)
        left = np.concatenate([np.zeros(bpp, np.int16), x[:-bpp]])
        ul = np.concatenate([np.zeros(bpp, np.int16), up[:-bpp]])
        if f == 0:
            pred = np.zeros_like(x)
        elif f == 1:
            pred = left
        elif f == 2:
            pred = up
        elif f == 3:
            pred = (left + up) // 2
        else:
            p = left + up - ul
            pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - ul)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, ul))
        out[y] = ((x - pred) % 256).astype(np.uint8)
    return out


@pytest.mark.parametrize("seed", range(8))
def test_fast_png_decoder_every_filter_mix(seed: int) -> None:
    from mistool.pngdecode import decode_png

    rng = np.random.default_rng(seed)
    img = _fast_cases()[8 + seed % 6]
    if seed >= 6:
        img = rng.integers(0, 256, (20, 30)).astype(np.uint8)  # noise: every byte changes
    filters = rng.choice([0, 1, 2, 3, 4], size=img.shape[0]).tolist()
    data = _png(_filter_rows(img, filters), filters)
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(ref, img)  # (the test's encoder is right)
    got = decode_png(data, 10**8)
    assert got is not None
    np.testing.assert_array_equal(got.pixels, img)
    np.testing.assert_array_equal(read_label_image_bytes(data), img)


def read_label_image_bytes(data: bytes, **kw: object) -> np.ndarray:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.png"
        path.write_bytes(data)
        return read_label_image(path, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("level", [0, 1, 3, 6, 9])
def test_libpng_adaptive_filters_decode(level: int) -> None:
    """With an explicit compression level OpenCV lets libpng pick filters per row
    (Paeth and Up rows among Sub and None: what ``mistool synth`` writes at level 3)."""
    from mistool.pngdecode import decode_png

    img = np.zeros((120, 150), np.uint8)
    pts = np.array([[10, 100], [140, 20], [148, 35], [20, 115]], np.int32)
    cv2.fillPoly(img, [pts], 160)
    cv2.circle(img, (120, 40), 15, 70, -1)
    data = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, level])[1].tobytes()
    got = decode_png(data, 10**8)
    assert got is not None
    np.testing.assert_array_equal(got.pixels, img)
    np.testing.assert_array_equal(read_label_image_bytes(data), img)


def test_fast_png_decoder_declines_what_it_does_not_handle(tmp_path: Path) -> None:
    from mistool.pngdecode import decode_png

    img = np.zeros((4, 6), np.uint8)
    img[1:3, 2:5] = 160
    sub = _filter_rows(img, [1, 1, 1, 1])
    assert decode_png(_png(sub, [1, 1, 1, 1], depth=4), 10**8) is None  # sub-byte depth
    assert decode_png(_png(sub, [1, 5, 1, 1]), 10**8) is None  # no such filter
    good = _png(sub, [1, 1, 1, 1])
    np.testing.assert_array_equal(decode_png(good, 10**8).pixels, img)  # type: ignore[union-attr]
    assert decode_png(good, 23) is None  # over max_pixels
    bad_crc = bytearray(good)
    bad_crc[-20] ^= 0xFF  # inside the IDAT chunk's data or CRC
    assert decode_png(bytes(bad_crc), 10**8) is None
    (tmp_path / "crc.png").write_bytes(bytes(bad_crc))
    with pytest.raises(MaskFormatError, match=r"crc\.png: cannot decode"):
        read_label_image(tmp_path / "crc.png")
    assert decode_png(good[:-12], 10**8) is None  # no IEND: truncated
    assert decode_png(good + b"\x00", 10**8) is None  # bytes after IEND


def test_fast_path_gate_closes_on_a_sequence_it_keeps_declining(tmp_path: Path) -> None:
    from mistool.sequence import FastPathGate

    img = _labels()
    # grey saved as RGB: left to OpenCV (the labels are the shared channel)
    path = tmp_path / "a.png"
    path.write_bytes(cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))[1])
    gate = FastPathGate(patience=3)
    for _ in range(5):
        np.testing.assert_array_equal(read_label_image(path, gate=gate), img)
    assert (gate.tried, gate.declined, gate.open) == (3, 3, False)
    ok = FastPathGate(patience=3)
    _write(tmp_path / "b.png", img)
    for _ in range(5):
        read_label_image(tmp_path / "b.png", gate=ok)
    assert (ok.tried, ok.declined, ok.open) == (5, 0, True)
    # every row filtered against the one above: the compiled pass undoes it as fast as
    # any other row, so the fast path keeps taking the frames
    paeth = [4] * img.shape[0]
    (tmp_path / "c.png").write_bytes(_png(_filter_rows(img, paeth), paeth))
    dependent = FastPathGate(patience=3)
    for _ in range(5):
        np.testing.assert_array_equal(read_label_image(tmp_path / "c.png", gate=dependent), img)
    assert (dependent.tried, dependent.declined, dependent.open) == (5, 0, True)


def test_jpeg_folder_is_lossy_like_a_video(tmp_path: Path) -> None:
    img = np.zeros((48, 64), np.uint8)
    img[10:30, 5:40] = 160
    cv2.imwrite(str(tmp_path / "0.jpg"), img)
    seq = open_sequence(tmp_path)
    assert seq.lossy and seq.config.parts["shaft"] == (145, 175)
    _write(tmp_path / "1.png", img)  # a lossless frame: values are exact again
    seq = open_sequence(tmp_path)
    assert not seq.lossy and seq.config.parts["shaft"] == (160, 160)


def test_fast_png_decoder_without_zlib_ng(monkeypatch: pytest.MonkeyPatch) -> None:
    """zlib-ng is optional: the standard library's zlib inflates the same bytes."""
    import zlib

    from mistool import pngdecode

    monkeypatch.setattr(pngdecode, "_ZLIB", zlib)
    img = _fast_cases()[9]
    for params in ([], [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        data = cv2.imencode(".png", img, params)[1].tobytes()
        np.testing.assert_array_equal(pngdecode.decode_png(data, 10**8).pixels, img)  # type: ignore[union-attr]
