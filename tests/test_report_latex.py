"""``report/anova.tex``: the ANOVA tables of ``anova.json`` as LaTeX, number for number."""

from __future__ import annotations

import json
import re

import numpy as np
from test_stats import PLANTED, planted

from wbc_jax.analysis import report
from wbc_jax.analysis.report import latex


def _value(cell: str) -> float | None:
    """A table cell back to a number: ``$a \\times 10^{k}$`` or a plain decimal, bold or not; None when empty; 0
    for a p value below the smallest float."""
    cell = _plain(cell)
    if not cell:
        return None
    if cell == r"$< 10^{-300}$":
        return 0.0
    m = re.fullmatch(r"\$(-?[\d.]+) \\times 10\^\{(-?\d+)\}\$", cell)
    return float(m.group(1)) * 10.0 ** int(m.group(2)) if m else float(cell)


def _plain(cell: str) -> str:
    """A cell without its bold markup (``{\\boldmath\\textbf{...}}``)."""
    return re.sub(r"^\{\\boldmath\\textbf\{(.*)\}\}$", r"\1", cell.strip())


def _tables(tex: str) -> dict[str, list[list[str]]]:
    out = {}
    for label, body in re.findall(r"\\label\{tab:anova-(\w+)\}.*?\\midrule\n(.*?)\\bottomrule", tex, re.S):
        out[label] = [[c.strip() for c in line.removesuffix(r" \\").split(" & ")] for line in body.splitlines()]
    return out


def test_tables_hold_the_json_numbers_and_bold_the_significant_terms(tmp_path):
    df = planted(seed=5)
    df.loc[df.index[:3], "success"] = False
    df["S"] = 2.0 * df["m"] - df["d"]  # zero within-cell variance: no F, p, eta
    csv = tmp_path / "results.csv"
    df.to_csv(csv, index=False)
    summary = report.run_report(str(csv), str(tmp_path / "rep"), figures=False)
    tex = (tmp_path / "rep" / "anova.tex").read_text()
    assert json.loads((tmp_path / "rep" / "anova.json").read_text())["metrics"].keys() == summary["metrics"].keys()
    tables = _tables(tex)
    assert list(tables) == list(summary["metrics"])
    for metric, rows in tables.items():
        ref = summary["metrics"][metric]
        assert len(rows) == len(ref["anova"])
        for cells, r in zip(rows, ref["anova"]):
            assert _plain(cells[0]).replace(r" $\times$ ", ":") == r["source"]
            reliable = ref["f_tests_reliable"]
            for cell, key, rel in zip(cells[1:], ("sum_sq", "df", "mean_sq", "F", "p"), (5e-4, 0, 5e-4, 5e-4, 5e-3)):
                got, want = _value(cell), r[key] if reliable or key not in ("F", "p") else None
                assert (got is None) if want is None else np.isclose(got, want, rtol=rel, atol=0), (metric, key)
            eta = r["partial_eta_sq"] if reliable else None
            assert _plain(cells[6]) == ("" if eta is None else f"{eta:.3f}")
            assert cells[0].startswith(r"{\boldmath\textbf{") == (r["source"] in ref["significant"])
    assert {_plain(row[0]) for row in tables["R"] if row[0].startswith("{")} >= {t for t in PLANTED if ":" not in t}
    assert not any(row[4] or row[5] or row[6] for row in tables["S"])  # unreliable F tests: left out
    assert "F tests unreliable" in tex.split(r"\label{tab:anova-S}")[0].rsplit(r"\caption", 1)[1]
    assert tex.count(r"\begin{table}") == tex.count(r"\end{table}") == len(summary["metrics"]) + 1  # + the means
    assert tex.count("{") == tex.count("}") - tex.count(r"\}") + tex.count(r"\{")


def test_escaping_and_numbers():
    assert latex.escape("gain.kp_x & 5% #1 ~$") == r"gain.kp\_x \& 5\% \#1 \textasciitilde{}\$"
    assert latex.escape("rad²") == "rad$^2$" and latex.escape("s²/m") == "s$^2$/m"
    assert latex._source("mu:gain.k_p") == r"mu $\times$ gain.k\_p"
    assert latex.escape("μ α Δ Α ς °") == r"$\mu$ $\alpha$ $\Delta$ A $\sigma$ $^\circ$"
    assert latex.escape("<|>") == r"\textless{}\textbar{}\textgreater{}" and latex.escape("日") == "?"
    assert latex._labels(["a_b", "a-b", "μ_g"]) == ["tab:anova-a-b", "tab:anova-a-b-2", "tab:anova-g"]
    assert latex.number(156422.1479) == r"$1.564 \times 10^{5}$"
    assert latex.number(9.1306e-06) == r"$9.131 \times 10^{-6}$"
    assert latex.number(0.43638) == "0.4364" and latex.number(2.0) == "2" and latex.number(None) == ""
    assert latex.number(float("nan")) == "" and latex.number(0.0016096, 3) == "0.00161"


def test_level_means_table_holds_each_levels_mean_and_sd(tmp_path):
    df = planted(seed=6)
    df.loc[df.index[:5], "success"] = False
    csv = tmp_path / "results.csv"
    df.to_csv(csv, index=False)
    report.run_report(str(csv), str(tmp_path / "rep"), figures=False)
    tex = (tmp_path / "rep" / "anova.tex").read_text()
    body = re.search(r"\\label\{tab:level-means\}.*?\\toprule\n(.*?)\n\\midrule\n(.*?)\\bottomrule", tex, re.S)
    assert body.group(1) == r"Factor & Level & R & T & $n$ \\"
    ok = df[df["success"]]
    rows = [[c.strip() for c in line.removesuffix(r" \\").split(" & ")] for line in body.group(2).splitlines()]
    assert [(r[0], float(r[1])) for r in rows] == [(f, float(v)) for f in ("m", "mu", "d") for v in sorted(set(df[f]))]
    for factor, level, *cells, n in rows:
        sel = ok[np.isclose(ok[factor], float(level))]
        assert int(n) == len(sel)
        for cell, metric in zip(cells, ("R", "T")):
            mean, sd = (_value(x) for x in cell.split(r" $\pm$ "))
            assert np.isclose(mean, sel[metric].mean(), rtol=5e-4) and np.isclose(sd, sel[metric].std(), rtol=5e-2)


def test_a_p_value_below_the_smallest_float_is_not_zero():
    row = dict(source="mu", sum_sq=1.0, df=2.0, mean_sq=0.5, F=1e9, p=0.0, partial_eta_sq=1.0)
    resid = dict(source="Residual", sum_sq=1e-9, df=10.0, mean_sq=1e-10, F=None, p=None, partial_eta_sq=None)
    tex = latex.metric_table("R", dict(significant=["mu"], anova=[row, resid], ss_type="III", n=13, df_resid=10.0),
                             "", 0.05, "tab:x")
    cells = [c.strip() for c in tex.splitlines()[8].removesuffix(r" \\").split(" & ")]
    assert _plain(cells[5]) == r"$< 10^{-300}$" and _value(cells[5]) == 0.0 and _plain(cells[0]) == "mu"
