"""Controller variants for ablation studies: which parts of the transport WBC are on, as per-run data.

A variant is three 0/1 switches (:class:`Variant`) carried in each run's ``ControlState``
(:mod:`wbc_jax.control.transport`). They are data, not static structure: one compiled rollout serves every
variant and a campaign may mix variants in one batched rollout (the ``variant`` and ``observer`` factors of
:mod:`wbc_jax.campaign.factors`). A switch at 1 leaves the controller exactly as without switches (products with
1.0 and unchanged bounds), so ``full`` reproduces earlier results bit for bit.

- ``tray_cone`` 0: the object's contact forces leave the whole-body QP. Their multipliers Lambda_b (the
  friction-pyramid rows (12) of the object contacts, i.e. the tray friction cone) are pinned to 0 and the
  object-wrench cost (the F_b,ref rows of (7)-(8)) gets weight 0; the tray still follows the object's
  reference through (11). The controller then neither respects the object's friction cone nor plans the
  object's load in its torques (the observer, when on, sees the load as an external wrench). Freeing the
  multipliers instead (bounds +-inf) would let the QP pull and push on the object at will: an unbounded
  phantom support of the robot, not a controller.
- ``observer`` 0: the momentum observer's gain is 0, so its estimated external wrench stays 0.
- ``posture`` 0: the arm posture task's weight is 0 (the null space of (11) is free).

This module is plain Python (no JAX): the spec validator reads :data:`VARIANTS` without importing JAX.
"""

from __future__ import annotations

from typing import NamedTuple


class Variant(NamedTuple):
    """Ablation switches of one run, each () float 1.0 (on) or 0.0 (off); leaves may carry a run axis."""

    tray_cone: object  # object contact forces with their friction cone and the object-wrench cost in the QP
    observer: object  # momentum observer (its gain k_obs is multiplied by this)
    posture: object  # arm posture task (its weight w_post is multiplied by this)


VARIANTS = {
    "full": Variant(1.0, 1.0, 1.0),
    "no_tray_cone": Variant(0.0, 1.0, 1.0),
    "no_observer": Variant(1.0, 0.0, 1.0),
    "no_posture": Variant(1.0, 1.0, 0.0),
}
FULL = VARIANTS["full"]
