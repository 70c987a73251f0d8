"""Synthetic cells: procedural parts, physically settled scenes, RGB-D rendering with sensor noise, BOP export.

MuJoCo's offscreen renderer needs an OpenGL backend chosen before `mujoco` is first imported; this package
defaults `MUJOCO_GL` to 'egl' (headless) when the user has not set it.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
