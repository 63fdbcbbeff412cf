"""MJX physics split so the controller reads fresh kinematics without a second forward pass.

``mjx.step`` = forward (position, velocity, actuation, acceleration, constraint solve) + integrate.
:func:`sense` runs the position and velocity stages; the controller reads M, bias forces,
Jacobians and contacts from its output; :func:`advance` finishes that same forward pass with the
controller's torques and integrates. Extra physics substeps per control step (zero-order hold) use
plain ``mjx.step``.
"""

from __future__ import annotations

from wbc_jax.model import mjx


def sense(m, d):
    """Position- and velocity-dependent stages of the forward pass."""
    d = mjx.fwd_position(m, d)
    return mjx.fwd_velocity(m, d)


def advance(m, d, ctrl, n_substeps: int = 1):
    """Finish the forward pass of a sensed ``d`` with ``ctrl``, integrate, then n_substeps - 1 more steps.

    Args:
        m: mjx.Model; d: mjx.Data returned by :func:`sense`; ctrl: (nu,) actuator torques [N m].
        n_substeps: physics steps per control step (static).
    """
    d = d.replace(ctrl=ctrl)
    d = mjx.fwd_actuation(m, d)
    d = mjx.fwd_acceleration(m, d)
    d = mjx.solve(m, d)
    d = mjx.euler(m, d)
    for _ in range(n_substeps - 1):
        d = mjx.step(m, d)
    return d
