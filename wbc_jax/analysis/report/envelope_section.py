"""The report's envelope section (:mod:`wbc_jax.analysis.envelope`) and the paper's claims
(:mod:`wbc_jax.analysis.claims`)."""

from __future__ import annotations

import pandas as pd

from wbc_jax.analysis import claims, envelope
from wbc_jax.analysis.report.document import Doc, fmt


def _pivot(t: pd.DataFrame, a: str, b: str, cells) -> pd.DataFrame:
    """Rows = levels of ``a``, columns = levels of ``b``, the strings ``cells`` (one per row of ``t``)."""
    out = t.assign(cell=list(cells)).pivot(index=a, columns=b, values="cell")
    out.columns = [f"{b} = {fmt(c, 'g')}" for c in out.columns]
    out.index = [fmt(i, "g") for i in out.index]
    return out.rename_axis(a).reset_index()


def _maps(d: Doc, t: pd.DataFrame, a: str, b: str) -> None:
    """Per variant: success rate and median / largest max slip over the (a, b) map."""
    for v in pd.unique(t["variant"]):
        tv = t[t["variant"] == v]
        d.h(4, f"{v}: successes / runs (good: max slip <= {envelope.SLIDE_MM:g} mm)")
        d.table(_pivot(tv, a, b, (f"{s}/{n} ({g} good)" for s, n, g in zip(tv["successes"], tv["runs"],
                                                                            tv["good"]))))
        d.h(4, f"{v}: max slip [mm], median (largest)")
        d.table(_pivot(tv, a, b, (f"{m:.3g} ({x:.3g})" for m, x in zip(tv["slip_median"], tv["slip_max"]))))


def _comparison(d: Doc, cmp: envelope.Comparison, t: pd.DataFrame, a: str, b: str) -> None:
    """``full`` minus one variant: the map of differences and the per-region tests."""
    d.h(3, f"{envelope.REFERENCE} against {cmp.variant}")
    d.p(envelope.verdict(cmp, a, b))
    diff = envelope.difference(t, a, b, cmp.variant)
    d.h(4, f"success rate, {envelope.REFERENCE} minus {cmp.variant}")
    d.table(_pivot(diff, a, b, (fmt(r, "+.2f") for r in diff["rate"])))
    c = cmp.table
    d.table(pd.DataFrame({
        a: c[a].map(lambda v: fmt(v, "g")), b: c[b].map(lambda v: fmt(v, "g")),
        f"good {envelope.REFERENCE}": [f"{g}/{n}" for g, n in zip(c["good_ref"], c["runs_ref"])],
        f"good {cmp.variant}": [f"{g}/{n}" for g, n in zip(c["good"], c["runs"])],
        "Fisher p": c["fisher_p"].map(lambda v: fmt(v, ".3g")),
        "Fisher p Bonferroni": c["fisher_p_bonf"].map(lambda v: fmt(v, ".3g")),
        f"median slip {envelope.REFERENCE} [mm]": c["slip_median_ref"].map(lambda v: fmt(v, ".3g")),
        f"median slip {cmp.variant} [mm]": c["slip_median"].map(lambda v: fmt(v, ".3g")),
        "Mann-Whitney p": c["mwu_p"].map(lambda v: fmt(v, ".3g")),
        "Mann-Whitney p Bonferroni": c["mwu_p_bonf"].map(lambda v: fmt(v, ".3g"))}))


def envelope_section(d: Doc, df: pd.DataFrame, factors) -> None:
    """The envelope section, where the table has one (:func:`wbc_jax.analysis.envelope.has_envelope`)."""
    res = envelope.analyse(df, factors)
    if res is None:
        return
    a, b = res["axes"]
    t = res["regions"]
    d.h(2, "Envelope: where each controller variant succeeds")
    d.p(f"Regions: the levels of {a} (rows) x {b} (columns), pooled over the other factors and the repetitions. A "
        f"run is good when it succeeds with max slip <= {envelope.SLIDE_MM:g} mm. Per region, {envelope.REFERENCE} "
        "against each other variant: Fisher's exact test on good runs, Mann-Whitney U on max slip (every run with "
        "a finite value; a failed run's up to its failure), two-sided, Bonferroni over the map's regions.")
    for cmp in res["comparisons"]:
        d.ul([envelope.verdict(cmp, a, b)])
    d.h(3, "Maps")
    _maps(d, t, a, b)
    d.h(3, "Boundary")
    d.p(f"Per variant and {a}: the largest {b} up to which every region succeeds in at least "
        f"{envelope.HOLDS_RATE:.0%} of its runs (holds to), and the first {b} where fewer than "
        f"{envelope.STOPS_RATE:.0%} succeed (stops at); empty: none within the measured levels.")
    bt = res["boundary"]
    d.table(pd.DataFrame({"variant": bt["variant"], a: bt[a].map(lambda v: fmt(v, "g")),
                          "holds to": bt["holds_to"].map(lambda v: fmt(v, "g")),
                          "stops at": bt["stops_at"].map(lambda v: fmt(v, "g"))}))
    for cmp in res["comparisons"]:
        _comparison(d, cmp, t, a, b)


def claims_section(d: Doc, df: pd.DataFrame, factors, alpha: float) -> None:
    """The paper's claims about mu, m and d, each answered from this table where its factor is varied."""
    t = claims.answer_claims(df, factors, alpha)
    if (t["answer"] == "not tested").all():
        return
    d.h(2, "The paper's claims")
    d.p(f"Each claim answered from this table's runs (alpha = {alpha:g}; the tests: `wbc_jax.analysis.claims`).")
    d.table(t)
