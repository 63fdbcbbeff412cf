"""Fig. 9-style snapshot strip of the trot (wbc_jax.analysis.video.render_strip,
wbc_jax.studies.trot_analysis): one PNG of N frames side by side at fixed times. Offscreen rendering needs an OpenGL
backend (MUJOCO_GL=egl or osmesa); where there is none the tests skip with the renderer's reason, as ``wbc-jax trot``
then leaves the picture out."""

import numpy as np
import pytest

from wbc_jax.analysis.video import render_strip
from wbc_jax.robot.model import load_mj_model
from wbc_jax.studies.trot_analysis import snapshot_times

FRAME = (60, 80)  # [px] (height, width) of one frame


@pytest.fixture(scope="module")
def flat():
    """MuJoCo C model of the flat scene and a (T, nq) log: the model's initial configuration, the trunk moving 1 cm
    forward per sample."""
    m = load_mj_model("flat")
    q = np.tile(m.qpos0, (20, 1))
    q[:, 0] += 0.01 * np.arange(20)
    return m, q, 0.005 * np.arange(20)


def test_strip_is_one_png_of_n_frames(flat, tmp_path):
    from PIL import Image

    m, q, t = flat
    path = tmp_path / "strip.png"
    why = render_strip(path, m, q, t, at=[0.0, 0.03, 0.06, 1.0], size=FRAME)  # 1.0 s: beyond the log, last sample
    if why:
        pytest.skip(why)
    img = np.asarray(Image.open(path).convert("RGB"))
    assert img.shape == (FRAME[0], 4 * FRAME[1], 3)
    frames = [img[:, k * FRAME[1]:(k + 1) * FRAME[1]] for k in range(4)]
    assert all(f.std() > 1.0 for f in frames)  # something rendered in every frame, not a blank panel


def test_strip_reason_instead_of_an_exception(flat, tmp_path):
    m, q, t = flat
    assert render_strip(tmp_path / "x.png", m, q, t, at=[]) == "no snapshots: empty log"
    assert not (tmp_path / "x.png").exists()


def test_snapshot_times_cover_one_gait_cycle():
    at = snapshot_times(0.5, 10.5, 0.25, 6)
    np.testing.assert_allclose(at, 5.5 + 0.5 * np.arange(6) / 6)  # from the step boundary at mid-walk, two steps
    at = snapshot_times(0.2, 1.2, 0.25, 4)  # a short walk: the cycle still fits before its end
    assert at[0] >= 0.2 and at[-1] < 1.2 and np.allclose(np.diff(at), 0.125)
