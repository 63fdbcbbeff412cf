"""Capture-point walking pattern (centroidal paper Sec. 2.3.1; Englsberger's recursion).

LIPM with natural frequency ``w = sqrt(g / z0)``; capture point (CP) ``xi = x + xdot / w``
(eq. 18); CP dynamics ``xi_dot = w (xi - P)`` (eq. 20) with the virtual leg ``P`` (the
midpoint of the stance pair, constant during a step); CoM ``xdot = -w (x - xi)`` (eq. 19).

Step indexing (used by every function here). Step ``i`` (i = 0..N-1) lasts ``T_i`` and
uses the virtual leg ``P_i = footsteps[i]``. It starts at
``t0 + sum_{j<i} T_j`` and its CP goes from ``xi_ini[i]`` to ``xi_eos[i]``:

    xi(tau) = P_i + exp(w tau) (xi_ini[i] - P_i),   tau in [0, T_i]       (eq. 21)
    xi_eos[i] = xi(T_i) = xi_ini[i + 1]
    xi_ini[i] = P_i + exp(-w T_i) (xi_eos[i] - P_i)                       (eq. 22)

The recursion runs backwards from ``xi_eos[N-1] = xi_final`` (usually the final virtual
leg, so the pattern ends at rest). With the trot scheduler of :mod:`.gait`, step ``i`` is
half-cycle ``i`` (``T = t_stance + t_swing``, ``t0 = t_start``) and ``P_i`` is the midpoint of
the pair that does not swing in it (:func:`footstep_plan_trot`).

The walking pattern of a trot (:func:`cp_walk_plan`, :func:`cp_walk_reference`) puts these together
with the gait scheduler and quintic swing-foot references: desired CP, desired CoM velocity from the
measured CoM (eq. 19) and swing references at any time t.

All functions are pure jax.numpy, jit- and vmap-able; ``N`` is static.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from .gait import PAIRS, GaitParams, gait_phase
from .swing import swing_reference


def _f(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


def omega(z0, g=9.81):
    """LIPM natural frequency ``w = sqrt(g / z0)`` [1/s] from the CoM height z0 [m]."""
    return jnp.sqrt(_f(g) / _f(z0))


def cp(x, xd, w):
    """Capture point ``xi = x + xd / w`` (eq. 18).

    Args:
        x: (2,) horizontal CoM position [m].
        xd: (2,) horizontal CoM velocity [m/s].
        w: () LIPM frequency [1/s].

    Returns:
        (2,) capture point [m].
    """
    return _f(x) + _f(xd) / w


def cp_trajectory(P, xi_ini, t, w):
    """CP during one step with a fixed virtual leg (eq. 21).

    Args:
        P: (2,) virtual-leg position of the step [m].
        xi_ini: (2,) CP at the start of the step [m].
        t: () time since the start of the step [s].
        w: () LIPM frequency [1/s].

    Returns:
        (2,) CP at time t [m] (its rate is ``cp_rate(xi, P, w)``).
    """
    P = _f(P)
    return P + jnp.exp(w * _f(t)) * (_f(xi_ini) - P)


def cp_rate(xi, P, w):
    """CP velocity ``xi_dot = w (xi - P)`` (eq. 20) [m/s]; xi, P (2,) [m]."""
    return w * (_f(xi) - _f(P))


def desired_com_velocity(x, xi, w):
    """Desired horizontal CoM velocity ``xdot = -w (x - xi)`` (eq. 19).

    Args:
        x: (2,) CoM position [m].
        xi: (2,) desired CP [m].
        w: () LIPM frequency [1/s].

    Returns:
        (2,) CoM velocity [m/s].
    """
    return -w * (_f(x) - _f(xi))


def _durations(t_step, n):
    return jnp.broadcast_to(_f(t_step), (n,))


def end_of_step_cps(footsteps, t_step, w, xi_final):
    """End-of-step CPs by backward recursion (eq. 22).

    Args:
        footsteps: (N, 2) virtual-leg positions P_i, one per step [m].
        t_step: () or (N,) step durations T_i [s].
        w: () LIPM frequency [1/s].
        xi_final: (2,) CP at the end of the last step [m] (its virtual leg for a stop).

    Returns:
        (N, 2) ``xi_eos[i]``, the CP at the end of step i (= start of step i+1);
        ``xi_eos[N-1] = xi_final``.
    """
    P = _f(footsteps)
    b = jnp.exp(-w * _durations(t_step, P.shape[0]))  # (N,)

    def back(xi_next_eos, inp):  # carry: xi_eos[i]; output it, pass xi_ini[i] = xi_eos[i-1]
        P_i, b_i = inp
        return P_i + b_i * (xi_next_eos - P_i), xi_next_eos

    _, eos = lax.scan(back, _f(xi_final), (P, b), reverse=True)
    return eos


def initial_cps(footsteps, xi_eos, t_step, w):
    """Start-of-step CPs ``xi_ini[i] = P_i + exp(-w T_i) (xi_eos[i] - P_i)`` (eq. 22).

    Args:
        footsteps: (N, 2) virtual legs [m].
        xi_eos: (N, 2) from :func:`end_of_step_cps` [m].
        t_step: () or (N,) step durations [s].
        w: () LIPM frequency [1/s].

    Returns:
        (N, 2) CP at the start of each step [m]; ``xi_ini[i] = xi_eos[i-1]`` for i >= 1.
    """
    P = _f(footsteps)
    b = jnp.exp(-w * _durations(t_step, P.shape[0]))[:, None]
    return P + b * (_f(xi_eos) - P)


def first_footstep_for_rest(x0, xi_eos0, t_step0, w):
    """Virtual leg of step 0 that makes the CP start at a resting CoM ``x0``.

    A robot at rest has ``xi = x0``; solving eq. 22 for ``P_0`` with ``xi_ini[0] = x0``
    gives ``P_0 = (x0 - b xi_eos[0]) / (1 - b)``, ``b = exp(-w T_0)``. ``xi_eos[0]`` does not
    depend on ``P_0``, so replace ``footsteps[0]`` by this and the pattern starts smoothly.

    Args:
        x0: (2,) CoM at rest [m].
        xi_eos0: (2,) ``end_of_step_cps(...)[0]`` [m].
        t_step0: () duration of step 0 [s].
        w: () LIPM frequency [1/s].

    Returns:
        (2,) P_0 [m] (behind x0 when walking forward).
    """
    b = jnp.exp(-w * _f(t_step0))
    return (_f(x0) - b * _f(xi_eos0)) / (1.0 - b)


class CPReference(NamedTuple):
    """Desired CP at one instant.

    Attributes:
        xi: (2,) desired CP [m].
        xi_dot: (2,) its rate [m/s] (0 before the first and after the last step).
        P: (2,) virtual leg of the current step [m].
        step: () int32 current step, clipped to [0, N-1].
    """

    xi: jnp.ndarray
    xi_dot: jnp.ndarray
    P: jnp.ndarray
    step: jnp.ndarray


def cp_reference(footsteps, xi_eos, t, t0, t_step, w) -> CPReference:
    """Desired CP at absolute time t from the step plan (eq. 21 written from the end).

    Uses ``xi = P_i + exp(-w (t_end_i - t)) (xi_eos[i] - P_i)`` (equal to eq. 21, with an
    exponent <= 0, so float32 stays accurate). Before ``t0`` it holds ``xi_ini[0]``; after
    the last step it holds ``xi_eos[N-1]``.

    Args:
        footsteps: (N, 2) virtual legs [m].
        xi_eos: (N, 2) end-of-step CPs [m].
        t: () time [s].
        t0: () start of step 0 [s].
        t_step: () or (N,) step durations [s].
        w: () LIPM frequency [1/s].

    Returns:
        CPReference.
    """
    P = _f(footsteps)
    n = P.shape[0]
    T = _durations(t_step, n)
    t = _f(t)
    ends = _f(t0) + jnp.cumsum(T)  # (N,)
    i = jnp.minimum(jnp.sum(t >= ends), n - 1).astype(jnp.int32)
    rem = jnp.clip(ends[i] - t, 0.0, T[i])
    P_i = P[i]
    xi = P_i + jnp.exp(-w * rem) * (_f(xi_eos)[i] - P_i)
    active = (t >= ends[i] - T[i]) & (t < ends[i])
    return CPReference(xi, jnp.where(active, w * (xi - P_i), 0.0), P_i, i)


class TrotFootsteps(NamedTuple):
    """Footstep plan of a straight trot.

    Attributes:
        P: (N, 2) virtual leg of step i: midpoint of the pair in stance during step i [m].
        feet: (N+1, 4, 2) foot positions (FL, FR, BL, BR): ``feet[0]`` initial,
            ``feet[i+1]`` after the swing of step i [m].
        xi_final: (2,) final CP = final virtual leg (the plan ends at rest) [m].
    """

    P: jnp.ndarray
    feet: jnp.ndarray
    xi_final: jnp.ndarray


def footstep_plan_trot(feet0_xy, heading, stride, n_steps: int) -> TrotFootsteps:
    """Footholds and virtual legs of a straight trot that starts and ends at rest.

    Step i swings pair ``i % 2`` ((FL, BR) first, as in :mod:`.gait`); that pair lands
    ``min(i + 1, N - 1) * stride`` ahead of its initial footholds along the heading. Hence
    the first and the last swing cover one stride, the others two; the virtual legs
    advance by one stride per step, ``P_i = c_pair + i * stride * d``; after the last step
    all feet are ``(N-1) stride`` ahead, aligned, and the CP rests on ``P_{N-1}``.

    Args:
        feet0_xy: (4, 2) initial foot positions (FL, FR, BL, BR) [m].
        heading: () walking direction yaw [rad] (d = (cos, sin); along -y: -pi/2).
        stride: () advance of the virtual leg per step [m] (speed ~ stride / step time).
        n_steps: N >= 2, number of steps (half-cycles); static.

    Returns:
        TrotFootsteps.
    """
    if n_steps < 2:
        raise ValueError("n_steps must be >= 2")
    feet0 = _f(feet0_xy)
    heading = _f(heading)
    d = jnp.stack([jnp.cos(heading), jnp.sin(heading)]) * _f(stride)  # (2,) per-step advance
    idx = jnp.arange(n_steps)
    pair_of = jnp.asarray([0, 1, 1, 0])  # FL, FR, BL, BR
    # advance (in strides) of each foot after step i: its pair's last landing
    last = jnp.minimum(idx + 1, n_steps - 1)  # landing advance of the pair swinging in step i
    swung = (idx[:, None] % 2) == pair_of[None, :]  # (N, 4) foot swings in step i
    adv = jnp.where(swung, last[:, None], 0)
    adv = lax.cummax(adv, axis=0)  # (N, 4) advances only grow
    adv = jnp.concatenate([jnp.zeros((1, 4), adv.dtype), adv], axis=0)  # (N+1, 4)
    feet = feet0[None] + adv[:, :, None].astype(feet0.dtype) * d  # (N+1, 4, 2)
    # stance pair of step i = the other pair, read in feet[i]
    mids = jnp.stack([0.5 * (feet[:, a] + feet[:, b]) for a, b in PAIRS], axis=1)  # (N+1, 2, 2)
    stance_pair = 1 - (idx % 2)
    P = mids[idx, stance_pair]
    xi_final = 0.5 * (mids[-1, 0] + mids[-1, 1])
    return TrotFootsteps(P, feet, xi_final)


# ----------------------------------------------------------------------------- walking pattern of a trot


class CPWalkPlan(NamedTuple):
    """Capture-point walking pattern of a straight trot (pytree; leaves may carry a batch axis).

    Attributes:
        feet: (N+1, 4, 2) footholds (FL, FR, BL, BR): ``feet[0]`` initial, ``feet[i+1]`` after step i [m].
        P: (N, 2) virtual legs (midpoint of the stance pair; ``P[0]`` set for a start from rest) [m].
        xi_eos: (N, 2) end-of-step CPs (eq. 22) [m].
        w: () LIPM frequency [1/s].
        z0: () CoM height of the LIPM (the CoM height reference) [m].
        foot_z: () foot-centre height at touchdown [m].
        swing_height: () swing apex above the higher end point [m].
        heading: (2,) unit walking direction.
        gait: GaitParams; half-cycle k is step k (``t_stop`` ends the plan).
    """

    feet: jnp.ndarray
    P: jnp.ndarray
    xi_eos: jnp.ndarray
    w: jnp.ndarray
    z0: jnp.ndarray
    foot_z: jnp.ndarray
    swing_height: jnp.ndarray
    heading: jnp.ndarray
    gait: GaitParams


def cp_walk_plan(feet0, com0, heading, stride, n_steps: int, gait: GaitParams, swing_height,
                 g=9.81) -> CPWalkPlan:
    """Plan a straight trot of ``n_steps`` half-cycles that starts and ends at rest (Sec. 2.3.1).

    The footholds are :func:`footstep_plan_trot` of the initial feet moved so that their centroid is
    under the CoM (a CoM ahead of the feet's centre, as with the arm on this robot, would otherwise end
    the walk with the legs leaning forward); the first virtual leg is
    :func:`first_footstep_for_rest`, so the desired CP starts at the resting CoM.

    Args:
        feet0: (4, 3) initial foot centres [m] (z gives the touchdown height).
        com0: (3,) initial CoM [m] (z gives the LIPM height z0).
        heading: () walking direction yaw [rad] (along world -y: -pi/2).
        stride: () virtual-leg advance per step [m].
        n_steps: N >= 2 (static).
        gait: GaitParams; its t_stop is replaced by the end of step N - 1.
        swing_height: () [m].

    Returns:
        CPWalkPlan.
    """
    feet0, com0 = _f(feet0), _f(com0)
    T = _f(gait.t_stance) + _f(gait.t_swing)
    w = omega(com0[2], g)
    shift = com0[:2] - jnp.mean(feet0[:, :2], axis=0)
    plan = footstep_plan_trot(feet0[:, :2] + shift, heading, stride, n_steps)
    feet = plan.feet.at[0].set(feet0[:, :2])
    eos = end_of_step_cps(plan.P, T, w, plan.xi_final)
    P = plan.P.at[0].set(first_footstep_for_rest(com0[:2], eos[0], T, w))
    gait = GaitParams(*(_f(x) for x in gait._replace(t_stop=_f(gait.t_start) + n_steps * T)))
    h = _f(heading)
    return CPWalkPlan(feet=feet, P=P, xi_eos=eos, w=w, z0=com0[2], foot_z=jnp.mean(feet0[:, 2]),
                      swing_height=_f(swing_height), heading=jnp.stack([jnp.cos(h), jnp.sin(h)]), gait=gait)


class WalkReference(NamedTuple):
    """Pattern output at one instant (world frame).

    Attributes:
        cp: CPReference (desired CP, its rate, virtual leg, step).
        v_xy: (2,) desired horizontal CoM velocity from the measured CoM, eq. 19 [m/s].
        swing: (4,) bool swing mask.
        p_sw, v_sw, a_sw: (4, 3) quintic swing-foot references [m, m/s, m/s^2].
    """

    cp: CPReference
    v_xy: jnp.ndarray
    swing: jnp.ndarray
    p_sw: jnp.ndarray
    v_sw: jnp.ndarray
    a_sw: jnp.ndarray


def cp_walk_reference(plan: CPWalkPlan, t, com_xy, p_lift) -> WalkReference:
    """Desired CP (eq. 21), CoM velocity (eq. 19) and swing-foot references at time t.

    Args:
        plan: CPWalkPlan; t: () time [s]; com_xy: (2,) measured CoM [m];
        p_lift: (4, 3) foot positions at their last liftoff (swing start) [m].
    """
    n = plan.P.shape[0]
    T = plan.gait.t_stance + plan.gait.t_swing
    ref = cp_reference(plan.P, plan.xi_eos, t, plan.gait.t_start, T, plan.w)
    gs = gait_phase(plan.gait, t)
    step = jnp.clip(gs.step_index, 0, n - 1)
    land = jnp.concatenate([jnp.asarray(plan.feet)[step + 1], jnp.full((4, 1), plan.foot_z)], axis=1)  # (4, 3)
    p, v, a = jax.vmap(lambda pl, pd, ph: swing_reference(pl, pd, ph, plan.gait.t_swing, plan.swing_height,
                                                          kind="quintic"))(p_lift, land, gs.swing_phase)
    return WalkReference(cp=ref, v_xy=desired_com_velocity(com_xy, ref.xi, plan.w), swing=gs.swing,
                         p_sw=p, v_sw=v, a_sw=a)
