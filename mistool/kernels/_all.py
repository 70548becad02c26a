"""Imports every kernel module (the worker processes' fork server preloads this, so each
worker inherits the compiled kernels instead of loading them at its first frame)."""

from __future__ import annotations

from mistool.kernels import warm

warm()
