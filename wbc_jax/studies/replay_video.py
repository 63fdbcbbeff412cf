"""A replayed run's video: the logged configurations rendered offscreen with MuJoCo, as MP4 (ffmpeg) or GIF.

Every logged sample in the window is one frame (the log's rate: one frame per ``Sim.log_every`` control steps),
played at that rate, each labelled with its simulated time and, from the failure instant on, the failure reason.
Rendering needs an OpenGL backend (``MUJOCO_GL=egl`` or ``osmesa`` on a headless machine); without one, or
without frames in the window, no video is written and the reason is returned.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import mujoco
import numpy as np

FRAME_SIZE = (360, 640)  # (height, width) [px], both even (the MP4 encoder's chroma subsampling)
CAMERA = dict(distance=2.2, azimuth=150.0, elevation=-20.0)  # tracking camera [m, deg, deg]


def _frames(mj_model: mujoco.MjModel, qpos: np.ndarray, times: np.ndarray, labels: list[str], track_body: int):
    """RGB frames (H, W, 3) uint8 of the configurations ``qpos`` (F, nq), each labelled; raises where MuJoCo has no
    OpenGL context."""
    from PIL import Image, ImageDraw

    renderer = mujoco.Renderer(mj_model, *FRAME_SIZE)
    cam = mujoco.MjvCamera()
    cam.type, cam.trackbodyid = mujoco.mjtCamera.mjCAMERA_TRACKING, track_body
    cam.distance, cam.azimuth, cam.elevation = CAMERA["distance"], CAMERA["azimuth"], CAMERA["elevation"]
    data = mujoco.MjData(mj_model)
    frames = []
    try:
        for q, t, label in zip(qpos, times, labels):
            data.qpos[:] = q
            mujoco.mj_forward(mj_model, data)
            renderer.update_scene(data, camera=cam)
            image = Image.fromarray(renderer.render())
            ImageDraw.Draw(image).text((8, 6), f"t = {t:.3f} s  {label}", fill=(255, 255, 255))
            frames.append(np.asarray(image))
    finally:
        renderer.close()
    return frames


def _write_mp4(path: Path, frames: list, fps: float) -> str | None:
    """H.264 MP4 through ffmpeg's stdin; None on success, else ffmpeg's last line."""
    h, w = frames[0].shape[:2]
    cmd = ["ffmpeg", "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
           "-r", f"{fps:g}", "-i", "-", "-pix_fmt", "yuv420p", "-movflags", "+faststart", str(path)]
    proc = subprocess.run(cmd, input=b"".join(f.tobytes() for f in frames), capture_output=True)
    if proc.returncode != 0:
        path.unlink(missing_ok=True)
        return (proc.stderr.decode(errors="replace").strip().splitlines() or ["ffmpeg failed"])[-1]
    return None


def write_video(folder: Path, mj_model: mujoco.MjModel, qpos: np.ndarray, times: np.ndarray, window,
                failure: tuple[float, str], track_body: int) -> tuple[str | None, str]:
    """Render the samples of ``qpos`` (T, nq) at ``times`` (T,) [s] inside ``window`` (start, end) [s] into
    ``folder/video.mp4`` (where ffmpeg is on the PATH and encodes it) or else ``folder/video.gif``.

    Args:
        mj_model: the run's MuJoCo C model (its factor values applied).
        failure: (instant [s], NaN for none; reason), written on the frames from that instant on.
        track_body: the body the camera follows.

    Returns:
        (the file's name, "") or (None, a one-line reason no video was written).
    """
    keep = (times >= window[0] - 1e-9) & (times <= window[1] + 1e-9)
    if not keep.any():
        return None, f"no video: no logged sample in the window {window[0]:g}-{window[1]:g} s"
    at, reason = failure
    labels = [f"failed: {reason}" if np.isfinite(at) and t >= at else "" for t in times[keep]]
    try:
        frames = _frames(mj_model, qpos[keep], times[keep], labels, track_body)
    except Exception as e:  # noqa: BLE001  (no OpenGL backend: MuJoCo raises various types)
        return None, (f"no video: offscreen rendering unavailable ({type(e).__name__}: {e}); set MUJOCO_GL=egl or "
                      "osmesa")
    fps = 1.0 / float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    why = "ffmpeg not found"
    if shutil.which("ffmpeg"):
        why = _write_mp4(folder / "video.mp4", frames, fps)
        if why is None:
            return "video.mp4", ""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    images[0].save(folder / "video.gif", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return "video.gif", f"GIF instead of MP4: {why}"
