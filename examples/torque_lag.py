"""A controller from outside the package: the transport WBC behind first-order actuator dynamics.

The QP's torques u_k pass through a first-order lag of time constant T before they reach the motors,
T dtau/dt = u - tau, discretized by backward Euler at the control period dt:

    tau_k = tau_{k-1} + a (u_k - tau_{k-1}),   a = dt / (T + dt),

starting at the first step's QP torque (tau_0 = u_0). A convex combination of torques within the QP's limits
stays within them. With T = 0, a = 1. It asks how much actuator bandwidth the paper's controller needs to
carry the cube without sliding.

Run it (from the repository root, so that ``examples.torque_lag`` imports) on the quick spec's cells and
compare it with the paper's controller cell by cell::

    wbc-jax campaign --spec sweeps/torque_lag.toml --out out/lag
    wbc-jax campaign --spec sweeps/quick.toml --out out/quick
    wbc-jax regress --compare out/quick out/lag

A spec's ``[plugin]`` table names the class and sets its fields (``time_constant`` here); the rules a plug-in
follows: :mod:`wbc_jax.rollout.controllers.plugin`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from wbc_jax.rollout.controllers import TransportController
from wbc_jax.rollout.controllers.base import keep_where


class LagState(NamedTuple):
    """The transport controller's state and the lag's memory."""

    inner: Any  # wbc_jax.control.transport.ControlState
    tau: jax.Array  # (nu,) [N m] the torque the motors received at the last step
    started: jax.Array  # () bool: a step has run (tau holds a torque)


def lag(tau_prev, u, started, dt: float, time_constant: float):
    """(nu,) [N m] the lagged torque: ``u`` on the first step, else tau_prev + dt / (T + dt) (u - tau_prev)."""
    a = dt / (time_constant + dt)
    return jnp.where(started, tau_prev + a * (u - tau_prev), u)


@dataclass(frozen=True, eq=False)
class TorqueLag(TransportController):
    """The transport WBC whose torques reach the motors through a first-order lag (module docstring)."""

    time_constant: float = 0.02  # [s] T, >= 0

    def __post_init__(self):
        if not self.time_constant >= 0:
            raise ValueError(f"TorqueLag.time_constant = {self.time_constant}: expected >= 0 [s]")

    def init_state(self, robot, d, dyn):
        nu = robot.mj_model.nu
        return LagState(super().init_state(robot, d, dyn), jnp.zeros(nu, d.qpos.dtype), jnp.zeros((), bool))

    def control(self, obs, ref, obj_model, gains, state, ids, mu):
        u, inner, diag = super().control(obs, ref, obj_model, gains, state.inner, ids, mu)
        tau = lag(state.tau, u, state.started, self.cfg.dt, self.time_constant)
        return tau, LagState(inner, tau, jnp.ones((), bool)), diag

    def freeze(self, frozen, new, old):
        inner = super().freeze(frozen, new.inner, old.inner)
        tau, started = keep_where(frozen, (new.tau, new.started), (old.tau, old.started))
        return LagState(inner, tau, started)

    def variant(self, cs):
        return super().variant(cs.inner)

    def with_variant(self, cs, switches):
        return cs._replace(inner=super().with_variant(cs.inner, switches))
