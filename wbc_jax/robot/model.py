"""Scene loading and static ids of the legged manipulator.

One :class:`Robot` is built once per process (it is not a pytree): it holds the MuJoCo C
model, its MJX twin and every static index the controllers, metrics and tests need. Ids are
plain Python ints / numpy int arrays so they stay static under ``jax.jit``. Robots compare and hash by value
(backend and compiled model), so caches of compiled programs key on them.

Conventions (see ``mjcf/legged_manipulator.xml``):
    * generalized velocities: ``qvel[0:6]`` floating base (world linear, body-frame angular, MuJoCo
      free-joint convention), ``qvel[6:24]`` the 18 actuated joints (12 leg joints FL, FR, BL, BR x
      [roll, pitch, knee], then 6 arm joints), ``qvel[24:30]`` the object's free joint.
    * feet order FL, FR, BL, BR everywhere.
"""

from __future__ import annotations

import os
from pathlib import Path

import mujoco
import numpy as np

from wbc_jax.errors import SceneError
from wbc_jax.physics.backend import mjx, put_model  # noqa: F401  (mjx re-exported: the package's one quiet import)
from wbc_jax.robot.sensors import with_contact_sensors
from wbc_jax.runtime.aot import model_digest
from wbc_jax.types import RobotIds

FEET = ("FL", "FR", "BL", "BR")
LEG_JOINTS = ("roll", "pitch", "knee")
ARM_JOINTS = tuple(f"arm_j{i}" for i in range(1, 7))
N_OBJ_CONTACTS = 4
SCENES = {"flat": "scene_flat.xml", "transport": "scene_transport.xml"}


def mjcf_dir() -> Path:
    """Folder holding the MJCF files (``$WBC_JAX_MJCF`` overrides the repository's ``mjcf/``)."""
    env = os.environ.get("WBC_JAX_MJCF")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "mjcf"


def scene_path(scene: str | os.PathLike) -> Path:
    """Resolve a scene name ('flat', 'transport') or an XML path; raise SceneError if missing."""
    s = str(scene)
    path = mjcf_dir() / SCENES[s] if s in SCENES else Path(s)
    if not path.is_file():
        raise SceneError(
            f"scene {s!r}: no such file {path} (expected one of {sorted(SCENES)} or a path to an MJCF file)"
        )
    return path


def load_mj_model(scene: str | os.PathLike) -> mujoco.MjModel:
    """Compile a scene into a MuJoCo C model; raise SceneError on a missing or invalid file."""
    path = scene_path(scene)
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:  # MuJoCo's XML/compile errors
        raise SceneError(f"scene {path}: MuJoCo could not compile it: {e}".replace("\n", " ")) from None


def _id(m: mujoco.MjModel, obj: mujoco.mjtObj, name: str, path: str) -> int:
    i = mujoco.mj_name2id(m, obj, name)
    if i < 0:
        raise SceneError(f"scene {path}: missing {obj.name[6:].lower()} {name!r}")
    return int(i)


def resolve_ids(m: mujoco.MjModel, path: str = "<model>") -> RobotIds:
    """Find every static id wbc_jax needs in a compiled scene."""
    G, B, S, P = (mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_SITE,
                  mujoco.mjtObj.mjOBJ_PAIR)
    foot_geom = np.array([_id(m, G, f"{f}_foot", path) for f in FEET])
    foot_site = np.array([_id(m, S, f"{f}_foot", path) for f in FEET])
    foot_body = m.geom_bodyid[foot_geom].astype(int)
    tray_geom = _id(m, G, "tray", path)
    floor = _id(m, G, "floor", path)

    act_joint = m.actuator_trnid[:, 0]
    if m.nu != 18:
        raise SceneError(f"scene {path}: expected 18 actuators, found {m.nu}")
    act_dof = m.jnt_dofadr[act_joint].astype(int)
    act_qpos = m.jnt_qposadr[act_joint].astype(int)
    tau_max = np.abs(m.actuator_ctrlrange[:, 1]).astype(float)

    obj_body = mujoco.mj_name2id(m, B, "object")
    if obj_body >= 0:
        obj_c = np.array([_id(m, G, f"obj_c{i}", path) for i in range(N_OBJ_CONTACTS)])
        obj_pair = np.array([_id(m, P, f"obj_c{i}_tray", path) for i in range(N_OBJ_CONTACTS)])
        obj_box = _id(m, G, "object", path)
        jnt = m.body_jntadr[obj_body]
        obj_qpos, obj_dof = int(m.jnt_qposadr[jnt]), int(m.jnt_dofadr[jnt])
        r_s = float(m.geom_size[obj_c[0], 0])
    else:
        obj_c = obj_pair = np.zeros(0, int)
        obj_box, obj_qpos, obj_dof, r_s = -1, -1, -1, 0.0

    g1, g2 = m.pair_geom1, m.pair_geom2
    foot_pair = np.array([np.where((g1 == fg) | (g2 == fg))[0] for fg in foot_geom])
    # ground: the floor and whatever the feet may stand on (the other geom of each foot pair)
    ground = np.unique(np.concatenate([[floor], np.where(np.isin(g1[foot_pair], foot_geom), g2[foot_pair],
                                                         g1[foot_pair]).ravel()]))
    on_ground = np.isin(g1, ground) | np.isin(g2, ground)
    other = np.where(np.isin(g1, ground), g2, g1)
    nonfoot = np.where(on_ground & ~np.isin(other, foot_geom) & (m.geom_bodyid[other] != obj_body))[0]
    wall_geoms = [i for i in range(m.ngeom) if (m.geom(i).name or "").startswith("wall")]
    wall_pair = np.where(np.isin(g1, wall_geoms) | np.isin(g2, wall_geoms))[0]

    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "home")
    if key < 0:
        raise SceneError(f"scene {path}: missing keyframe 'home'")
    return RobotIds(
        trunk_body=_id(m, B, "trunk", path), foot_geom=foot_geom, foot_site=foot_site,
        foot_body=foot_body, foot_radius=float(m.geom_size[foot_geom[0], 0]),
        tray_body=int(m.geom_bodyid[tray_geom]), tray_geom=tray_geom, tray_site=_id(m, S, "tray_top", path),
        tray_half=m.geom_size[tray_geom].copy(), obj_body=int(obj_body), obj_box_geom=obj_box,
        obj_contact_geom=obj_c, obj_pair=obj_pair, obj_sphere_radius=r_s, obj_qpos_adr=obj_qpos,
        obj_dof_adr=obj_dof, act_dof=act_dof, act_qpos=act_qpos, tau_max=tau_max,
        nv_robot=int(obj_dof) if obj_dof >= 0 else int(m.nv), floor_geom=floor,
        nonfoot_floor_pair=nonfoot, foot_pair=foot_pair, wall_pair=wall_pair, key_home=int(key),
    )


class Robot:
    """A compiled scene, its MJX model and static ids (one-time setup, not a pytree).

    Args:
        scene: 'flat', 'transport' or a path to a scene XML.
        backend: MJX implementation of the physics, "jax" or "warp" (:mod:`wbc_jax.physics.backend`; resolve "auto"
            before). With "warp" the scene gets the contact sensors the rollout reads
            (:func:`wbc_jax.robot.sensors.with_contact_sensors`); the physics is the same model's, box-box pairs on
            MuJoCo Warp's box_box primitive.
        solver_iterations: MuJoCo constraint-solver iterations per physics step (``opt.iterations``); 0: the
            scene's own value.
    """

    def __init__(self, scene: str | os.PathLike = "flat", backend: str = "jax", solver_iterations: int = 0):
        import jax

        if backend not in ("jax", "warp"):
            raise ValueError(f"backend {backend!r}: expected 'jax' or 'warp'")
        self.path = scene_path(scene)
        self.backend = backend
        base = load_mj_model(self.path)
        if solver_iterations:
            base.opt.iterations = int(solver_iterations)
        self.ids = resolve_ids(base, str(self.path))
        if backend == "warp":
            import warp

            warp.config.quiet = True  # no banner or per-kernel-module load lines on the console
            self.mj_model, self.sensors = with_contact_sensors(self.path, base, self.ids)
            self.mj_model.opt.iterations = base.opt.iterations
            # on this process's device: MJX's default, jax.devices()[0], is process 0's in a multi-process run
            self.mjx_model = put_model(self.mj_model, "warp", jax.local_devices()[0])
        else:
            self.mj_model, self.sensors = base, None
            self.mjx_model = put_model(self.mj_model, "jax", jax.local_devices()[0])
        self.total_robot_mass = float(self.mj_model.body_subtreemass[self.ids.trunk_body])
        self.key = (backend, model_digest(self.mj_model))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Robot) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)

    def home_qpos(self, d: float | None = None) -> np.ndarray:
        """Home configuration (nq,) with the object (side d [m]) resting centred on the tray."""
        m, ids = self.mj_model, self.ids
        data = mujoco.MjData(m)
        mujoco.mj_resetDataKeyframe(m, data, ids.key_home)
        mujoco.mj_kinematics(m, data)
        qpos = data.qpos.copy()
        if ids.has_object:
            side = float(m.geom_size[ids.obj_box_geom, 0] * 2) if d is None else float(d)
            top = data.site_xpos[ids.tray_site]
            R = data.site_xmat[ids.tray_site].reshape(3, 3)
            a = ids.obj_qpos_adr
            qpos[a : a + 3] = top + R[:, 2] * (side / 2)
            q = np.zeros(4)
            mujoco.mju_mat2Quat(q, R.flatten())
            qpos[a + 3 : a + 7] = q
        return qpos
