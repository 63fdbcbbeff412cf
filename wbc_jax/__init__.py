"""wbc_jax: batched whole-body control of legged manipulators in MuJoCo MJX."""

import os as _os

# Offscreen rendering (wbc_jax.analysis.video) on a headless machine: MuJoCo picks its OpenGL backend when it is
# first imported, so the default has to be set before that. An explicit MUJOCO_GL always wins.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "egl"

__version__ = "0.1.0"
