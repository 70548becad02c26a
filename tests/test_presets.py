"""Label presets: the endovis18 colour preset, and the hint naming a preset when a
sequence's values are exactly a preset's."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.api import track
from mistool.cli import main
from mistool.config import PRESETS, load_config, matching_preset
from mistool.synth import synthesize

# EndoVis'18 colours as RGB, written independently of mistool's preset table
E18 = {"shaft": (0, 255, 0), "clasper": (0, 255, 255), "wrist": (125, 255, 12)}
E17 = PRESETS["endovis17"]


@pytest.fixture(scope="module")
def grey17(tmp_path_factory):
    """A short EndoVis'17-valued (10/20/30) sequence with a wrist, and its truth."""
    out = tmp_path_factory.mktemp("presets") / "grey"
    return synthesize(out, frames=8, instruments=2, seed=2, preset="endovis17")


def _recolour(src: Path, dst: Path, toml: str) -> None:
    """The same masks as EndoVis'18 colour PNGs (RGB), with the given mistool.toml."""
    dst.mkdir()
    for f in sorted(src.glob("*.png")):
        grey = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        rgb = np.zeros((*grey.shape, 3), np.uint8)
        for part, colour in E18.items():
            rgb[grey == E17[part]] = colour
        cv2.imwrite(str(dst / f.name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (dst / "mistool.toml").write_text(toml, encoding="utf-8")


def test_endovis18_colour_preset_tracks_like_the_grey_masks(grey17, tmp_path):
    camera = (grey17.path / "mistool.toml").read_text(encoding="utf-8").split("[camera]")[1]
    colour = tmp_path / "colour"
    _recolour(
        grey17.path, colour, 'labels = "endovis18"\nclasper_length_mm = 16.0\n[camera]' + camera
    )
    cfg = load_config(colour)
    assert cfg.colour_masks and cfg.parts["wrist"] == (0x7DFF0C, 0x7DFF0C)
    ref, got = track(grey17.path), track(colour)
    assert got.num_rows == ref.num_rows > 0
    assert set(got["part"].tolist()) == {"shaft", "wrist", "clasper"}
    for c in ("cx_px", "cy_px", "length_px", "angle_deg", "end_x_mm", "end_z_mm"):
        np.testing.assert_array_equal(got[c], ref[c])
    # --labels endovis18 on the command line reads the colours too
    (colour / "mistool.toml").write_text("[camera]" + camera, encoding="utf-8")
    out = tmp_path / "m.csv"
    assert main(["track", str(colour), "-o", str(out), "--labels", "endovis18", "-q"]) == 0


def test_preset_hint_for_grey_values(grey17, tmp_path, capsys):
    """Masks valued 10/20/30 with no mistool.toml: the warning names endovis17."""
    bare = tmp_path / "bare"
    bare.mkdir()
    for f in grey17.path.glob("*.png"):
        shutil.copy(f, bare / f.name)
    assert main(["track", str(bare), "-o", str(tmp_path / "m.csv")]) == 0
    err = capsys.readouterr().err
    assert "10, 20, 30" in err and 'set labels = "endovis17"' in err


def test_preset_hint_for_colour_masks(grey17, tmp_path, capsys):
    """EndoVis'18 colour masks read with grey settings: the one-line error names endovis18."""
    colour = tmp_path / "colour"
    _recolour(grey17.path, colour, "fps = 2.0\n")
    assert main(["track", str(colour), "-o", str(tmp_path / "m.csv")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mistool: error: ") and err.count("\n") == 1
    assert 'set labels = "endovis18"' in err


@pytest.mark.parametrize(
    "values,colour,expected",
    [
        ([10, 20, 30], False, "endovis17"),
        ([0, 10, 30, 99], False, "endovis17"),
        ([160, 70], False, "endovis15"),
        ([85, 170, 255], False, "ternaus"),
        ([10], False, None),  # one value says nothing
        ([5, 6, 7], False, None),
        ([0x00FF00, 0x00FFFF], True, "endovis18"),
        ([0x00FF00, 0x00FFFF], False, None),
        ([10, 20, 30], True, None),
    ],
)
def test_matching_preset(values, colour, expected):
    assert matching_preset(values, colour) == expected
