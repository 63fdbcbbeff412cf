"""A controller from outside the package: the transport WBC behind first-order actuator dynamics.

The QP's torques u_k pass through a first-order lag of time constant T before they reach the motors,
T dtau/dt = u - tau, discretized by backward Euler at the control period dt:

    tau_k = tau_{k-1} + a (u_k - tau_{k-1}),   a = dt / (T + dt),

starting at the first step's QP torque (tau_0 = u_0). A convex combination of torques within the QP's limits
stays within them; with T = 0 the motors receive the QP's torques. It asks how much actuator bandwidth the paper's
controller needs to carry the cube without sliding.

A spec's ``[plugin]`` table names the class and sets ``time_constant``; a ``plugin.time_constant`` factor varies it
per run in one batch (the state carries it: :meth:`TorqueLag.with_params`). Run from the repository root, so that
``examples.torque_lag`` imports::

    wbc-jax campaign --spec sweeps/torque_lag.toml --out out/lag

The rules a plug-in follows: :mod:`wbc_jax.rollout.controllers.plugin`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.rollout.controllers import TransportController
from wbc_jax.rollout.controllers.base import keep_where
from wbc_jax.rollout.packed import broadcast_like


class LagState(NamedTuple):
    """The transport controller's state, the lag's memory, its time constant (per run) and its own metric's sums."""

    inner: Any  # wbc_jax.control.transport.ControlState
    tau: jax.Array  # (nu,) [N m] the torque the motors received at the last step
    started: jax.Array  # () bool: a step has run (tau holds a torque)
    time_constant: jax.Array  # () [s] T of this run
    err_sq_sum: jax.Array  # () [N^2 m^2] sum over control steps of mean_j (tau_j - u_j)^2
    steps: jax.Array  # () control steps summed


def lag(tau_prev, u, started, dt: float, time_constant):
    """(nu,) [N m] the lagged torque: ``u`` on the first step or with T = 0, else tau_prev + dt / (T + dt)
    (u - tau_prev)."""
    a = dt / (time_constant + dt)
    return jnp.where(started & (time_constant > 0), tau_prev + a * (u - tau_prev), u)


@dataclass(frozen=True, eq=False)
class TorqueLag(TransportController):
    """The transport WBC whose torques reach the motors through a first-order lag (module docstring)."""

    time_constant: float = 0.02  # [s] T, >= 0
    extra_columns = ("lag_err_rms_Nm",)  # results.csv: RMS of (tau - u) over joints and control steps [N m]

    def __post_init__(self):
        if not self.time_constant >= 0:
            raise ValueError(f"TorqueLag.time_constant = {self.time_constant}: expected >= 0 [s]")

    def init_state(self, robot, d, dyn):
        dtype, zero = d.qpos.dtype, jnp.zeros((), d.qpos.dtype)
        return LagState(super().init_state(robot, d, dyn), jnp.zeros(robot.mj_model.nu, dtype), jnp.zeros((), bool),
                        jnp.asarray(self.time_constant, dtype), zero, zero)

    def with_params(self, cs, params):
        """``cs`` with each run's time constant (``params["time_constant"]``: (B,) [s])."""
        return cs._replace(time_constant=broadcast_like(cs.time_constant, params["time_constant"]))

    def control(self, obs, ref, obj_model, gains, state, ids, mu):
        u, inner, diag = super().control(obs, ref, obj_model, gains, state.inner, ids, mu)
        tau = lag(state.tau, u, state.started, self.cfg.dt, state.time_constant)
        return tau, state._replace(inner=inner, tau=tau, started=jnp.ones((), bool),
                                   err_sq_sum=state.err_sq_sum + jnp.mean((tau - u) ** 2), steps=state.steps + 1), diag

    def freeze(self, frozen, new, old):
        inner = super().freeze(frozen, new.inner, old.inner)
        return keep_where(frozen, new._replace(inner=None), old._replace(inner=None))._replace(inner=inner)

    def finalize(self, sim, acc, state, p_goal, mu, n, course: bool) -> dict:
        """The transport's results and ``lag_err_rms_Nm``: sqrt(sum / steps) of the run's sums (up to its failure,
        where it failed: a frozen run keeps them)."""
        out = super().finalize(sim, acc, state, p_goal, mu, n, course)
        err, steps = (np.asarray(x)[:n] for x in (state.cs.err_sq_sum, state.cs.steps))
        out["lag_err_rms_Nm"] = np.sqrt(err / np.maximum(steps, 1))
        return out

    def variant(self, cs):
        return super().variant(cs.inner)

    def with_variant(self, cs, switches):
        return cs._replace(inner=super().with_variant(cs.inner, switches))
