"""What the campaign needs to know of each controller (``[campaign] controller``) without JAX: its results columns,
the report's and the manifest's metrics, the metrics ``regress`` compares with their default tolerance bands, and
the factors a spec may vary with it. The controllers themselves: :mod:`wbc_jax.rollout.controllers`.
"""

from __future__ import annotations

from typing import NamedTuple

from wbc_jax.campaign.factors import PLUGIN_PREFIX

# the report's responses (wbc_jax.analysis.report.inputs.CAMPAIGN_METRICS and TROT_METRICS, which read a results.csv
# without its spec; not imported: spec loading stays free of pandas)
CAMPAIGN_METRICS = ("R", "T", "S")
TROT_METRICS = ("speed_mps", "cp_err_x_rms_mm", "cp_err_y_rms_mm", "roll_amp_deg", "pitch_amp_deg")


class ControllerInfo(NamedTuple):
    """One controller's campaign facts."""

    columns: tuple  # results.csv metric columns (after the factors, rep, seed and success)
    report: tuple  # the report's ANOVA responses
    means: tuple  # manifest.json metric_means
    regress: dict  # regress's metrics: name -> (rel, abs) default tolerance band
    factors: tuple | None  # factors a spec may vary; None: every factor of wbc_jax.campaign.factors (gain.<leaf>
    #                        included) but those of CENTROIDAL_ONLY


_COMMON = ("fell", "trunk_low", "body_contact", "nonfinite", "overflow", "qp_flagged", "qp_flag_fraction",
           "qp_iters_mean", "qp_iters_max", "solver_cap_fraction", "fail_reason", "failure_s", "first_contact_s",
           "first_contact", "min_clearance_mm", "min_clearance_s", "min_clearance_pair")

CONTROLLERS = {
    "transport": ControllerInfo(
        columns=("R", "T", "S", "R_plan", "max_slip_mm", "fell", "trunk_low", "body_contact", "dropped", "slid",
                 "hit_wall", "qp_flagged", "qp_flag_fraction", "qp_iters_mean", "qp_iters_max", "nonfinite",
                 "overflow", "solver_cap_fraction", "boundary_fraction", "boundary_cone_fraction",
                 "boundary_fraction_plan", "boundary_cone_fraction_plan", "final_err_mm", "fail_reason", "failure_s",
                 "first_contact_s", "first_contact", "window_s", "min_clearance_mm", "min_clearance_s",
                 "min_clearance_pair"),
        report=CAMPAIGN_METRICS, means=("R", "T", "S", "max_slip_mm"),
        regress={"R": (0.02, 1e-3), "T": (0.05, 2e-5), "S": (0.05, 1e-3), "max_slip_mm": (0.10, 0.05)},
        factors=None),
    "centroidal": ControllerInfo(
        columns=("speed_mps", "cp_err_x_rms_mm", "cp_err_y_rms_mm", "cp_err_x_max_mm", "roll_amp_deg",
                 "pitch_amp_deg", "yaw_amp_deg", "max_tau_ratio", "max_qp_tau_excess_Nm", "foot_slip_mm",
                 "distance_m", "planned_distance_m", "walked", "min_trunk_z_m", "object_slip_mm", *_COMMON),
        report=TROT_METRICS, means=TROT_METRICS,
        regress={"speed_mps": (0.02, 2e-3), "cp_err_x_rms_mm": (0.05, 0.2), "cp_err_y_rms_mm": (0.05, 0.2),
                 "roll_amp_deg": (0.05, 0.02), "pitch_amp_deg": (0.05, 0.02)},
        factors=("m", "mu", "d", "ground_mu", "speed", "push_N", "qvel_noise_std", "mass_error")),
}


CENTROIDAL_ONLY = ("mass_error",)  # factors of the centroidal controller alone


def may_vary(name: str, factor: str) -> bool:
    """Controller ``name`` accepts the factor ``factor`` (a plug-in's ``plugin.<field>`` whichever its family)."""
    if factor.startswith(PLUGIN_PREFIX):
        return True
    allowed = CONTROLLERS[name].factors
    return factor not in CENTROIDAL_ONLY if allowed is None else factor in allowed


def info(campaign: dict) -> ControllerInfo:
    """The :class:`ControllerInfo` of a spec's ``campaign`` table (or a manifest's ``spec.campaign``)."""
    return CONTROLLERS[campaign.get("controller", "transport")]
