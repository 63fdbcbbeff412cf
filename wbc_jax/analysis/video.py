"""Render a logged run with MuJoCo's offscreen renderer: an animated GIF, or a strip of snapshots.

The rollouts log the full configuration (``qpos``) every ``log_every`` steps; this replays it in
MuJoCo C (kinematics only) and writes the frames with Pillow (a matplotlib dependency). Offscreen
rendering needs an OpenGL backend (``MUJOCO_GL=egl`` on a headless machine with a GPU driver, or
``osmesa``); without one :func:`render_gif` and :func:`render_strip` return a reason instead of raising,
so a headless run still writes its other outputs.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np


def _tracking_camera(m: mujoco.MjModel, body: int, distance: float = 2.6, azimuth: float = 150.0,
                     elevation: float = -20.0) -> mujoco.MjvCamera:
    """A camera following ``body``; azimuth and elevation [deg] as MuJoCo's (azimuth: the direction it looks in)."""
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    cam.trackbodyid = body
    cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
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


def render_strip(path, mj_model: mujoco.MjModel, qpos: np.ndarray, times: np.ndarray, at, size=(240, 320),
                 track_body: int = 1, azimuth: float = 150.0, elevation: float = -15.0, distance: float = 1.8,
                 label: bool = True) -> str | None:
    """Write one PNG of N snapshots side by side (the centroidal paper's Fig. 9: the robot trotting).

    Args:
        path: output .png path; mj_model: the run's MuJoCo C model.
        qpos: (T, nq) logged configurations; times: (T,) their times [s], increasing.
        at: (N,) snapshot times [s]; each frame is the first logged sample at or after its time (the last sample
            for a time beyond the log).
        size: (height, width) of one frame [px]; the PNG is height x (N width).
        track_body, azimuth, elevation, distance: the camera follows this body from this direction [deg] and
            distance [m].
        label: print each frame's time in its top-left corner.

    Returns:
        None on success, else a one-line reason why no picture was written.
    """
    at = np.atleast_1d(np.asarray(at, float))
    if at.size == 0 or len(times) == 0:
        return "no snapshots: empty log"
    try:
        from PIL import Image, ImageDraw

        renderer = mujoco.Renderer(mj_model, size[0], size[1])
    except Exception as e:  # no OpenGL backend on this machine
        return f"no snapshots: offscreen rendering unavailable ({type(e).__name__}: {e})"
    d = mujoco.MjData(mj_model)
    cam = _tracking_camera(mj_model, track_body, distance, azimuth, elevation)
    idx = np.minimum(np.searchsorted(np.asarray(times), at - 1e-9), len(times) - 1)
    strip = Image.new("RGB", (size[1] * len(idx), size[0]), "white")
    try:
        for j, i in enumerate(idx):
            d.qpos[:] = qpos[i]
            mujoco.mj_forward(mj_model, d)
            renderer.update_scene(d, camera=cam)
            frame = Image.fromarray(renderer.render())
            if label:
                ImageDraw.Draw(frame).text((6, 4), f"t = {float(times[i]):.2f} s", fill=(255, 255, 255))
            strip.paste(frame, (j * size[1], 0))
    finally:
        renderer.close()
    strip.save(Path(path))
    return None
