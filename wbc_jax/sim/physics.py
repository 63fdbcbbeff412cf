"""MJX physics split so the controller reads fresh kinematics without a second forward pass.

``mjx.step`` = forward (position, velocity, actuation, acceleration, constraint solve) + integrate.
:func:`sense` runs the position and velocity stages; the controller reads M, bias forces,
Jacobians and contacts from its output; :func:`finish` completes that same forward pass with the
controller's torques and integrates: one physics step. A control period of ``n_substeps`` physics steps
(zero-order hold: ``ctrl`` and ``xfrc_applied`` stay as set) is :func:`finish` followed by
``n_substeps - 1`` plain ``mjx.step`` calls in a ``lax.scan`` (:func:`advance`; the rollout runs its own scan
that also samples its physics-rate monitors after every step, ``wbc_jax.sim.rollout.physics_period``).

After any of these steps, ``d.contact`` (and ``efc_force``) belong to the positions at the *start* of that
step (collision runs before integration): after :func:`finish` they are the sensed ``d``'s contacts.
"""

from __future__ import annotations

import jax

from wbc_jax.sim.model import mjx


def sense(m, d):
    """Position- and velocity-dependent stages of the forward pass."""
    d = mjx.fwd_position(m, d)
    return mjx.fwd_velocity(m, d)


def finish(m, d, ctrl):
    """One physics step from a sensed ``d``: finish its forward pass with ``ctrl`` and integrate.

    Args:
        m: mjx.Model; d: mjx.Data returned by :func:`sense`; ctrl: (nu,) actuator torques [N m].

    Returns:
        mjx.Data one timestep later (``ctrl`` kept, contacts and constraint forces of the step's start).
    """
    d = d.replace(ctrl=ctrl)
    d = mjx.fwd_actuation(m, d)
    d = mjx.fwd_acceleration(m, d)
    d = mjx.solve(m, d)
    return mjx.euler(m, d)


def hold(m, d, n: int):
    """``n`` (static, >= 0) further plain ``mjx.step`` calls with ``d.ctrl`` held (``lax.scan``, one traced step)."""
    if n <= 0:
        return d
    return jax.lax.scan(lambda d, _: (mjx.step(m, d), None), d, None, length=n)[0]


def advance(m, d, ctrl, n_substeps: int = 1):
    """Finish the forward pass of a sensed ``d`` with ``ctrl``, integrate, then n_substeps - 1 more steps.

    Args:
        m: mjx.Model; d: mjx.Data returned by :func:`sense`; ctrl: (nu,) actuator torques [N m].
        n_substeps: physics steps per control step (static, >= 1); the torques are held over all of them.
    """
    return hold(m, finish(m, d, ctrl), n_substeps - 1)
