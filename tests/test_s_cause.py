"""The S study's pieces without a closed loop: contact-law scene variants, common random numbers, the acceleration
decomposition and the MuJoCo C replay of the object (MuJoCo C only: no compiled rollout)."""

from __future__ import annotations

import mujoco
import numpy as np

from wbc_jax.campaign import build, spec
from wbc_jax.campaign.design import design
from wbc_jax.robot.model import load_mj_model, resolve_ids
from wbc_jax.robot.scenario import scene_variant
from wbc_jax.studies import s_cause, s_cause_replay

DT = 0.001  # [s] the scenes' timestep
STEPS = 300
REST_ACC = 0.05  # [m/s^2] a cube resting on a motionless tray: MuJoCo's soft contact settles within this


def test_scene_variant_sets_options_and_object_pairs(tmp_path):
    path = scene_variant("flat", {"cone": "elliptic", "impratio": 1.0, "iterations": 50},
                         obj_solimp=(0.9, 0.95, 0.001, 0.5, 2), out_dir=str(tmp_path))
    m = load_mj_model(path)
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 1.0 and m.opt.iterations == 50
    ids = resolve_ids(m)
    np.testing.assert_allclose(m.pair_solimp[ids.obj_pair], [[0.9, 0.95, 0.001, 0.5, 2]] * 4)
    base = load_mj_model("flat")
    np.testing.assert_array_equal(m.pair_solref, base.pair_solref)  # solref untouched


def test_contact_scene_of_a_campaign():
    plain = spec.parse_spec({"factors": dict(mu=[0.4, 0.7])}).campaign
    assert build.contact_scene(plain) == "transport"
    elliptic = spec.parse_spec({"campaign": dict(cone="elliptic", impratio=1.0),
                                "factors": dict(mu=[0.4, 0.7])}).campaign
    m = load_mj_model(build.contact_scene(elliptic))
    assert m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 1.0


def test_common_draws_share_each_repetition():
    s = spec.parse_spec({"campaign": dict(reps=2), "factors": dict(mu=[0.4, 0.7, 1.0]),
                         "perturbations": dict(object_xy_mm=3.0, base_speed_std=0.02)})
    dz = s_cause.common_draws(design(s), 2)
    np.testing.assert_array_equal(dz.seed[0::2], dz.seed[0])
    np.testing.assert_array_equal(dz.obj_dx[1::2], dz.obj_dx[1])
    assert dz.seed[0] != dz.seed[1]
    np.testing.assert_array_equal(dz.mu, [0.4, 0.4, 0.7, 0.7, 1.0, 1.0])


def test_object_acceleration_by_hand():
    qvel = np.zeros((3, 30))
    qvel[:, 24] = [0.001, 0.002, 0.003]  # the object's x velocity rises 1 mm/s per step
    acc = s_cause_replay.object_acceleration(np.zeros(30), qvel, 24, DT)
    np.testing.assert_allclose(acc[:, 0], 1.0)
    assert abs(s_cause_replay.smoothness(np.zeros(30), qvel, 24, DT) - 1.0) < 1e-9


def _resting_recording() -> s_cause.Recording:
    """The robot held at its home pose (zero velocity) with the object on the tray, as a recording."""
    from wbc_jax.robot.model import Robot

    robot = Robot("flat")
    qpos0 = robot.home_qpos(0.08)
    nv, nu = robot.mj_model.nv, robot.mj_model.nu
    dz = s_cause.common_draws(design(spec.parse_spec({"campaign": dict(reps=1, scene="flat"),
                                                      "factors": dict(mu=[0.4, 0.7])})), 1)
    return s_cause.Recording(t=DT * np.arange(1, STEPS + 1), dt=DT, qpos0=np.stack([qpos0] * 2),
                             qvel0=np.zeros((2, nv)), qpos=np.tile(qpos0, (2, STEPS, 1)),
                             qvel=np.zeros((2, STEPS, nv)), tau=np.zeros((2, STEPS, nu)),
                             f_obj=np.zeros((2, STEPS, 4, 3)), design=dz, scene=str(robot.path))


def test_replay_keeps_the_robot_and_lets_the_object_rest(tmp_path):
    rec = _resting_recording()
    qvel = s_cause_replay.replay_object(rec, 0)
    ids = resolve_ids(load_mj_model("flat"))
    acc = s_cause_replay.object_acceleration(rec.qvel0[0], qvel, ids.obj_dof_adr, DT)
    assert np.all(np.linalg.norm(acc[STEPS // 2:], axis=1) < REST_ACC)
    a = ids.obj_dof_adr
    with_object = rec.qvel.copy()
    with_object[:, :, a:a + 6] = qvel[None, :, a:a + 6]
    rec = rec._replace(qvel=with_object)
    parts = s_cause_replay.decompose(rec, 0, walk_start_s=0.1)["walking"]
    assert parts.tray == 0.0  # the robot's recorded state does not move
    assert abs(parts.relative - parts.total) < 1e-12
    assert parts.total <= parts.normal + parts.tangential + 1e-12
    path = tmp_path / "rec.npz"
    s_cause.save(rec, str(path))
    back = s_cause.load(str(path))
    np.testing.assert_array_equal(back.qvel, rec.qvel)
    np.testing.assert_array_equal(back.design.mu, rec.design.mu)
