"""One metric's section of the report: its model, ANOVA table, assumption tests, simple main effects,
interaction shapes and descriptives per factor level."""

from __future__ import annotations

import pandas as pd

from wbc_jax.analysis import interaction, sensitivity
from wbc_jax.analysis.report.document import Doc, fmt

RESULT = {True: "ok", False: "REJECTED (p < {alpha:g})", None: "not run"}  # an assumption test's verdict


def metric_section(d: Doc, m: str, r: dict, level_means: pd.DataFrame, alpha: float) -> None:
    """The section of metric ``m`` (its label; ``r``: its entry of :func:`wbc_jax.analysis.stats.analyze`'s
    ``metrics``; ``level_means``: its rows of the level means)."""
    fit = r["fit"]
    d.h(2, f"Metric {m}")
    d.p(f"Model {fit.formula}; n = {fit.n}; residual df = {fmt(fit.df_resid, 'g')}; MSE = {fmt(fit.mse)}.")
    if not fit.reliable:
        d.p("**F tests unreliable**: " + "; ".join(fit.unreliable_reasons)
            + ". F, p and partial eta squared are omitted below (anova.json keeps the raw numbers).")
    d.h(3, f"ANOVA (type {fit.ss_type} SS)")
    d.table(_anova_table(fit, r["significant"]))
    _sensitivity(d, fit, level_means, alpha)
    d.h(3, "Assumptions")
    d.table(pd.DataFrame([{
        "test": a["test"], "assumption": a["assumption"], "statistic": fmt(a["statistic"]), "p": fmt(a["p"], ".3g"),
        "result": RESULT[a["ok"]].format(alpha=alpha), "note": a["note"],
    } for a in r["assumptions"]]))
    if r["simple_effects"]:
        d.h(3, "Simple main effects")
        for s in r["simple_effects"]:
            _simple_effects(d, s)
    elif fit.reliable:
        d.p("No significant two-way interaction: no simple main effects.")
    if r["emms"]:
        d.h(3, "Interaction shapes")
        d.p("Disordinal: two lines of the interaction plot cross within the plotted range (the order of the line "
            "factor's levels reverses across the x-axis levels; EMMs); ordinal otherwise.")
        d.table(pd.DataFrame(interaction.shapes(r["emms"])))
    d.h(3, "Descriptives per factor level (successful runs)")
    lm = level_means
    d.table(pd.DataFrame({"factor": lm["factor"], "level": lm["level"].map(lambda v: fmt(v, "g")),
                          "mean": lm["mean"].map(fmt), "SD": lm["sd"].map(fmt), "n": lm["n"]}))


def _sensitivity(d: Doc, fit, level_means: pd.DataFrame, alpha: float) -> None:
    """The smallest main effects the F tests detect with :data:`wbc_jax.analysis.sensitivity.POWER` probability
    (factors with the same range shown together)."""
    by_range: dict[str, list[str]] = {}
    for f, v in sensitivity.main_effect_ranges(fit, level_means, alpha).items():
        if v is not None:
            by_range.setdefault(fmt(v), []).append(f)
    if by_range:
        d.p(f"Sensitivity: at alpha = {alpha:g}, with this MSE and n, the F test detects a main effect with "
            f"{sensitivity.POWER * 100:g} % probability when two of its level means are at least "
            + "; ".join(f"{v} apart ({', '.join(fs)})" for v, fs in by_range.items())
            + ", the others between them; a smaller effect may go undetected.")


def _anova_table(fit, significant: list[str]) -> pd.DataFrame:
    """The ANOVA table as shown: F, p and partial eta squared left empty when the F tests are unreliable."""
    t = fit.table
    return pd.DataFrame({
        "source": t["source"], "SS": t["sum_sq"].map(fmt), "df": t["df"].map(lambda v: fmt(v, "g")),
        "MS": t["mean_sq"].map(fmt),
        "F": t["F"].map(fmt) if fit.reliable else "",
        "p": t["p"].map(lambda v: fmt(v, ".3g")) if fit.reliable else "",
        "partial η²": t["partial_eta_sq"].map(lambda v: fmt(v, ".3f")) if fit.reliable else "",
        "sig.": ["*" if s in significant else "" for s in t["source"]],
    })


def _simple_effects(d: Doc, s: dict) -> None:
    """One :func:`wbc_jax.analysis.stats.simple_effects` result: its F tests and pairwise comparisons."""
    d.h(4, f"{s['effect']} at each level of {s['by']}")
    d.p(s["method"] + ".")
    te = s["tests"].copy()
    te[s["by"]] = te[s["by"]].map(lambda v: fmt(v, "g"))
    for c, spec in (("F", ".4g"), ("p", ".3g"), ("partial_eta_sq", ".3f"), ("df2", "g")):
        te[c] = te[c].map(lambda v, spec=spec: fmt(v, spec))
    d.table(te)
    pr = s["pairs"].copy()
    for c in pr.columns:
        spec = "g" if c in (s["by"], "level_a", "level_b", "df") else (".3g" if c.startswith("p_") else ".4g")
        pr[c] = pr[c].map(lambda v, spec=spec: fmt(v, spec))
    d.table(pr)
