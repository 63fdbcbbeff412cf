"""Capture-point walking pattern (``wbc_jax.planner.capture_point``) against closed-form LIPM solutions and a
float64 forward simulation of the capture-point dynamics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax import planner as pl

plan_trot_j = jax.jit(pl.footstep_plan_trot, static_argnums=3)
eos_j = jax.jit(pl.end_of_step_cps)
ini_j = jax.jit(pl.initial_cps)
gait_t = jax.jit(jax.vmap(pl.gait_phase, in_axes=(None, 0)))

def test_cp_recursion_closed_form_constant_stride():
    """Uniform steps P_i = i s ending at rest: xi_eos[i] - P_i = s (1 - b^(N-1-i)) / (1 - b)."""
    w = float(pl.omega(0.43))
    assert w == pytest.approx(np.sqrt(9.81 / 0.43), rel=1e-6)
    N, s, T = 12, 0.1, 0.25
    P = np.stack([np.arange(N) * s, np.zeros(N)], 1)
    eos = np.asarray(eos_j(P, T, w, P[-1]))
    b = np.exp(-w * T)
    ref = s * (1 - b ** (N - 1 - np.arange(N))) / (1 - b)
    np.testing.assert_allclose(eos[:, 0] - P[:, 0], ref, atol=1e-5)
    np.testing.assert_allclose(eos[:, 1], 0.0, atol=1e-7)
    ini = np.asarray(ini_j(P, eos, T, w))
    np.testing.assert_allclose(ini[1:], eos[:-1], atol=1e-5)


def test_cp_forward_simulation_reaches_end_of_step_cps():
    """Integrate the LIPM x'' = w^2 (x - P) (float64 RK4) from a CoM whose CP is xi_ini[0]."""
    w = float(pl.omega(0.45))
    rng = np.random.default_rng(3)
    N = 7
    T = rng.uniform(0.2, 0.3, size=N)
    P = np.cumsum(rng.uniform(-0.05, 0.12, size=(N, 2)), axis=0)
    eos = np.asarray(eos_j(P, T, w, P[-1] + np.array([0.01, -0.02])), np.float64)
    ini = np.asarray(ini_j(P, eos, T, w), np.float64)
    x = np.array([0.03, -0.02])
    xd = w * (ini[0] - x)  # so that x + xd / w = xi_ini[0]
    n_sub = 400
    for i in range(N):
        h = T[i] / n_sub

        def f(state, Pi=P[i]):
            return np.concatenate([state[2:], w**2 * (state[:2] - Pi)])

        y = np.concatenate([x, xd])
        for _ in range(n_sub):
            k1 = f(y)
            k2 = f(y + 0.5 * h * k1)
            k3 = f(y + 0.5 * h * k2)
            k4 = f(y + h * k3)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        x, xd = y[:2], y[2:]
        np.testing.assert_allclose(np.asarray(pl.cp(x, xd, w)), eos[i], atol=2e-5)
    # eq. (21) inside a step and eq. (19) consistency
    xi_mid = pl.cp_trajectory(P[2], ini[2], 0.5 * T[2], w)
    np.testing.assert_allclose(xi_mid, P[2] + np.exp(w * 0.5 * T[2]) * (ini[2] - P[2]), atol=1e-5)
    np.testing.assert_allclose(pl.desired_com_velocity(x, eos[-1], w), -w * (x - eos[-1]), atol=1e-6)


def test_cp_reference_and_trot_plan():
    params = pl.GaitParams(t_stance=0.05, t_swing=0.2, t_start=0.5)
    T = params.t_stance + params.t_swing
    feet0 = np.array([[0.19, -0.29], [-0.19, -0.29], [0.19, 0.29], [-0.19, 0.29]])  # facing -y
    N, stride = 10, 0.1
    plan = plan_trot_j(feet0, -np.pi / 2, stride, N)
    P, feet = np.asarray(plan.P), np.asarray(plan.feet)
    np.testing.assert_allclose(P[:, 0], 0.0, atol=1e-6)
    np.testing.assert_allclose(P[:, 1], -stride * np.arange(N), atol=1e-6)
    moved = np.linalg.norm(np.diff(feet, axis=0), axis=-1)  # (N, 4)
    np.testing.assert_allclose(moved[0], [stride, 0, 0, stride], atol=1e-6)
    np.testing.assert_allclose(moved[3], [0, 2 * stride, 2 * stride, 0], atol=1e-6)
    np.testing.assert_allclose(moved[-1].max(), stride, atol=1e-6)
    np.testing.assert_allclose(feet[-1] - feet0, np.broadcast_to([0.0, -(N - 1) * stride], (4, 2)), atol=1e-6)
    np.testing.assert_allclose(plan.xi_final, P[-1], atol=1e-6)

    w = float(pl.omega(0.43))
    eos = eos_j(plan.P, T, w, plan.xi_final)
    P0 = jax.jit(pl.first_footstep_for_rest)(jnp.zeros(2), eos[0], T, w)
    P_rest = plan.P.at[0].set(P0)
    np.testing.assert_allclose(ini_j(P_rest, eos, T, w)[0], [0.0, 0.0], atol=1e-6)

    ref = jax.jit(jax.vmap(pl.cp_reference, in_axes=(None, None, 0, None, None, None)))
    ts = np.linspace(0.0, params.t_start + N * T + 0.5, 2001)
    r = ref(P_rest, eos, jnp.asarray(ts), params.t_start, T, w)
    xi = np.asarray(r.xi)
    assert np.abs(xi[ts <= params.t_start]).max() < 1e-6  # starts at the resting CoM
    np.testing.assert_allclose(xi[-1], plan.xi_final, atol=1e-5)
    assert np.abs(np.diff(xi, axis=0)).max() < 0.01  # continuous across steps
    step_ends = params.t_start + T * np.arange(1, N + 1)
    r_end = ref(P_rest, eos, jnp.asarray(step_ends - 1e-5), params.t_start, T, w)
    np.testing.assert_allclose(r_end.xi, eos, atol=1e-4)
    # the gait's step index matches the CP step inside the walk
    st = gait_t(params, jnp.asarray(ts))
    walking = (ts > params.t_start) & (ts < step_ends[-1])
    np.testing.assert_array_equal(np.asarray(st.step_index)[walking], np.asarray(r.step)[walking])
    mid = walking & (np.abs(((ts - params.t_start) % T) - T / 2) < T / 4)
    xd_fd = np.gradient(xi[:, 1], ts)
    np.testing.assert_allclose(xd_fd[mid], np.asarray(r.xi_dot)[mid, 1], atol=0.01)
    # vmap over strides (batched plans) through the whole chain
    def chain(s):
        pln = pl.footstep_plan_trot(feet0, -np.pi / 2, s, N)
        return pl.end_of_step_cps(pln.P, T, w, pln.xi_final)

    eos_b = jax.jit(jax.vmap(chain))(jnp.array([0.05, 0.1]))
    np.testing.assert_allclose(eos_b[1], eos, atol=1e-6)
    np.testing.assert_allclose(eos_b[0], 0.5 * np.asarray(eos), atol=1e-6)
