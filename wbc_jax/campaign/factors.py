"""The factors a campaign spec may vary (``[factors]`` of ``sweeps/*.toml``): names, kinds of level, ranges, the
order of the design, and where a run's value comes from when the factor is not varied.

A spec varies 1 to :data:`MAX_FACTORS` of these, each with at least 2 distinct levels; the design is the product
of their levels in :func:`design_order` (the registry's order, then ``gain.*`` leaves in ``TransportGains``
order), whatever the order in the file (the spec hash does not see the file's order either). The paper's
m, mu, d therefore keep their design order and run seeds.

Kinds of level:

- ``number``: a finite number in the factor's range (``lo < value <= hi`` when ``lo_open``, else
  ``lo <= value <= hi``), in the factor's unit.
- ``bool``: ``true``/``false`` or 1/0 (stored as 1/0: the results column holds 1/0).
- ``choice``: one of the factor's strings.

``gain.<leaf>`` (any leaf of :class:`wbc_jax.control.transport.TransportGains`, e.g. ``gain.kp_obj``) is a
``number`` factor: a multiplier of that leaf of the campaign's gains (the defaults or ``--gains``), 0..100.
``plugin.<field>`` (a float or bool field of the spec's ``[plugin]`` class, :mod:`wbc_jax.campaign.spec_controller`)
is a ``number`` (any finite value) or ``bool`` factor: the field's value per run, set in the controller's state.

Plain Python (no JAX): the spec validator reads it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from wbc_jax.control.variants import VARIANTS

MAX_FACTORS = 5
GAIN_PREFIX = "gain."
PLUGIN_PREFIX = "plugin."
# TransportGains._fields (wbc_jax.control.transport), listed here so that loading a spec needs no JAX;
# tests/test_factors.py checks that they agree
GAIN_LEAVES = ("kp_com", "kd_com", "kp_rot", "kd_rot", "kp_obj", "kd_obj", "kp_obj_rot", "kd_obj_rot", "kp_sw",
               "kd_sw", "kd_stance", "kp_post", "kd_post", "w_com", "w_obj_f", "w_obj_t", "w_post", "r_vdot",
               "r_lam", "r_slack", "k_obs", "f_min", "f_max", "tau_margin")
OBJECT = ("m", "mu", "d")  # the paper's factors: always columns of results.csv
REGULARIZATION = ("r_vdot", "r_lam")  # gains that must stay > 0 (the QP's regularization: zero makes it singular)


@dataclass(frozen=True)
class FactorDef:
    """One factor: ``kind`` ("number", "bool" or "choice"); for numbers the range ``lo``..``hi`` (``lo``
    excluded when ``lo_open``) in ``unit``; for choices the allowed strings; ``fixed``: the spec key (or rule)
    that gives a run's value when the factor is not varied."""

    kind: str
    fixed: str
    lo: float = 0.0
    hi: float = 0.0
    lo_open: bool = False
    unit: str = ""
    choices: tuple = ()


REGISTRY = {
    "m": FactorDef("number", "campaign.m", 0.0, 20.0, True, "[kg]"),
    "mu": FactorDef("number", "campaign.mu", 0.0, 5.0, True, "[-]"),
    "d": FactorDef("number", "campaign.d", 0.008, 0.2, True, "[m]"),
    "ground_mu": FactorDef("number", "campaign.ground_mu", 0.0, 5.0, True, "[-]"),
    "speed": FactorDef("number", "campaign.speed", 0.01, 0.5, False, "[m/s]"),
    "obj_accel": FactorDef("number", "campaign.obj_accel", 0.0, 20.0, False, "[m/s^2]"),
    "push_N": FactorDef("number", "perturbations.push_max_N", 0.0, 200.0, False, "[N]"),
    "qvel_noise_std": FactorDef("number", "perturbations.qvel_noise_std", 0.0, 1.0, False, "[m/s, rad/s]"),
    "observer": FactorDef("bool", "on (unless the variant turns it off)"),
    "variant": FactorDef("choice", "campaign.variant", choices=tuple(VARIANTS)),
    "mass_error": FactorDef("number", "campaign.mass_error", -0.5, 1.0, True, "[-] fraction (centroidal)"),
}
GAIN = FactorDef("number", "1 (the campaign's gains)", 0.0, 100.0, False, "[x the leaf's value]")


def plugin_factor(default) -> FactorDef | None:
    """The factor of a plug-in field whose default is ``default``: bool or number (a float field); None for
    another type."""
    fixed = "plugin.<field> (the [plugin] table's value or the class's default)"
    if isinstance(default, bool):
        return FactorDef("bool", fixed)
    if isinstance(default, float):
        return FactorDef("number", fixed, -math.inf, math.inf, False, "[the field's unit]")
    return None


def factor_def(name: str, plugin_fields: dict | None = None) -> FactorDef | None:
    """The definition of factor ``name`` (``gain.<leaf>`` and, with the spec's plug-in fields ``plugin_fields``
    (name -> default), ``plugin.<field>`` included); None for an unknown name."""
    if name.startswith(GAIN_PREFIX):
        return GAIN if name[len(GAIN_PREFIX):] in GAIN_LEAVES else None
    if name.startswith(PLUGIN_PREFIX):
        field = name[len(PLUGIN_PREFIX):]
        return plugin_factor(plugin_fields[field]) if plugin_fields and field in plugin_fields else None
    return REGISTRY.get(name)


def known_names() -> str:
    """The accepted names, for error messages."""
    return (", ".join(REGISTRY) + f", {GAIN_PREFIX}<leaf> (leaf: {', '.join(GAIN_LEAVES)}), {PLUGIN_PREFIX}<field> "
            "(a float or bool field of the [plugin] class)")


def design_order(names, plugin_fields=()) -> list[str]:
    """``names`` (known factors) in design order: the registry's, then ``gain.*`` in ``GAIN_LEAVES`` order, then
    ``plugin.*`` in the order of ``plugin_fields`` (the class's fields)."""
    order = [*REGISTRY, *(GAIN_PREFIX + leaf for leaf in GAIN_LEAVES), *(PLUGIN_PREFIX + f for f in plugin_fields)]
    return sorted(names, key=order.index)
