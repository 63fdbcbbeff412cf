"""The rollout's static configuration: :class:`Sim` (frozen, hashed by value: the key of the compiled programs)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from wbc_jax.physics import contacts
from wbc_jax.robot.model import Robot
from wbc_jax.rollout.controllers import controller_class
from wbc_jax.rollout.controllers import plugin as plugins
from wbc_jax.runtime.static import ByValue

SENSING = ("auto", "exact", "delayed")
"""What the controller reads on the Warp backend (:func:`resolve_sensing`; "auto": "delayed" on Warp with one physics
step per control step, else "exact"). "exact": Warp's position and velocity stages (``sense``) give the controller the
kinematics, mass matrix, bias forces and contacts of the current state before it acts, and the step after it skips them
(two Warp calls per control step, one forward pass). "delayed": no such call; the controller reads the fields Warp's
``step`` left, which belong to the state at the start of that step, so the controller sees the state one physics step
(1 ms) old and its torques act on the current one; control-rate metrics and the log are taken at that (consistent) older
state; with sensor noise, the noise reaches the velocities the controller reads but not its bias forces (computed by the
step with the true velocities)."""
MONITORS = ("all", "no_clearance", "finite_only")  # Sim.monitors: what the rollout measures besides the physics


def resolve_sensing(sensing: str, backend: str, n_substeps: int = 1) -> str:
    """``sensing`` (:data:`SENSING`) for a resolved physics ``backend``: "auto" -> "delayed" on Warp with one
    physics step per control step (the same campaign outcome, one Warp call fewer per step), else "exact".

    Raises:
        ValueError: an unknown value, or "delayed" where it saves nothing.
    """
    if sensing not in SENSING:
        raise ValueError(f"sensing = {sensing!r}: expected one of {', '.join(SENSING)}")
    if sensing == "auto":
        return "delayed" if backend == "warp" and n_substeps == 1 else "exact"
    if sensing == "delayed" and (backend != "warp" or n_substeps != 1):
        raise ValueError(f"sensing = 'delayed' needs the Warp backend and one physics step per control step (got "
                         f"backend {backend!r}, {n_substeps} substeps): it drops Warp's sensing call, which the "
                         f"JAX backend does not make")
    return sensing


@dataclass(frozen=True, eq=False)
class Sim(ByValue):
    """Static rollout structure: the robot, the controller (:mod:`wbc_jax.rollout.controllers`), physics substeps
    and contact indices.

    Compared and hashed by value (:class:`wbc_jax.runtime.static.ByValue`): equal Sims share compiled programs.
    The ``*_slots`` fields index MJX contact slots on the JAX backend and contact-sensor addresses in ``sensordata``
    on Warp (``wbc_jax.physics.contacts``, whose readers take the Sim); ``nonfoot_geoms`` names each non-foot entry.
    """

    robot: Robot
    controller: object  # a wbc_jax.rollout.controllers.Controller (its settings: .cfg)
    n_substeps: int
    log_every: int
    nonfoot_slots: np.ndarray
    nonfoot_geoms: np.ndarray  # (len(nonfoot_slots), 2) geom ids of each non-foot slot's pair (robot part, ground)
    wall_slots: np.ndarray
    foot_slots: np.ndarray
    obj_slots: np.ndarray
    sensor_noise: bool = False  # the controller sees qvel + noise (Push.qvel_noise_std); costs a velocity pass
    sensing: str = "exact"  # "exact" (Warp: a sensing call before the controller) or "delayed" (:data:`SENSING`)
    monitors: str = "all"  # :data:`MONITORS`: "all" (every run); "no_clearance" (clearance +inf) and "finite_only"
    #                        (physics-rate monitors zero but `finite`, control-rate metrics only counted) exist for
    #                        `bench rollout --campaign`, which times what the monitors cost

    @property
    def cfg(self):
        """The controller's static settings."""
        return self.controller.cfg

    @property
    def exportable(self) -> bool:
        """Its programs may be kept on disk as exported programs (:mod:`wbc_jax.runtime.aot`): the JAX physics (MuJoCo
        Warp's kernels are FFI calls registered per process) and a controller of the package (a plug-in's sources
        are not in that cache's key)."""
        return self.robot.backend != "warp" and plugins.built_in(self.controller)

    @property
    def dt_control(self) -> float:
        """Control period [s] (= n_substeps x dt_physics)."""
        return self.cfg.dt

    @property
    def dt_physics(self) -> float:
        """Physics timestep [s] (the model's ``opt.timestep``)."""
        return float(self.robot.mj_model.opt.timestep)


def make_sim(robot: Robot, cfg=None, n_substeps: int = 1, log_every: int = 20, sensor_noise: bool = False,
             sensing: str = "exact", controller: str = "transport", plugin: tuple = ()) -> Sim:
    """The Sim of ``robot``.

    Args:
        robot: the scene. cfg: the controller's settings; ``cfg.dt`` (the control period [s]) must equal
            ``n_substeps`` x the model's timestep; None: default settings with that period.
        n_substeps: physics steps per control step (>= 1). log_every: control steps per logged row.
        sensor_noise: the controller sees noisy velocities (``Push.qvel_noise_std``).
        sensing: :data:`SENSING` (:func:`resolve_sensing`).
        controller: the controller's name (:data:`wbc_jax.rollout.controllers.CONTROLLERS`).
        plugin: ``()`` or (``"module:Class"``, ((field, value), ...)): a plug-in subclass of that controller with
            its own fields set (:mod:`wbc_jax.rollout.controllers.plugin`).

    Raises:
        ValueError: ``n_substeps`` < 1, a control period that is not ``n_substeps`` physics steps, or a sensing
            mode the backend does not support, a plug-in that does not load.
    """
    h = float(robot.mj_model.opt.timestep)
    n_substeps = int(n_substeps)
    if n_substeps < 1:
        raise ValueError(f"n_substeps = {n_substeps}: expected >= 1")
    sensing = resolve_sensing(sensing, robot.backend, n_substeps)
    kind = controller_class(controller, plugin[0] if plugin else "")
    plug_in = kind.default(h * n_substeps) if cfg is None else kind(cfg)
    if plugin:
        plug_in = dataclasses.replace(plug_in, **dict(plugin[1]))
    cfg = plug_in.cfg
    if abs(cfg.dt - h * n_substeps) > 1e-9 * h:
        raise ValueError(f"control period cfg.dt = {cfg.dt} s != n_substeps ({n_substeps}) x the model's timestep "
                         f"({h} s)")
    idx = contacts.sim_indices(robot)
    return Sim(robot=robot, controller=plug_in, n_substeps=n_substeps, log_every=log_every, nonfoot_slots=idx.nonfoot,
               nonfoot_geoms=idx.nonfoot_geoms, wall_slots=idx.wall, foot_slots=idx.foot, obj_slots=idx.obj,
               sensor_noise=sensor_noise, sensing=sensing)
