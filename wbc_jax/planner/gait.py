"""Trot scheduler: which feet swing at time t, and how far into their swing they are.

Timeline (all times in seconds, world clock ``t``)::

    [0, t_start)                      standing, step_index = -1
    half-cycle k >= 0 starts at       t_start + k H,   H = t_stance + t_swing
      [0, t_stance)                   four-foot support
      [t_stance, H)                   diagonal pair k % 2 swings:
                                      k even: (FL, BR) = feet (0, 3); k odd: (FR, BL) = (1, 2)

A half-cycle is one "footstep" of the transport paper (a stance phase then a swing
phase), and one step of the capture-point pattern (the virtual leg of step k is the
midpoint of the pair that does NOT swing in k). Stopping: half-cycle k is stepped only if
it ends no later than ``t_stop`` (with a 1e-4 s tolerance); after that all four feet stay
in stance. :func:`t_stop_after` gives the ``t_stop`` for a number of half-cycles.

Everything is pure ``jax.numpy`` on a traced scalar ``t``; :class:`GaitParams` leaves may
be python floats or (batched) arrays.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

FL, FR, BL, BR = 0, 1, 2, 3
FOOT_NAMES = ("FL", "FR", "BL", "BR")
FOOT_PAIR = (0, 1, 1, 0)  # diagonal pair of each foot: 0 = (FL, BR), 1 = (FR, BL)
PAIRS = ((FL, BR), (FR, BL))
_T_STOP_TOL = 1e-4  # [s]


class GaitParams(NamedTuple):
    """Trot timing.

    Attributes:
        t_stance: four-foot support at the start of each half-cycle [s].
        t_swing: diagonal swing at the end of each half-cycle [s].
        t_start: standing time before the first half-cycle [s].
        t_stop: no half-cycle that would end after this time is stepped [s] (inf: never
            stop).
    """

    t_stance: float = 0.15
    t_swing: float = 0.115
    t_start: float = 0.5
    t_stop: float = float("inf")


class GaitState(NamedTuple):
    """Gait state at one instant (leading batch axes under vmap).

    Attributes:
        swing: (4,) bool, foot is in swing (FL, FR, BL, BR).
        swing_phase: (4,) progress of the swing in [0, 1) (0 at liftoff); 0 for stance.
        step_index: () int32 half-cycle counter; -1 before ``t_start``. Keeps counting
            (by time) after ``t_stop``; see ``stepping``.
        t_in_half: () time since the start of the current half-cycle [s]; before
            ``t_start`` the time since t = 0.
        t_to_liftoff: (4,) time until the foot's next liftoff [s] (a swinging foot: its
            next swing, two half-cycles on); inf when none is scheduled.
        t_to_touchdown: (4,) time until the foot's next touchdown [s] (a swinging foot:
            the end of the current swing); inf when none is scheduled.
        stepping: () bool, the current half-cycle contains a swing (started, not stopped).
        swing_pair: () int32, pair that swings in the current half-cycle (0 = (FL, BR),
            1 = (FR, BL)); -1 before ``t_start``.
    """

    swing: jnp.ndarray
    swing_phase: jnp.ndarray
    step_index: jnp.ndarray
    t_in_half: jnp.ndarray
    t_to_liftoff: jnp.ndarray
    t_to_touchdown: jnp.ndarray
    stepping: jnp.ndarray
    swing_pair: jnp.ndarray


def half_cycle(params: GaitParams):
    """Half-cycle duration H = t_stance + t_swing [s]."""
    return params.t_stance + params.t_swing


def foot_stance_time(params: GaitParams):
    """Time each foot spends in stance per full cycle, 2 t_stance + t_swing [s]."""
    return 2.0 * params.t_stance + params.t_swing


def t_stop_after(params: GaitParams, n_half_cycles):
    """``t_stop`` that lets exactly ``n_half_cycles`` half-cycles be stepped [s]."""
    return params.t_start + n_half_cycles * half_cycle(params)


def _stepped(k, span, H):
    """Whether half-cycle k (float) is stepped; span = t_stop - t_start [s]."""
    return (k >= 0) & ((k + 1.0) * H <= span + _T_STOP_TOL)


def gait_phase(params: GaitParams, t) -> GaitState:
    """Trot gait state at time ``t``.

    Args:
        params: GaitParams (floats or arrays).
        t: () time [s] (may be traced).

    Returns:
        GaitState.
    """
    dtype = jnp.result_type(float)
    t = jnp.asarray(t, dtype=dtype)
    ts, tw, t0, tstop = (jnp.asarray(x, dtype=dtype) for x in params)
    H = ts + tw
    s = t - t0
    k = jnp.floor(s / H)
    tau = s - k * H
    # float rounding can leave tau just outside [0, H)
    low, high = tau < 0.0, tau >= H
    k = jnp.where(low, k - 1.0, jnp.where(high, k + 1.0, k))
    tau = jnp.where(low, tau + H, jnp.where(high, tau - H, tau))
    started = s >= 0.0
    k = jnp.where(started, k, -1.0)
    span = tstop - t0

    pair = jnp.asarray(FOOT_PAIR, dtype=dtype)  # (4,)
    k_pair = jnp.mod(k, 2.0)
    stepping = started & _stepped(k, span, H)
    swing = stepping & (k_pair == pair) & (tau >= ts)
    phase = jnp.where(swing, jnp.clip((tau - ts) / tw, 0.0, 1.0), 0.0)

    # next liftoff: first half-cycle kc >= max(k, 0) of the foot's parity whose liftoff is after t
    kb = jnp.maximum(k, 0.0)
    tau_b = jnp.where(started, tau, s)  # time since the start of half-cycle kb (< 0 before start)
    kc = kb + jnp.mod(pair - kb, 2.0)  # (4,)
    kc = jnp.where(started & (kc == k) & (tau >= ts), kc + 2.0, kc)
    dt_lo = (kc - kb) * H + ts - tau_b
    has_next = _stepped(kc, span, H)
    t_to_liftoff = jnp.where(has_next, dt_lo, jnp.inf)
    t_to_touchdown = jnp.where(swing, H - tau, jnp.where(has_next, dt_lo + tw, jnp.inf))

    return GaitState(
        swing=swing,
        swing_phase=phase,
        step_index=k.astype(jnp.int32),
        t_in_half=jnp.where(started, tau, t),
        t_to_liftoff=t_to_liftoff,
        t_to_touchdown=t_to_touchdown,
        stepping=stepping,
        swing_pair=jnp.where(started, k_pair, -1.0).astype(jnp.int32),
    )
