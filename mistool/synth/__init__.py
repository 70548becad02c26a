"""Synthetic mask sequences with exact ground truth (``mistool synth``).

A pinhole camera looks at instruments (a cylindrical shaft pivoting about a trocar outside
the view, a wrist, two jaws) that move smoothly; every frame is ray cast exactly
(:mod:`mistool.synth.render`), optionally corrupted (:mod:`mistool.synth.corrupt`), and
written with ``mistool.toml`` and ``truth.csv`` (:mod:`mistool.synth.writer`).
"""

from mistool.synth.corrupt import Corruptions
from mistool.synth.motion import MotionOptions
from mistool.synth.render import RayCaster, RenderBuffers
from mistool.synth.scene import ImageCamera, InstrumentGeometry, InstrumentPose
from mistool.synth.writer import VIDEO_CODECS, SceneOptions, SynthResult, synthesize

__all__ = [
    "VIDEO_CODECS",
    "Corruptions",
    "ImageCamera",
    "InstrumentGeometry",
    "InstrumentPose",
    "MotionOptions",
    "RayCaster",
    "RenderBuffers",
    "SceneOptions",
    "SynthResult",
    "synthesize",
]
