r"""The report's tables as LaTeX (``report/anova.tex``), for a paper: one ``booktabs`` ANOVA table per metric, then
the metrics' mean +- SD per factor level.

Each table holds what ``anova.json`` holds for the metric (sources, sums of squares, df, mean squares, F, p, partial
eta squared; left out where the F tests are unreliable), in the same display units, with the terms significant at the
report's alpha in bold. The file is a fragment to ``\input`` into a document whose preamble loads ``booktabs``.
"""

from __future__ import annotations

import math
import re
import unicodedata

_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{",
            "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}", "<": r"\textless{}",
            ">": r"\textgreater{}", "|": r"\textbar{}"}
_CAPITALS = {"Gamma", "Delta", "Theta", "Lambda", "Xi", "Pi", "Sigma", "Upsilon", "Phi", "Psi", "Omega"}
_LATIN = {"alpha": "A", "beta": "B", "epsilon": "E", "zeta": "Z", "eta": "H", "iota": "I", "kappa": "K", "mu": "M",
          "nu": "N", "omicron": "O", "rho": "P", "tau": "T", "chi": "X"}
_SYMBOLS = {"²": "$^2$", "³": "$^3$", "°": r"$^\circ$", "µ": r"$\mu$", "±": r"$\pm$", "×": r"$\times$",
            "≤": r"$\leq$", "≥": r"$\geq$", "−": "-"}


def escape(text: str) -> str:
    """``text`` for LaTeX: its special characters escaped, Greek letters, superscripts and a few symbols in math, any
    other non-ASCII character as ``?`` (pdfLaTeX has no glyph for most)."""
    return "".join(_SPECIAL.get(c) or _SYMBOLS.get(c) or _greek(c) or (c if c.isascii() else "?") for c in str(text))


def _greek(c: str) -> str | None:
    r"""A Greek letter as math (``$\alpha$``, ``$\Delta$``; a capital LaTeX has no command for: its Latin twin),
    else None."""
    m = re.fullmatch(r"GREEK (SMALL|CAPITAL) LETTER (?:FINAL )?([A-Z]+)", unicodedata.name(c, ""))
    if m is None:
        return None
    letter = m.group(2).lower()
    if m.group(1) == "CAPITAL":
        return f"$\\{letter.capitalize()}$" if letter.capitalize() in _CAPITALS else _LATIN.get(letter, "?")
    return "o" if letter == "omicron" else f"$\\{letter}$"


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
    reliable = result.get("f_tests_reliable", True)
    rows = []
    for r in result["anova"]:
        p_value = r"$< 10^{-300}$" if r["p"] == 0 else number(r["p"], 3)  # below the smallest float: not zero
        tests = [number(r["F"]), p_value, "" if r["partial_eta_sq"] is None else f"{r['partial_eta_sq']:.3f}"]
        cells = [_source(r["source"]), number(r["sum_sq"]), number(r["df"]), number(r["mean_sq"]),
                 *(tests if reliable else ["", "", ""])]
        if r["source"] in significant:
            cells = [rf"{{\boldmath\textbf{{{c}}}}}" if c else c for c in cells]
        rows.append(" & ".join(cells) + r" \\")
    caption = (f"ANOVA of {escape(metric)}" + (f" [{escape(unit)}]" if unit else "")
               + f" (type {escape(result['ss_type'])} sums of squares, $n = {result['n']}$, "
               f"residual df {number(result['df_resid'])}); bold: $p < {alpha:g}$"
               + ("" if reliable else "; F tests unreliable, F, $p$ and $\\eta^2_p$ left out: "
                  + escape("; ".join(result.get("unreliable_reasons") or []))) + ".")
    return "\n".join([r"\begin{table}[ht]", r"\centering", rf"\caption{{{caption}}}", rf"\label{{{label}}}",
                      r"\begin{tabular}{lrrrrrr}", r"\toprule",
                      r"Source & SS & df & MS & $F$ & $p$ & $\eta^2_p$ \\", r"\midrule", *rows, r"\bottomrule",
                      r"\end{tabular}", r"\end{table}", ""])


def means_table(level_means, metrics: list[str], units: dict) -> str:
    """Each metric's mean and SD per factor level (successful runs; ``level_means``: the report's long table with
    metric, factor, level, mean, sd, n), one column per metric, n of the first metric's runs."""
    first = level_means[level_means["metric"] == metrics[0]]
    rows = []
    for f, level, n in zip(first["factor"], first["level"], first["n"]):
        cells = [escape(f), escape(f"{level:g}" if isinstance(level, float) else level)]
        for m in metrics:
            row = level_means[(level_means["metric"] == m) & (level_means["factor"] == f)
                              & (level_means["level"] == level)].iloc[0]
            cells.append("" if not row["n"] else rf"{number(row['mean'])} $\pm$ {number(row['sd'], 2)}")
        rows.append(" & ".join([*cells, str(int(n))]) + r" \\")
    head = " & ".join(["Factor", "Level", *(escape(m) + (f" [{escape(units[m])}]" if units.get(m) else "")
                                             for m in metrics), "$n$"]) + r" \\"
    return "\n".join([r"\begin{table}[ht]", r"\centering",
                      r"\caption{Mean $\pm$ SD per factor level (successful runs).}", r"\label{tab:level-means}",
                      rf"\begin{{tabular}}{{ll{'r' * len(metrics)}r}}", r"\toprule", head, r"\midrule", *rows,
                      r"\bottomrule", r"\end{tabular}", r"\end{table}", ""])


def document(summary: dict, source: str, level_means=None) -> str:
    """``anova.tex``: a comment naming the results table ``source``, one table per metric of ``summary`` (the
    report's ``anova.json``), then the metrics' means per factor level (:func:`means_table`; ``level_means``:
    the report's, None: left out)."""
    units = summary.get("units") or {}
    head = [f"% ANOVA tables of {source} (wbc-jax report); \\usepackage{{booktabs}} in the preamble", ""]
    metrics = list(summary["metrics"])
    tables = [metric_table(m, r, units.get(m, ""), summary["alpha"], label)
              for (m, r), label in zip(summary["metrics"].items(), _labels(metrics))]
    if level_means is not None and metrics:
        tables.append(means_table(level_means, metrics, units))
    return "\n".join(head + tables)


def _labels(metrics: list[str]) -> list[str]:
    """``tab:anova-<metric>`` with the metric's name reduced to letters, digits and ``-``; a name that reduces to
    an earlier one's gets its position appended."""
    out = []
    for i, m in enumerate(metrics):
        label = "tab:anova-" + (re.sub(r"[^A-Za-z0-9]+", "-", m).strip("-") or "metric")
        out.append(label if label not in out else f"{label}-{i + 1}")
    return out
