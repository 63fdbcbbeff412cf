"""The envelope of a campaign with a controller ``variant`` factor: where each variant succeeds, and where the
reference (``full``) does better than an ablated variant.

A *region* is one combination of the levels of the two map axes (:func:`map_axes`: two of the non-variant factors),
pooled over the other factors' levels and the repetitions. Per variant and region: runs, successes, the success
rate, the median and largest max slip. A run is *good* when it succeeds and its max slip is at most
:data:`SLIDE_MM` (a run that slides further counts as failing the transport even if it ends within the flags).

Per region, ``full`` against another variant: Fisher's exact test (two-sided) on the 2 x 2 table of good / not good
runs, and the Mann-Whitney U test (two-sided) on max slip over every run with a finite value (a failed run's slip is
that up to its failure). ``p_bonf`` multiplies by the number of regions of the map (capped at 1). The
*boundary* of a variant along the column axis, per row level: the largest column level up to which every region
has a success rate of at least :data:`HOLDS_RATE`, and the first level whose rate is below :data:`STOPS_RATE`.

Plain pandas and scipy (no JAX).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pandas as pd

from wbc_jax.analysis.table import levels, success_column

REFERENCE = "full"
SLIDE_MM = 5.0  # [mm] a max slip above this counts as sliding
HOLDS_RATE = 0.9  # a region's success rate at or above this: the variant holds there
STOPS_RATE = 0.5  # below this: the variant has stopped succeeding
REGION_P = 0.01  # Fisher's p (Bonferroni over the map's regions) below which a region's difference counts
# the map axes, in order of preference, among the varied non-variant factors
AXIS_ORDER = ("mu", "obj_accel", "speed", "push_N", "m", "d", "ground_mu", "qvel_noise_std")


class Comparison(NamedTuple):
    """``full`` against one variant over a map (:func:`compare_regions`)."""

    variant: str
    table: pd.DataFrame  # one row per region: COMPARE_COLUMNS
    found: pd.DataFrame  # the regions where full is good more often with p_bonf < REGION_P


COMPARE_COLUMNS = ["runs_ref", "runs", "good_ref", "good", "rate_ref", "rate", "fisher_odds", "fisher_p",
                   "fisher_p_bonf", "slip_median_ref", "slip_median", "mwu_u", "mwu_p", "mwu_p_bonf"]


def has_envelope(df: pd.DataFrame, factors) -> bool:
    """The table has a ``variant`` factor with ``full`` and another level, and two other varied factors."""
    return ("variant" in factors and REFERENCE in set(df["variant"].astype(str)) and df["variant"].nunique() > 1
            and map_axes(df, factors) is not None)


def map_axes(df: pd.DataFrame, factors) -> tuple[str, str] | None:
    """(row axis, column axis): the first two varied factors other than ``variant`` in :data:`AXIS_ORDER` (then the
    table's order); None with fewer than two."""
    others = [f for f in factors if f != "variant" and df[f].nunique() > 1]
    ranked = sorted(others, key=lambda f: (AXIS_ORDER.index(f) if f in AXIS_ORDER else len(AXIS_ORDER),
                                           others.index(f)))
    return (ranked[0], ranked[1]) if len(ranked) >= 2 else None


def _frame(df: pd.DataFrame) -> pd.DataFrame:
    out = df.copy()
    out["variant"] = out["variant"].astype(str)
    out["_ok"] = success_column(df).to_numpy()
    out["_slip"] = pd.to_numeric(df["max_slip_mm"], errors="coerce") if "max_slip_mm" in df else np.nan
    out["_good"] = out["_ok"] & (out["_slip"].fillna(np.inf) <= SLIDE_MM)
    return out


def regions(df: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Per (variant, a, b): runs, successes, rate, good (successes with max slip <= SLIDE_MM), slip_median,
    slip_max [mm] (finite values of every run)."""
    f = _frame(df)
    g = f.groupby(["variant", a, b], sort=True)
    out = pd.DataFrame({"runs": g.size(), "successes": g["_ok"].sum().astype(int), "good": g["_good"].sum().astype(int),
                        "slip_median": g["_slip"].median(), "slip_max": g["_slip"].max()}).reset_index()
    out["rate"] = out["successes"] / out["runs"]
    return out


def difference(t: pd.DataFrame, a: str, b: str, variant: str, value: str = "rate") -> pd.DataFrame:
    """Per region: ``full``'s ``value`` minus ``variant``'s (long table a, b, value)."""
    ref = t[t["variant"] == REFERENCE].set_index([a, b])[value]
    other = t[t["variant"] == variant].set_index([a, b])[value]
    return (ref - other).rename(value).reset_index()


def _fisher(good_ref, n_ref, good, n):
    from scipy import stats as sps

    return sps.fisher_exact([[good_ref, n_ref - good_ref], [good, n - good]])


def _mwu(x_ref, x):
    from scipy import stats as sps

    if not len(x_ref) or not len(x):
        return np.nan, np.nan
    res = sps.mannwhitneyu(x_ref, x, alternative="two-sided")
    return float(res.statistic), float(res.pvalue)


def compare_regions(df: pd.DataFrame, a: str, b: str, variant: str) -> Comparison:
    """``full`` against ``variant`` in every region of the (a, b) map (module docstring)."""
    f = _frame(df)
    rows, keys = [], []
    for (va, vb), g in f.groupby([a, b], sort=True):
        ref, oth = g[g["variant"] == REFERENCE], g[g["variant"] == variant]
        if not len(ref) or not len(oth):
            continue
        odds, p = _fisher(int(ref["_good"].sum()), len(ref), int(oth["_good"].sum()), len(oth))
        s_ref, s = ref["_slip"].to_numpy(float), oth["_slip"].to_numpy(float)
        s_ref, s = s_ref[np.isfinite(s_ref)], s[np.isfinite(s)]
        u, pu = _mwu(s_ref, s)
        rows.append([len(ref), len(oth), int(ref["_good"].sum()), int(oth["_good"].sum()), ref["_good"].mean(),
                     oth["_good"].mean(), float(odds), float(p), np.nan, np.median(s_ref) if len(s_ref) else np.nan,
                     np.median(s) if len(s) else np.nan, u, pu, np.nan])
        keys.append((va, vb))
    table = pd.DataFrame(rows, columns=COMPARE_COLUMNS)
    table.insert(0, b, [k[1] for k in keys])
    table.insert(0, a, [k[0] for k in keys])
    k = max(len(table), 1)
    table["fisher_p_bonf"] = np.minimum(table["fisher_p"] * k, 1.0)
    table["mwu_p_bonf"] = np.minimum(table["mwu_p"] * k, 1.0)
    found = table[(table["rate_ref"] > table["rate"]) & (table["fisher_p_bonf"] < REGION_P)]
    return Comparison(variant, table, found)


def boundary(t: pd.DataFrame, a: str, b: str) -> pd.DataFrame:
    """Per variant and level of ``a``: ``holds_to`` (the largest level of ``b`` up to which every region's success
    rate is >= HOLDS_RATE; NaN if not even the first) and ``stops_at`` (the first level of ``b`` with a rate below
    STOPS_RATE; NaN if none), the levels of ``b`` in increasing order."""
    rows = []
    for (v, va), g in t.groupby(["variant", a], sort=True):
        g = g.sort_values(b)
        ok = (g["rate"] >= HOLDS_RATE).to_numpy()
        held = int(np.argmin(ok)) if not ok.all() else len(ok)
        stops = np.flatnonzero((g["rate"] < STOPS_RATE).to_numpy())
        rows.append([v, va, g[b].iloc[held - 1] if held else np.nan, g[b].iloc[stops[0]] if len(stops) else np.nan])
    return pd.DataFrame(rows, columns=["variant", a, "holds_to", "stops_at"])


def verdict(cmp: Comparison, a: str, b: str) -> str:
    """One sentence: the regions where ``full`` is good (succeeds without sliding) significantly more often than
    ``cmp.variant``, or that there are none within the measured levels."""
    if not len(cmp.found):
        return (f"No region of the ({a}, {b}) map where {REFERENCE} succeeds without sliding (max slip <= "
                f"{SLIDE_MM:g} mm) significantly more often than {cmp.variant} (Fisher's exact test, Bonferroni over "
                f"{len(cmp.table)} regions, p < {REGION_P:g}) within the measured levels.")
    where = "; ".join(f"{a} = {r[a]:g}, {b} = {r[b]:g}: {r.good_ref}/{r.runs_ref} vs {r.good}/{r.runs} good, "
                      f"p = {r.fisher_p_bonf:.2g}" for _, r in cmp.found.iterrows())
    return (f"{REFERENCE} succeeds without sliding significantly more often than {cmp.variant} in "
            f"{len(cmp.found)} of {len(cmp.table)} regions (Fisher's exact test, Bonferroni, p < {REGION_P:g}): "
            f"{where}.")


def analyse(df: pd.DataFrame, factors) -> dict | None:
    """Everything the report's envelope section shows, or None without an envelope (:func:`has_envelope`):
    {"axes": (a, b), "regions": :func:`regions`, "boundary": :func:`boundary`, "comparisons": [Comparison per
    non-reference variant]}."""
    if not has_envelope(df, factors):
        return None
    a, b = map_axes(df, factors)
    t = regions(df, a, b)
    others = [v for v in levels(df["variant"].astype(str)) if v != REFERENCE]
    return {"axes": (a, b), "regions": t, "boundary": boundary(t, a, b),
            "comparisons": [compare_regions(df, a, b, v) for v in others]}
