"""The transport paper's metrics R, T, S as a campaign's report defines and shows them: formula, unit, direction,
and the unit each is shown in (T: mm; a campaign's results.csv keeps metres).

The definitions are those of ``wbc_jax.metrics.paper`` (not imported: the report stays JAX-free).
"""

from __future__ import annotations

from typing import NamedTuple

import pandas as pd

from wbc_jax.analysis.report.document import Doc


class MetricDef(NamedTuple):
    """One metric of a campaign's results table."""

    name: str  # what it measures
    unit: str  # the unit the report shows it in
    scale: float  # shown value = results.csv value x scale
    formula: str  # its definition
    direction: str  # which way is better, and why


PAPER_METRICS = {
    "R": MetricDef("robustness", "rad²", 1.0,
                   "R = (1/T_win) ∫ 1/H dt, H = (1/λ) Σ_i 1/((θ_i − α_i)(θ_i + α_i)), λ = 4, θ_i = atan(μ) the "
                   "friction cone's half-angle, α_i the angle between the force on the object's contact i and its "
                   "normal",
                   "higher is better: the contact forces further inside their friction cones (at most θ²; an "
                   "unloaded contact or a force on or outside its cone counts 1/H = 0)"),
    "T": MetricDef("tracking error", "mm", 1e3,
                   "T = (1/T_win) ∫ ‖p_ref − p‖ dt, p the object's centre of mass, p_ref its planned path",
                   "lower is better: the object closer to its planned path (results.csv: metres)"),
    "S": MetricDef("smoothness", "s²/m", 1.0,
                   "S = T_win / ∫ ‖v̇_b‖ dt, v̇_b the acceleration of the object's centre of mass",
                   "higher is better: a smoother transport (less acceleration of the object in total)"),
}
WINDOW = ("T_win: the metric window, the planned path's duration plus the settle time [s]; the integrals run over "
          "the simulation's physics steps inside it.")


def labels(metrics, is_campaign: bool) -> dict[str, str]:
    """Metric -> its label in tables and figures: "T [mm]" for a campaign's paper metrics, else the name."""
    return {m: f"{m} [{PAPER_METRICS[m].unit}]" if is_campaign and m in PAPER_METRICS else m for m in metrics}


def in_display_units(data: pd.DataFrame, metrics, is_campaign: bool) -> pd.DataFrame:
    """``data`` with a campaign's paper metrics scaled to the units the report shows (T: m -> mm)."""
    scaled = {m: data[m] * PAPER_METRICS[m].scale for m in metrics
              if is_campaign and m in PAPER_METRICS and PAPER_METRICS[m].scale != 1.0}
    return data.assign(**scaled) if scaled else data


def units(metrics, is_campaign: bool) -> dict[str, str]:
    """Metric -> the unit of its numbers in the report (a campaign's paper metrics only)."""
    return {m: PAPER_METRICS[m].unit for m in metrics if is_campaign and m in PAPER_METRICS}


def metrics_section(d: Doc, metrics) -> None:
    """The definitions of the paper metrics among ``metrics``: formula, unit, direction."""
    shown = [m for m in metrics if m in PAPER_METRICS]
    if not shown:
        return
    d.h(2, "Metrics")
    d.ul([f"{m}, {PAPER_METRICS[m].name} [{PAPER_METRICS[m].unit}]: {PAPER_METRICS[m].formula}; "
          f"{PAPER_METRICS[m].direction}." for m in shown])
    d.p(WINDOW)
