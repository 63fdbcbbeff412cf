"""Render a logged run to an animated GIF with MuJoCo's offscreen renderer.

The rollout logs the full configuration (``Log.qpos``) every ``log_every`` steps; this replays it in
MuJoCo C (kinematics only) and writes the frames with Pillow (a matplotlib dependency). Offscreen
rendering needs an OpenGL backend (``MUJOCO_GL=egl`` on a headless machine with a GPU driver, or
``osmesa``); without one :func:`render_gif` returns a reason instead of raising, so a headless run
still writes its other outputs.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np


def _tracking_camera(m: mujoco.MjModel, body: int) -> mujoco.MjvCamera:
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    cam.trackbodyid = body
    cam.distance, cam.azimuth, cam.elevation = 2.6, 150.0, -20.0
    return cam


def render_gif(path, mj_model: mujoco.MjModel, qpos: np.ndarray, times: np.ndarray, fps: float = 12.5,
               size=(320, 480), track_body: int = 1) -> str | None:
    """Write an animated GIF of a logged trajectory.

    Args:
        path: output .gif path; mj_model: the run's MuJoCo C model (factor values applied).
        qpos: (T, nq) logged configurations; times: (T,) their times [s].
        fps: frame rate of the GIF (frames are picked from the log at this rate).
        size: (height, width) [px]; track_body: body the camera follows.

    Returns:
        None on success, else a one-line reason why no video was written.
    """
    try:
        from PIL import Image

        renderer = mujoco.Renderer(mj_model, size[0], size[1])
    except Exception as e:  # no OpenGL backend on this machine
        return f"no video: offscreen rendering unavailable ({type(e).__name__}: {e})"
    d = mujoco.MjData(mj_model)
    cam = _tracking_camera(mj_model, track_body)
    idx = np.unique(np.searchsorted(times, np.arange(times[0], times[-1], 1.0 / fps)))
    frames = []
    for i in idx:
        d.qpos[:] = qpos[i]
        mujoco.mj_forward(mj_model, d)
        renderer.update_scene(d, camera=cam)
        frames.append(Image.fromarray(renderer.render()))
    renderer.close()
    if not frames:
        return "no video: empty log"
    frames[0].save(Path(path), save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return None
