"""Render one frame of the obstacle course (robot at its home pose, cube on the tray) to a PNG.

    MUJOCO_GL=egl python examples/render_course.py [OUT.png]

Needs an offscreen OpenGL backend (EGL, or ``MUJOCO_GL=osmesa``); the README's picture is made by this script.
"""

import sys

import mujoco
from PIL import Image

from wbc_jax.robot.model import Robot

out = sys.argv[1] if len(sys.argv) > 1 else "docs/img/course.png"
robot = Robot("transport")
m = robot.mj_model
d = mujoco.MjData(m)
d.qpos[:] = robot.home_qpos()
mujoco.mj_forward(m, d)
cam = mujoco.MjvCamera()
cam.type = mujoco.mjtCamera.mjCAMERA_FREE
cam.lookat[:] = (0.0, -1.5, 0.3)  # the middle of the course: blocks 1-2, the wall's gap beyond them
cam.distance, cam.azimuth, cam.elevation = 3.6, 30.0, -20.0
with mujoco.Renderer(m, 360, 640) as renderer:
    renderer.update_scene(d, camera=cam)
    Image.fromarray(renderer.render()).save(out, optimize=True)
print(f"wrote {out}")
