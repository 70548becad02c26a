"""The bookmarks sidecar: schema, round trip, atomic writes, bad input, masks untouched."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from mistool.annotations import (
    Bookmark,
    add_bookmark,
    caption_at,
    default_path,
    load_annotations,
    remove_bookmark,
    save_annotations,
)
from mistool.errors import ConfigError, InputPathError


def test_round_trip_sorted_and_extra_keys_kept(tmp_path: Path) -> None:
    p = tmp_path / "annotations.json"
    assert load_annotations(p) == []  # absent: no bookmarks
    add_bookmark(p, 30, "suturing", "phase")
    items = add_bookmark(p, 5, " needle grasped ", "event")
    assert [(b.frame, b.text, b.kind) for b in items] == [
        (5, "needle grasped", "event"),
        (30, "suturing", "phase"),
    ]
    data = json.loads(p.read_text())
    assert data["mistool_annotations"] == 1
    assert data["bookmarks"][0] == {"frame": 5, "text": "needle grasped", "kind": "event"}
    data["bookmarks"][1]["author"] = "teacher"
    p.write_text(json.dumps(data))
    again = load_annotations(p)
    assert again[1].extra == {"author": "teacher"}
    save_annotations(p, again)
    assert json.loads(p.read_text())["bookmarks"][1]["author"] == "teacher"
    assert [b.frame for b in remove_bookmark(p, 0)] == [30]
    assert Bookmark(50, "x").time_s(25.0) == 2.0


def test_default_path_beside_the_sequence(tmp_path: Path) -> None:
    assert default_path(tmp_path) == tmp_path / "annotations.json"
    video = tmp_path / "Segmentation.avi"
    video.write_bytes(b"")
    assert default_path(video) == tmp_path / "Segmentation.annotations.json"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{not json", "not valid JSON"),
        ("[]", "expected an object"),
        ('{"mistool_annotations": 2, "bookmarks": []}', "version 2"),
        ('{"bookmarks": [{"frame": -1, "text": "a"}]}', r"bookmarks\[0\]: frame"),
        ('{"bookmarks": [{"frame": 1.5, "text": "a"}]}', "frame must be an integer"),
        ('{"bookmarks": [{"frame": 1, "text": ""}]}', "text must be"),
        ('{"bookmarks": [{"frame": 1, "text": "a", "kind": "x"}]}', "kind must be one of"),
        ('{"bookmarks": [3]}', "expected an object"),
    ],
)
def test_bad_files_are_one_line_errors(tmp_path: Path, content: str, message: str) -> None:
    p = tmp_path / "a.json"
    p.write_text(content)
    with pytest.raises(ConfigError, match=message) as info:
        load_annotations(p)
    assert str(p) in str(info.value) and "\n" not in str(info.value)


def test_writes_only_json_regular_files_atomically(tmp_path: Path) -> None:
    mask = tmp_path / "000000.png"
    mask.write_bytes(b"\x89PNG not really")
    with pytest.raises(InputPathError, match=r"\.json"):
        save_annotations(mask, [Bookmark(0, "x")])
    assert mask.read_bytes() == b"\x89PNG not really"
    folder = tmp_path / "dir.json"
    folder.mkdir()
    with pytest.raises(InputPathError, match="not a regular file"):
        save_annotations(folder, [])
    link = tmp_path / "link.json"
    link.symlink_to(mask)
    with pytest.raises(InputPathError, match="not a regular file"):
        save_annotations(link, [])
    assert mask.read_bytes() == b"\x89PNG not really"
    # a failure while writing leaves the old file and no temporary file behind
    p = tmp_path / "annotations.json"
    save_annotations(p, [Bookmark(1, "kept")])
    before = p.read_text()

    class Boom:
        frame = 2

        def to_json(self) -> dict:
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        save_annotations(p, [Bookmark(1, "new"), Boom()])  # type: ignore[list-item]
    assert p.read_text() == before
    assert sorted(os.listdir(tmp_path)) == sorted(
        ["000000.png", "dir.json", "link.json", "annotations.json"]
    )


def test_caption_holds_events_and_phases() -> None:
    marks = [Bookmark(10, "start", "phase"), Bookmark(20, "cut", "event")]
    assert caption_at(marks, 5, 25) is None
    assert caption_at(marks, 12, 25).text == "start"
    assert caption_at(marks, 100, 25) is None  # the event is too old
    assert caption_at(marks, 44, 25).text == "cut"
    assert caption_at([marks[0]], 1000, 25).text == "start"  # a phase holds


def test_bookmark_command(tmp_path: Path, capsys) -> None:
    from mistool.cli import main

    seq = tmp_path / "seq"
    seq.mkdir()
    png = seq / "000000.png"
    import cv2
    import numpy as np

    cv2.imwrite(str(png), np.zeros((8, 8), np.uint8))
    before = png.read_bytes()
    (seq / "mistool.toml").write_text("fps = 10.0\n")
    assert main(["bookmark", str(seq), "--add", "2.5s", "suturing", "--kind", "phase"]) == 0
    assert main(["bookmark", str(seq), "--add", "3", "cut"]) == 0
    capsys.readouterr()
    assert main(["bookmark", str(seq)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "frame      3" in lines[0] and "cut" in lines[0]
    assert "frame     25" in lines[1] and "phase" in lines[1] and "2.50 s" in lines[1]
    assert main(["bookmark", str(seq), "--remove", "0"]) == 0
    assert [b.text for b in load_annotations(seq / "annotations.json")] == ["suturing"]
    assert main(["bookmark", str(seq), "--add", "x", "y"]) == 1
    assert "--add 'x'" in capsys.readouterr().err
    assert main(["bookmark", str(seq), "--remove", "5"]) == 1
    assert png.read_bytes() == before
    assert sorted(p.name for p in seq.iterdir()) == [
        "000000.png",
        "annotations.json",
        "mistool.toml",
    ]
