"""Build hook: ship the bundled ``sample_masks/`` and ``web_assets/`` inside the wheel.

In a source checkout they stay at the repository root (see ``mistool/resources.py``); a
regular (non-editable) install copies them to ``mistool/_bundled/``.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildPyWithBundles(build_py):
    def run(self) -> None:
        super().run()
        root = Path(__file__).resolve().parent
        for name in ("sample_masks", "web_assets"):
            src = root / name
            if src.is_dir():
                dst = Path(self.build_lib) / "mistool" / "_bundled" / name
                shutil.copytree(src, dst, dirs_exist_ok=True)


setup(cmdclass={"build_py": BuildPyWithBundles})
