"""Transport whole-body controller (transport paper, Sec. IV-C), in JAX: one control step is the momentum
observer's update, the QP of :mod:`wbc_jax.control.transport_qp` (eqs. (7)-(14)) solved warm-started by
:func:`wbc_jax.qp.solve_qp`, and the torques of its solution (Sec. IV-C-4), which drive the motors directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.control.transport_qp import (
    N_EQ_ROWS,
    N_FEET,
    N_OBJ,
    TransportGains,
    TransportQP,
    build_qp,
    default_gains,
    planned_object_forces,
)
from wbc_jax.control.variants import FULL, Variant
from wbc_jax.qp import QPResult, QPSettings, empty_factors, last_usable, solve_qp
from wbc_jax.qp.api import resolve_settings
from wbc_jax.spatial import GRAVITY, full_precision
from wbc_jax.types import DynTerms, ObjectModel, Observation, Reference, RobotIds

__all__ = [
    "N_EQ_ROWS",
    "N_FEET",
    "N_OBJ",
    "ControlState",
    "ObserverState",
    "QPDiag",
    "TransportConfig",
    "TransportGains",
    "TransportQP",
    "assemble",
    "build_qp",
    "control_qp_settings",
    "default_gains",
    "init_control_state",
    "observer_update",
    "planned_object_forces",
    "transport_control",
]


class ObserverState(NamedTuple):
    """First-order centroidal momentum observer ([33]): r = K_O (h_G - h_G0 - int(W + m g + r) dt).

    Attributes: h0 (6,) initial momentum; integral (6,); r (6,) estimated external wrench about the
    CoM [N, N m]; w_cmd (6,) last commanded net contact wrench about the CoM.
    """

    h0: jax.Array
    integral: jax.Array
    r: jax.Array
    w_cmd: jax.Array


class ControlState(NamedTuple):
    """Controller memory between steps: warm start, observer, the arm's nominal posture q_post (6,)
    [rad] (its configuration at the start), and the run's ablation switches (:mod:`wbc_jax.control.variants`;
    data, constant over the run)."""

    warm: QPResult
    obs: ObserverState
    q_post: jax.Array
    variant: Variant


def control_qp_settings(iters: int = 4, **kw) -> QPSettings:
    """ADMM settings of the control loop (``kw``: other :class:`~wbc_jax.qp.QPSettings` fields to override).

    ``iters`` iterations warm-started from the previous step's solution, then blocks of 4 (``check_every``) while
    OSQP's test at tolerance 1e-4 (``eps_abs``, ``eps_rel``) fails, up to 200 (``max_iters``); the first
    ``N_EQ_ROWS`` rows ((9)-(11)) held exactly (``eq_rows``); rho fixed at 3 on the inequality rows
    (``adapt_every=0``: one factorization per step); 2 Ruiz passes; the linear solve and the implementation picked
    per backend (``linsolve`` and ``kernel`` ``"auto"``: on a GPU the fused Pallas kernels).
    """
    return QPSettings(**{**dict(iters=iters, eps_abs=1e-4, eps_rel=1e-4, linsolve="auto", adapt_every=0,
                                rho=3.0, ruiz_iters=2, eq_rows=N_EQ_ROWS, max_iters=200, check_every=4,
                                kernel="auto"),
                          **kw})


@dataclass(frozen=True)
class TransportConfig:
    """Static controller structure (hashable; changing it recompiles).

    Attributes:
        k: friction-pyramid edges; qp: ADMM settings; dt: control period [s].
    """

    k: int = 4
    qp: QPSettings = control_qp_settings()
    dt: float = 0.001

    @property
    def n_var(self) -> int:
        return 24 + self.k * (N_FEET + N_OBJ)

    @property
    def n_con(self) -> int:
        return N_EQ_ROWS + 4 + 18 + self.k * (N_FEET + N_OBJ)


class QPDiag(NamedTuple):
    """Per-step QP health and command: tau (18,) applied (clipped) torques [N m], prim_res, dual_res, flag,
    tau_excess: () largest amount by which the unclipped QP torque exceeded its limit [N m] (< 0: within),
    iters: () int32 ADMM iterations the step took, obj_forces: (4, 3) the object contact forces the solution
    plans, tray contact frame, normal first [N] (:func:`planned_object_forces`)."""

    tau: jax.Array
    prim_res: jax.Array
    dual_res: jax.Array
    flag: jax.Array
    tau_excess: jax.Array
    iters: jax.Array
    obj_forces: jax.Array


def qp_settings(cfg: TransportConfig) -> QPSettings:
    """The settings the controller solves its QP with: ``cfg.qp`` with the multiplier rows as the box block."""
    return cfg.qp._replace(box_rows=cfg.k * (N_FEET + N_OBJ))


def initial_factors(cfg: TransportConfig):
    """The first warm start's QP factors where the solver will reuse factors on this machine
    (``QPSettings.reuse_factors`` as :func:`wbc_jax.qp.api.resolve_settings` leaves it), else None."""
    s = resolve_settings(qp_settings(cfg), cfg.qp.iters, jnp.zeros(()).dtype, jax.default_backend())
    return empty_factors(cfg.n_var, cfg.n_con, s) if s.reuse_factors else None


def init_control_state(cfg: TransportConfig, dyn: DynTerms, ids: RobotIds) -> ControlState:
    n, mcon = cfg.n_var, cfg.n_con
    z = jnp.zeros
    # no warm point yet (zeros), but a valid rho: the settings' initial rho (a 0 would be clipped to rho_min and,
    # with rho adaptation off, kept for the whole run)
    warm = QPResult(x=z(n), y=z(mcon), z=z(mcon), prim_res=z(()), dual_res=z(()),
                    flag=jnp.zeros((), jnp.int32), iters=jnp.zeros((), jnp.int32), rho=z(()) + cfg.qp.rho,
                    factors=initial_factors(cfg))
    obs = ObserverState(h0=dyn.h_G, integral=z(6), r=z(6), w_cmd=z(6))
    return ControlState(warm=warm, obs=obs, q_post=dyn.q[ids.act_qpos[12:]],
                        variant=Variant(*(jnp.asarray(v, float) for v in FULL)))


def observer_update(obs: ObserverState, dyn: DynTerms, k_obs, dt) -> ObserverState:
    """One Euler step of the momentum observer, using last step's commanded contact wrench."""
    g = jnp.array([0.0, 0.0, -GRAVITY * dyn.mass, 0.0, 0.0, 0.0])
    integral = obs.integral + (obs.w_cmd + g + obs.r) * dt
    r = k_obs * (dyn.h_G - obs.h0 - integral)
    return obs._replace(integral=integral, r=r)


@full_precision
def assemble(obs: Observation, ref: Reference, om: ObjectModel, gains: TransportGains, cs: ControlState,
             ids: RobotIds, cfg: TransportConfig, mu_ground=1.0):
    """Observer step and the QP of this control step: ``(new ObserverState, TransportQP)``."""
    dyn = obs.robot
    observer = observer_update(cs.obs, dyn, gains.k_obs * cs.variant.observer, cfg.dt)
    return observer, build_qp(dyn, obs.obj, obs.J_tray_obj, obs.Jdv_tray_obj, ref, om, gains, observer.r, ids, cfg.k,
                              mu_ground, cs.q_post, cs.variant)


@full_precision
def transport_control(obs: Observation, ref: Reference, om: ObjectModel, gains: TransportGains,
                      cs: ControlState, ids: RobotIds, cfg: TransportConfig, mu_ground=1.0):
    """One control step: observer, QP, torques.

    Args:
        obs: what the controller reads of the state (:func:`wbc_jax.physics.observe.observe`); ref: the planner's
            reference; om: the controller's object model; gains; cs: its state; ids: static ids; cfg: its
            static configuration; mu_ground: () or (4,) friction under each foot.

    Returns:
        (tau (18,) actuator torques [N m], new ControlState, QPDiag). An :func:`~wbc_jax.qp.unusable` solve
        (``FLAG_NONFINITE``, ``FLAG_DIVERGED``) is not applied: the last applied solution stands in for the
        torques, the observer's commanded wrench and the state's warm result (whose flag makes the next solve
        start afresh: :func:`wbc_jax.qp.solve_qp`'s warm rule).
    """
    with jax.named_scope("qp_assemble"):
        observer, qp = assemble(obs, ref, om, gains, cs, ids, cfg, mu_ground)
    res = last_usable(solve_qp(qp.P, qp.q, qp.A, qp.l, qp.u, warm=cs.warm, settings=qp_settings(cfg)), cs.warm)
    tau_raw = qp.A_tau @ res.x + qp.h_a
    tmax = jnp.asarray(ids.tau_max)
    tau = jnp.clip(tau_raw, -tmax, tmax)
    # commanded net contact wrench about the CoM, for the observer's next step
    observer = observer._replace(w_cmd=qp.H_com @ res.x)
    diag = QPDiag(tau=tau, prim_res=res.prim_res, dual_res=res.dual_res, flag=res.flag,
                  tau_excess=jnp.max(jnp.abs(tau_raw) - tmax), iters=res.iters,
                  obj_forces=planned_object_forces(res.x, om.mu, ids.nv_robot, cfg.k))
    return tau, cs._replace(warm=res, obs=observer), diag
