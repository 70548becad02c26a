"""mistool.toml: presets, defaults, overrides and every kind of invalid file."""

from __future__ import annotations

from pathlib import Path

import pytest

from mistool.config import PRESETS, Config, config_from_dict, load_config, pack_rgb
from mistool.errors import ConfigError


def test_presets_match_the_design() -> None:
    assert PRESETS["endovis15"] == {"shaft": 160, "clasper": 70}
    assert PRESETS["endovis17"] == {"shaft": 10, "wrist": 20, "clasper": 30}
    assert PRESETS["ternaus"] == {"shaft": 85, "wrist": 170, "clasper": 255}


def test_defaults_without_a_file(tmp_path: Path) -> None:
    cfg = load_config(tmp_path)
    assert cfg == Config()
    assert cfg.fps == 25.0 and cfg.parts == {"shaft": (160, 160), "clasper": (70, 70)}
    assert cfg.camera is None and cfg.instruments == () and not cfg.colour_masks


def test_full_file(tmp_path: Path) -> None:
    (tmp_path / "mistool.toml").write_text(
        """
fps = 30
source = "Video.avi"
labels = "endovis17"
min_area_px = 5
[parts]
clasper = [25, 35]
[camera]
fx = 580.0
fy = 581
cx = 359.5
cy = 287.5
[[instrument]]
name = "left"
shaft = 160
clasper = [60, 80]
shaft_diameter_mm = 5.0
[[instrument]]
shaft = 100
""",
        encoding="utf-8",
    )
    cfg = load_config(tmp_path)
    assert cfg.fps == 30.0 and cfg.min_area_px == 5 and cfg.labels == "endovis17"
    assert cfg.source == tmp_path / "Video.avi"  # relative to the file
    assert cfg.parts == {"shaft": (10, 10), "wrist": (20, 20), "clasper": (25, 35)}
    assert cfg.camera is not None and cfg.camera.fy == 581.0
    assert cfg.camera.K[0, 2] == 359.5
    left, second = cfg.instruments
    assert left.name == "left" and left.parts == {"shaft": (160, 160), "clasper": (60, 80)}
    assert second.name == "2"
    assert cfg.shaft_diameter_for("left") == 5.0 and cfg.shaft_diameter_for("2") == 8.0
    assert cfg.part_names() == ("shaft", "wrist", "clasper")
    assert cfg.path == tmp_path / "mistool.toml"


def test_colours_and_overrides() -> None:
    cfg = config_from_dict({"parts": {"shaft": "#A0a0a0", "clasper": "#004600"}})
    assert cfg.colour_masks and cfg.parts["shaft"] == (pack_rgb(160, 160, 160),) * 2
    assert pack_rgb(1, 2, 3) == 0x010203
    over = cfg.with_overrides(fps=50.0, min_area_px=None)
    assert over.fps == 50.0 and over.min_area_px == cfg.min_area_px


@pytest.mark.parametrize(
    "text, message",
    [
        ("fps = ", "invalid TOML"),
        ("fsp = 25.0", r"unknown key\(s\) fsp"),
        ('fps = "fast"', "fps must be a number"),
        ("fps = 0", "fps must be > 0"),
        ("fps = true", "fps must be a number"),
        ("min_area_px = -1", "min_area_px must be an integer >= 0"),
        ('labels = "endovis99"', "not a preset"),
        ("[parts]\nshaft = [200, 100]", r"reversed range; write \[100, 200\]"),
        ("[parts]\nshaft = [1, 2, 3]", "parts.shaft must be"),
        ('[parts]\nshaft = "#12345"', "not a label value"),
        ("[parts]\nshaft = 70000", "outside the label range"),
        ("[parts]\nhandle = 3", r"unknown key\(s\) in \[parts\]: handle"),
        ("[camera]\nfx = 0.0\nfy = 1.0\ncx = 0.0\ncy = 0.0", "camera.fx must be > 0"),
        ("[camera]\nfx = -5.0\nfy = 1.0\ncx = 0.0\ncy = 0.0", "camera.fx must be > 0"),
        ("[camera]\nfx = 500.0\nfy = 500.0\ncx = 1.0", r"\[camera\] is missing cy"),
        ("[camera]\nfx = 5.0\nfy = 5.0\ncx = 1.0\ncy = 1.0\nk1 = 0.1", r"unknown key\(s\) in"),
        ('[[instrument]]\nname = "a"', "gives no part values"),
        ("[[instrument]]\nshaft = 1\ncolour = 2", r"unknown key\(s\) in instrument\[0\]"),
        (
            '[[instrument]]\nname = "a"\nshaft = 1\n[[instrument]]\nname = "a"\nshaft = 2',
            "used twice",
        ),
        ("[[instrument]]\nshaft = 1\nshaft_diameter_mm = 0", "shaft_diameter_mm must be > 0"),
        ("instrument = 3", "array of tables"),
    ],
)
def test_invalid_files_name_the_file_and_the_problem(
    tmp_path: Path, text: str, message: str
) -> None:
    path = tmp_path / "mistool.toml"
    path.write_text(text + "\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=message) as info:
        load_config(tmp_path)
    assert str(info.value).startswith(str(path))
    assert "\n" not in str(info.value)
