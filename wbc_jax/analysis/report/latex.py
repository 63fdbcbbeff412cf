r"""The report's ANOVA tables as LaTeX (``report/anova.tex``), for a paper: one ``booktabs`` table per metric.

Each table holds what ``anova.json`` holds for the metric (sources, sums of squares, df, mean squares, F, p, partial
eta squared), in the same display units, with the terms significant at the report's alpha in bold. The file is a
fragment to ``\input`` into a document whose preamble loads ``booktabs``.
"""

from __future__ import annotations

import math
import re

_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{",
            "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}
_UNITS = {"²": "$^2$", "³": "$^3$", "μ": r"$\mu$", "η": r"$\eta$"}


def escape(text: str) -> str:
    """``text`` with LaTeX's special characters escaped and the units' superscripts and Greek letters in math."""
    return "".join(_SPECIAL.get(c, _UNITS.get(c, c)) for c in str(text))


def number(x, digits: int = 4) -> str:
    r"""``x`` with ``digits`` significant digits, a power of ten as ``\times 10^{k}`` in math; "" for None/NaN."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return ""
    if float(x).is_integer() and abs(x) < 1e6:
        return str(int(x))
    mantissa, _, exp = f"{float(x):.{digits}g}".partition("e")
    return f"${mantissa} \\times 10^{{{int(exp)}}}$" if exp else mantissa


def _source(name: str) -> str:
    return r" $\times$ ".join(escape(part) for part in name.split(":"))


def metric_table(metric: str, result: dict, unit: str, alpha: float, label: str) -> str:
    """One metric's ANOVA table (``result``: the metric's entry of ``anova.json``'s ``metrics``)."""
    significant = set(result["significant"])
    rows = []
    for r in result["anova"]:
        cells = [_source(r["source"]), number(r["sum_sq"]), number(r["df"]), number(r["mean_sq"]), number(r["F"]),
                 number(r["p"], 3), "" if r["partial_eta_sq"] is None else f"{r['partial_eta_sq']:.3f}"]
        if r["source"] in significant:
            cells = [rf"\textbf{{{c}}}" if c else c for c in cells]
        rows.append(" & ".join(cells) + r" \\")
    caption = (f"ANOVA of {escape(metric)}" + (f" [{escape(unit)}]" if unit else "")
               + f" (type {escape(result['ss_type'])} sums of squares, $n = {result['n']}$, "
               f"residual df {number(result['df_resid'])}); bold: $p < {alpha:g}$"
               + ("" if result.get("f_tests_reliable", True) else "; F tests unreliable: "
                  + escape("; ".join(result.get("unreliable_reasons") or []))) + ".")
    return "\n".join([r"\begin{table}[ht]", r"\centering", rf"\caption{{{caption}}}", rf"\label{{{label}}}",
                      r"\begin{tabular}{lrrrrrr}", r"\toprule",
                      r"Source & SS & df & MS & $F$ & $p$ & $\eta^2_p$ \\", r"\midrule", *rows, r"\bottomrule",
                      r"\end{tabular}", r"\end{table}", ""])


def document(summary: dict, source: str) -> str:
    """``anova.tex``: a comment naming the results table ``source``, then one table per metric of ``summary``
    (the report's ``anova.json``)."""
    units = summary.get("units") or {}
    head = [f"% ANOVA tables of {source} (wbc-jax report); \\usepackage{{booktabs}} in the preamble", ""]
    tables = [metric_table(m, r, units.get(m, ""), summary["alpha"], "tab:anova-" + re.sub(r"[^A-Za-z0-9]", "-", m))
              for m, r in summary["metrics"].items()]
    return "\n".join(head + tables)
