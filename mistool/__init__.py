"""mistool: 3D motion of surgical instruments from segmentation masks."""

__version__ = "0.1.0"
