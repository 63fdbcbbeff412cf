"""Sections beyond the ANOVA: success rates, controller variants against the reference, and, for a campaign's
results table, R from the simulator against the QP's plan, clearance and QP convergence."""

from __future__ import annotations

import numpy as np
import pandas as pd

from wbc_jax.analysis import ablation, sensitivity, stats, success
from wbc_jax.analysis.report.document import Doc, fmt

QP_FLAG = "qp_flag_fraction"  # a campaign's results.csv column: the report's QP convergence section
QP_FLAG_LINE = 0.001  # wbc_jax.metrics.paper.QP_FLAG_FRACTION (not imported: the report stays JAX-free)
R_PLAN = "R_plan"  # a campaign's results.csv column: the report's "R: simulator vs planned forces" section
R_SOURCE_COLUMNS = (("R", "R (simulator)"), ("R_plan", "R (QP plan)"),
                    ("boundary_fraction", "rule share, simulator [%]"),
                    ("boundary_cone_fraction", "of which on/outside the cone [%]"),
                    ("boundary_fraction_plan", "rule share, plan [%]"),
                    ("boundary_cone_fraction_plan", "of which on/outside the cone, plan [%]"))
CLEARANCE = "min_clearance_mm"  # a campaign's results.csv column: the report's clearance section


def success_sections(d: Doc, extra: dict, factors, alpha: float) -> None:
    """The report's success-rate tables and, for an ablation factor, the comparisons with the reference."""
    d.h(2, "Success rate (all runs)")
    d.p("Share of runs with success = True per factor level and per pair of factors, pooled over the other "
        "factors and the repetitions (failed runs included; cells: successes/runs (rate)); "
        f"{success.CONFIDENCE * 100:g} % interval: Clopper-Pearson (exact binomial), so 0 failures in n runs still "
        "bounds the failure rate.")
    lv = extra["by_level"]
    d.table(pd.DataFrame({"factor": lv["factor"], "level": lv["level"].map(lambda v: fmt(v, "g")),
                          "successes/runs": [f"{s}/{n}" for s, n in zip(lv["successes"], lv["runs"])],
                          "rate [%]": (100 * lv["rate"]).map(lambda v: fmt(v, ".1f")),
                          f"{success.CONFIDENCE * 100:g} % interval [%]": [
                              "" if n == 0 else f"{100 * a:.1f}-{100 * b:.1f}"
                              for a, b, n in zip(lv["ci_low"], lv["ci_high"], lv["runs"])]}))
    for (a, b), t in extra["by_pair"].items():
        d.h(3, f"{a} × {b}")
        d.table(success.wide(t, a, b, fmt=lambda v: fmt(v, "g")))
    if len(extra["ablation"]):
        _ablation_section(d, extra["ablation"], alpha)


def _ablation_section(d: Doc, t: pd.DataFrame, alpha: float) -> None:
    """Each level of an ablation factor against the reference (:func:`wbc_jax.analysis.ablation.compare`)."""
    d.h(2, "Controller variants against the reference")
    d.p("Each level of " + ", ".join(f"`{f}`" for f in pd.unique(t["factor"])) + " against the reference "
        "(" + ", ".join(f"{f} = {ablation.REFERENCE[f]}" for f in pd.unique(t["factor"])) + "), pooled over "
        "the other factors: Welch's t test and the Mann-Whitney U test on max slip [mm] and R (successful "
        "runs), Fisher's exact test on success (all runs); two-sided, Bonferroni over the levels compared.")
    d.ul(ablation.answers(t, alpha))
    d.table(pd.DataFrame({
        "factor": t["factor"], "level": t["level"].map(lambda v: fmt(v, "g")), "metric": t["metric"],
        "test": t["test"], "n": t["n"], "n ref": t["n_ref"], "value": t["value"].map(fmt),
        "ref value": t["value_ref"].map(fmt), "statistic": t["statistic"].map(fmt),
        "p": t["p"].map(lambda v: fmt(v, ".3g")), "p Bonferroni": t["p_bonf"].map(lambda v: fmt(v, ".3g")),
        f"detectable ({sensitivity.POWER * 100:g} %)": t["detectable"].map(fmt),
        "differs": ["yes" if x else "no" for x in t["differs"]]}))


def campaign_sections(d: Doc, df: pd.DataFrame, factors) -> None:
    """The sections of a campaign's columns present in ``df``: R sources, clearance, QP convergence."""
    if R_PLAN in df.columns:
        _r_sources_section(d, df, factors)
    if CLEARANCE in df.columns:
        _clearance_section(d, df, factors)
    if QP_FLAG in df.columns:
        _qp_section(d, df, factors)


def r_sources(df: pd.DataFrame, factors) -> pd.DataFrame:
    """Per cell (successful runs), the means of R from the simulator's and from the QP's planned object forces and
    the boundary rule's shares (columns of :data:`R_SOURCE_COLUMNS` present in ``df``; shares as fractions)."""
    ok = stats.successful(df)
    cols = [c for c, _ in R_SOURCE_COLUMNS if c in ok.columns]
    num = ok[list(factors)].join(ok[cols].apply(pd.to_numeric, errors="coerce"))
    out = num.groupby(list(factors), sort=True)[cols].mean().reset_index()
    out.insert(len(factors), "n", num.groupby(list(factors), sort=True).size().to_numpy())
    return out


def _r_sources_section(d: Doc, df: pd.DataFrame, factors) -> None:
    """R from the simulator's contact forces next to R from the QP's planned object forces, with the boundary
    rule's share of each (the fraction of the window's samples whose 1/H the rule set to 0)."""
    t = r_sources(df, factors)
    d.h(2, "R: simulator forces vs the QP's planned forces (successful runs)")
    d.p("R (simulator): the paper's robustness metric of the contact forces MuJoCo applies to the object (every "
        "physics step); R (QP plan): the same metric of the object contact forces the whole-body QP planned "
        "(F_c = E_c Lambda_b per contact, every control step). Rule share: the fraction of the metric window's "
        "samples whose integrand 1/H the boundary rule set to 0 (a contact without load, or a force on or outside "
        "the circular cone); 'on/outside the cone' is the part of a share with every contact loaded. "
        "Means per cell.")
    shown = t[list(factors)].map(lambda v: fmt(v, "g"))
    shown["n"] = t["n"]
    for c, name in R_SOURCE_COLUMNS:
        if c in t.columns:
            shown[name] = t[c].map(lambda v: fmt(100 * v, ".2f")) if "[%]" in name else t[c].map(fmt)
    d.table(shown)


def _clearance_section(d: Doc, df: pd.DataFrame, factors) -> None:
    """Per cell, the smallest clearance over its runs (all runs, failed ones included) with its time and pair."""
    c = pd.to_numeric(df[CLEARANCE], errors="coerce")
    d.h(2, "Clearance (all runs)")
    d.p("Smallest signed distance between a non-foot robot geom and the floor, blocks or wall over each run [mm] "
        "(negative: penetration; inf: none reported, e.g. on the Warp backend without penetration); per cell the "
        "run with the smallest.")
    rows = []
    for key, g in df.assign(_c=c).groupby(factors, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        i = g["_c"].idxmin() if g["_c"].notna().any() else g.index[0]
        r = g.loc[i]
        pair = r.get("min_clearance_pair", "")
        rows.append([*(fmt(v, "g") for v in key), "inf" if r["_c"] == np.inf else fmt(r["_c"], ".3f"),
                     int(r["run"]) if "run" in g else "", fmt(r.get("min_clearance_s", np.nan), ".3f"),
                     pair if isinstance(pair, str) else ""])
    d.table(pd.DataFrame(rows, columns=[*factors, "min clearance [mm]", "run", "at [s]", "pair"]))


def _qp_section(d: Doc, df: pd.DataFrame, factors) -> None:
    """Per cell, the share of control steps whose QP ended outside its tolerance (all runs): mean and worst run."""
    f = pd.to_numeric(df[QP_FLAG], errors="coerce")
    d.h(2, "QP convergence (all runs)")
    d.p("Share of each run's control steps whose whole-body QP ended its ADMM iterations (the solver's cap "
        "included) outside its tolerance (OSQP's test); a run above "
        f"{100 * QP_FLAG_LINE:g} % is `qp_flagged`. Per cell: mean over the runs, the worst run, how many runs are "
        "flagged, and the ADMM iterations per control step (mean over the runs' means, most in one step).")
    cols = {"_f": f}
    for k in ("qp_iters_mean", "qp_iters_max"):
        cols[k] = pd.to_numeric(df[k], errors="coerce") if k in df else np.nan
    g = df.assign(**cols).groupby(factors, sort=True)
    rows = [[*(fmt(v, "g") for v in (key if isinstance(key, tuple) else (key,))), fmt(100 * s["_f"].mean(), ".3f"),
             fmt(100 * s["_f"].max(), ".3f"), f"{int((s['_f'] > QP_FLAG_LINE).sum())}/{len(s)}",
             fmt(s["qp_iters_mean"].mean(), ".1f"), fmt(s["qp_iters_max"].max(), "g")] for key, s in g]
    d.table(pd.DataFrame(rows, columns=[*factors, "mean [%]", "worst run [%]", "runs flagged", "iterations mean",
                                        "iterations max"]))
