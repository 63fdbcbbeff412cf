"""``wbc-jax report``: outputs, warnings, and bad input through the real CLI (subprocess)."""

from __future__ import annotations

import json
import logging
import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_stats import FACTORS, PLANTED, planted

from wbc_jax.analysis import report, stats
from wbc_jax.analysis.render import ReportWorker, Workers
from wbc_jax.errors import InputError

REPO = Path(__file__).resolve().parents[1]
ROW_KEYS = {"source", "sum_sq", "df", "mean_sq", "F", "p", "partial_eta_sq"}


def _cli(csv: Path, out: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "wbc_jax", "report", str(csv), "--out", str(out), *extra],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _strict_json(path: Path) -> dict:
    def no_nan(c):
        raise ValueError(f"non-JSON constant {c}")

    return json.loads(path.read_text(), parse_constant=no_nan)


def _leftovers(parent: Path, name: str) -> list[str]:
    return [p.name for p in parent.iterdir() if p.name.startswith(f".{name}.")]


def test_cli_full_report_with_figures(tmp_path):
    """The one test that renders figures: the full CLI path on planted data."""
    csv = tmp_path / "results.csv"
    df = planted(seed=1)
    df["S"] = df["R"] * 0.5 + np.random.default_rng(0).standard_normal(len(df))
    df.loc[[3, 50], "success"] = False
    df.to_csv(csv, index=False)
    out = tmp_path / "rep"
    p = _cli(csv, out)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == 0, stderr
    assert {f.name for f in out.iterdir()} == {"report.md", "report.html", "anova.json", "anova.tex", "design.csv",
                                              "cell_means.csv", "manifest.json", "figures"}
    pngs = ["means.png", "interactions_R.png", "interactions_T.png", "interactions_S.png", "qq.png",
            "success_levels.png", "success_pairs.png"]
    assert sorted(p.name for p in (out / "figures").iterdir()) == sorted(pngs)
    for png in pngs:
        data = (out / "figures" / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    html = (out / "report.html").read_text()
    assert html.count('src="data:image/png;base64,') == 7 and 'src="figures/' not in html
    assert "Interaction plots of T:" in html
    md = (out / "report.md").read_text()
    assert "![" in md and "figures/means.png" in md and "## Metric R" in md
    summary = _strict_json(out / "anova.json")
    assert summary["ss_type"] == "III" and summary["n_failed"] == 2 and list(summary["metrics"]) == ["R", "T", "S"]
    r = summary["metrics"]["R"]
    assert set(r["significant"]) == PLANTED
    assert all(set(row) == ROW_KEYS for row in r["anova"]) and r["anova"][-1]["source"] == "Residual"
    assert {a["test"] for a in r["assumptions"]} == {"Lilliefors KS", "Shapiro-Wilk", "Levene (mean)",
                                                   "Brown-Forsythe (median)"}
    assert [s["by"] for s in r["simple_effects"]] == ["d", "mu"]
    man = _strict_json(out / "manifest.json")
    assert man["rows"] == len(df) and len(man["sha256"]) == 64
    assert not _leftovers(tmp_path, "rep")

    # the same figures from worker processes (wbc_jax.analysis.render; the CLI above used them only on 4+ cores):
    # 3 workers for 7 figures, one of them dead before its job (its figure and the 4 left over are drawn in this
    # process), byte for byte those of the CLI
    workers = Workers(3)
    workers.processes[0].kill()
    report.run_report(str(csv), str(tmp_path / "rep2"), workers=workers)
    assert all(p.returncode is not None for p in workers.processes)  # every worker ended
    assert sorted(workers.answered.values()) == ["lost"] * 5 + ["ok"] * 2  # 2 drawn by workers
    for png in (out / "figures").iterdir():
        assert (tmp_path / "rep2" / "figures" / png.name).read_bytes() == png.read_bytes(), png.name


def test_report_worker_writes_the_same_report_and_raises_its_errors(tmp_path):
    """A campaign's report process (wbc_jax.analysis.render.ReportWorker, started during the rollout on 4+ cores):
    the same tables as this process's report of the same results; an input error of the report raised in the
    caller as the same one-line error. Figures off and no figure workers (test_cli_full_report_with_figures
    compares the workers' figures)."""
    csv = tmp_path / "results.csv"
    planted(seed=2).to_csv(csv, index=False)
    worker = ReportWorker(n_figures=0)
    got = worker.run_report(str(csv), str(tmp_path / "w"), figures=False)
    assert worker.answered == "ok" and worker.process.returncode == 0
    ref = report.run_report(str(csv), str(tmp_path / "p"), figures=False)
    assert got.keys() == ref.keys() and got["metrics"] == ref["metrics"] and got["success"] == ref["success"]
    for name in ("report.md", "cell_means.csv", "design.csv"):
        assert (tmp_path / "w" / name).read_bytes() == (tmp_path / "p" / name).read_bytes(), name
    worker = ReportWorker(n_figures=0)
    with pytest.raises(InputError, match="results file not found") as e:
        worker.run_report(str(tmp_path / "none.csv"), str(tmp_path / "x"))
    assert worker.answered == "error" and "\n" not in str(e.value) and not (tmp_path / "x").exists()


def test_unbalanced_and_deterministic_metric_report(tmp_path):
    df = planted(seed=3)
    rng = np.random.default_rng(2)
    df = df.drop(index=rng.choice(len(df), size=15, replace=False))  # missing runs
    df.loc[df.index[:6], "success"] = False  # failed runs
    df["S"] = 2.0 * df["m"] - df["d"]  # deterministic: zero within-cell variance
    csv = tmp_path / "results.csv"
    df.to_csv(csv, index=False)
    out = tmp_path / "rep"
    summary = report.run_report(str(csv), str(out), figures=False)
    s, r = summary["metrics"]["S"], summary["metrics"]["R"]
    assert s["f_tests_reliable"] is False and s["significant"] == []
    assert any("zero within-cell variance" in w for w in s["warnings"])
    assert any("zero within-cell variance" in w for w in s["unreliable_reasons"]) and not r["unreliable_reasons"]
    assert r["f_tests_reliable"] is True and set(r["significant"]) >= PLANTED
    assert any("unbalanced" in w for w in r["warnings"])
    assert any("6 of 93 runs failed" in w for w in summary["warnings"])
    md = (out / "report.md").read_text()
    assert "S: F tests are unreliable" in md and "**F tests unreliable**" in md and "unbalanced design" in md
    # the deterministic metric's ANOVA shows SS and MS but no F, p, partial eta squared
    s_table = md.split("## Metric S")[1].split("### Assumptions")[0]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in s_table.splitlines() if line.startswith("| ")]
    assert rows[0][:7] == ["source", "SS", "df", "MS", "F", "p", "partial η²"] and len(rows) == 8
    assert all(r[1] and r[3] and r[4:] == ["", "", "", ""] for r in rows[1:])
    assert not (out / "figures").exists()
    design = (out / "design.csv").read_text().splitlines()
    assert design[0] == "m,mu,d,runs,successes,failures" and len(design) == 28
    _strict_json(out / "anova.json")


def test_existing_dir_replaced_only_on_success(tmp_path):
    """An earlier report is replaced only with force and only on success; a foreign folder never."""
    from wbc_jax.errors import OutputError

    csv = tmp_path / "results.csv"
    planted(seed=1).to_csv(csv, index=False)
    out = tmp_path / "rep"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    with pytest.raises(OutputError, match="not empty"):
        report.run_report(str(csv), str(out), figures=False, force=True)
    assert (out / "stale.txt").read_text() == "old"
    (out / "stale.txt").unlink()
    report.run_report(str(csv), str(out), figures=False)  # an empty folder is fine
    before = (out / "anova.json").read_bytes()
    with pytest.raises(OutputError, match="--force"):
        report.run_report(str(csv), str(out), figures=False)
    with pytest.raises(InputError):
        report.run_report(str(csv), str(out), factors=["m", "nope"], figures=False, force=True)
    assert (out / "anova.json").read_bytes() == before
    report.run_report(str(csv), str(out), figures=False, force=True)
    assert (out / "anova.json").exists()
    assert not _leftovers(tmp_path, "rep")
    assert oct(out.stat().st_mode & 0o777) != "0o700"


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _bad_cases(tmp: Path) -> dict:
    """name -> (csv path, extra CLI args, expected message part)."""
    good = planted(seed=1)
    nonnum = good.astype({"R": object})
    nonnum.loc[5, "R"] = "abc"
    frames = {
        "missing_column": (good, ["--factors", "m,mu,x"], "factor column 'x' is not in the table"),
        "missing_metric": (good, ["--metrics", "R,Q"], "metric column 'Q' is not in the table"),
        "non_numeric_metric": (nonnum, [], "metric 'R' is not numeric (e.g. 'abc')"),
        "one_level_factor": (good.assign(d=0.06), [], "factor 'd' has only one level (0.06);"),  # no np.float64
        "duplicate_run_ids": (good.assign(run=[*range(100), 3, 3, 7, *range(200, 205)]), [],
                              "duplicate_run_ids.csv: run ids appear more than once in column 'run': 3, 7 "),
        "no_factors": (good.drop(columns=FACTORS), [], "no factor columns"),
        "bad_alpha": (good, ["--alpha", "1.5"], "alpha must be between 0 and 1"),
    }
    out = {}
    for name, (df, extra, msg) in frames.items():
        csv = tmp / f"{name}.csv"
        df.to_csv(csv, index=False)
        out[name] = (csv, extra, msg)
    out["empty_file"] = (_write(tmp / "empty.csv", ""), [], "results file is empty")
    out["header_only"] = (_write(tmp / "header.csv", "m,mu,d,rep,seed,success,R\n"), [], "header but no rows")
    out["not_found"] = (tmp / "nope.csv", [], "results file not found")
    out["directory"] = (tmp, [], "results path is a directory")
    out["binary"] = (tmp / "bin.csv", [], "not a readable CSV")
    (tmp / "bin.csv").write_bytes(b"m,mu\n\xff\xfe\x00\x81,\x00\n")
    good.to_csv(tmp / "semicolon.csv", sep=";", index=False)
    out["semicolon"] = (tmp / "semicolon.csv", [], "separates its columns with semicolons, not commas")
    out["manifest_json"] = (_write(tmp / "manifest.json", '{"command": "wbc-jax campaign"}'), [],
                            "manifest.json is a JSON file, not a results CSV (a campaign's manifest.json? its table is")
    return out


CLI_CASES = ["missing_column", "non_numeric_metric", "one_level_factor", "empty_file", "not_found", "duplicate_run_ids"]
INPROC_CASES = ["missing_metric", "no_factors", "bad_alpha", "header_only", "directory", "binary", "semicolon",
                "manifest_json"]


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    return _bad_cases(tmp_path_factory.mktemp("bad"))


@pytest.fixture(scope="module")
def cli_runs(cases):
    """The issue's bad-input kinds through the real CLI, as parallel subprocesses."""
    runs = {}
    for name in CLI_CASES:
        csv, extra, msg = cases[name]
        out = csv.parent / f"out_{name}"
        runs[name] = (_cli(csv, out, *extra), out, msg)
    csv, extra, msg = cases["one_level_factor"]  # an existing output directory stays untouched
    kept = csv.parent / "out_existing"
    kept.mkdir()
    (kept / "old.md").write_text("previous report")
    runs["existing_dir"] = (_cli(csv, kept, *extra), kept, "folder is not empty")
    return {name: (*p.communicate(timeout=120), p.returncode, out, msg) for name, (p, out, msg) in runs.items()}


@pytest.mark.parametrize("name", [*CLI_CASES, "existing_dir"])
def test_bad_input_cli(cli_runs, name):
    stdout, stderr, rc, out, msg = cli_runs[name]
    assert rc == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("wbc-jax report: error: ") and msg in lines[0], stderr
    assert "Traceback" not in stderr and stdout == ""
    if name == "existing_dir":
        assert [p.name for p in out.iterdir()] == ["old.md"]
    else:
        assert not out.exists()
    assert not _leftovers(out.parent, out.name)


@pytest.mark.parametrize("name", INPROC_CASES)
def test_bad_input_in_process(cases, name):
    csv, extra, msg = cases[name]
    kw = dict(zip(extra[::2], extra[1::2]))
    args = {"factors": kw.get("--factors"), "metrics": kw.get("--metrics")}
    args = {k: v.split(",") for k, v in args.items() if v}
    out = csv.parent / f"inproc_{name}"
    with pytest.raises(InputError) as e:
        report.run_report(str(csv), str(out), alpha=float(kw.get("--alpha", 0.05)), figures=False, **args)
    assert msg in str(e.value) and "\n" not in str(e.value)
    assert not out.exists() and not _leftovers(out.parent, out.name)


# ---------------------------------------------------------------- a report that explains itself


def _campaign_dir(tmp_path: Path, reps: int = 3, factors=("m", "mu"), drop=()) -> Path:
    """A campaign's folder: results.csv (2 x 2 cells of m, mu; T in metres) and the manifest.json beside it."""
    rng = np.random.default_rng(0)
    grid = pd.MultiIndex.from_product([[0.2, 0.4], [0.4, 1.0], range(reps)], names=["m", "mu", "rep"])
    df = grid.to_frame(index=False)
    df.insert(0, "run", np.arange(len(df)))
    df = df.assign(d=0.06, seed=df["run"], success=True, fail_reason="")
    df["R"] = 0.3 + 0.1 * (df["m"] == 0.4) + 0.01 * rng.standard_normal(len(df))
    df["T"] = 0.01 + 0.004 * (df["mu"] == 0.4) + 0.001 * rng.standard_normal(len(df))
    df["S"] = 10.0 * df["m"] + df["mu"]  # the same in both runs of a cell
    df.drop(columns=list(drop)).to_csv(tmp_path / "results.csv", index=False)
    spec = {"campaign": {"name": "tiny"}, "factors": {f: [] for f in factors}, "analysis": {"order": 2}}
    (tmp_path / "manifest.json").write_text(json.dumps({"command": "wbc-jax campaign", "spec_path": "sweeps/t.toml",
                                                        "spec_hash": "ab" * 32, "spec": spec}))
    return tmp_path / "results.csv"


def test_campaign_report_defines_its_metrics_and_shows_T_in_mm(tmp_path):
    csv = _campaign_dir(tmp_path)
    summary = report.run_report(str(csv), str(tmp_path / "rep"), figures=False)
    md = (tmp_path / "rep" / "report.md").read_text()
    assert md.startswith("# ANOVA report: tiny campaign (sweeps/t.toml)\n\nResults `")
    assert "written by `wbc-jax campaign` from the spec `sweeps/t.toml` (spec hash `abababababab`)." in md
    html = (tmp_path / "rep" / "report.html").read_text()
    assert "<title>ANOVA report: tiny campaign (sweeps/t.toml)</title>" in html
    metrics = md.split("## Metrics\n")[1].split("\n## ")[0]
    assert "R, robustness [rad²]: R = (1/T_win) ∫ 1/H dt" in metrics and "T = (1/T_win) ∫ ‖p_ref − p‖ dt" in metrics
    assert "S = T_win / ∫ ‖v̇_b‖ dt" in metrics and "T, tracking error [mm]" in metrics
    directions = [re.search(r"; (\w+) is better: ", line) for line in metrics.splitlines() if line.startswith("- ")]
    assert [d.group(1) for d in directions] == ["higher", "lower", "higher"]
    assert summary["units"] == {"R": "rad²", "T": "mm", "S": "s²/m"} and "## Metric T [mm]" in md
    # T in mm: cell means 1000 x those of the CSV (metres); F and p the same as in metres
    df = pd.read_csv(csv)
    cells = pd.read_csv(tmp_path / "rep" / "cell_means.csv").query("metric == 'T'").set_index(["m", "mu"])["mean"]
    np.testing.assert_allclose(cells, 1e3 * df.groupby(["m", "mu"])["T"].mean(), rtol=1e-12)
    metres = stats.analyze(df, ["m", "mu"], ["T"])["metrics"]["T"]["anova"]
    shown = pd.DataFrame(summary["metrics"]["T"]["anova"])
    np.testing.assert_allclose(shown["F"][:-1], metres["F"][:-1], rtol=1e-9)
    np.testing.assert_allclose(shown["sum_sq"], 1e6 * metres["sum_sq"], rtol=1e-9)


def test_variance_tests_not_run_on_two_runs_per_cell(tmp_path):
    """2 runs per cell: both lie equally far from their cell's centre, so Levene's statistic is a ratio of rounding
    errors: not run, with the reason (and the zero-variance cells of S named), instead of 'rejected, p = 0'."""
    csv = _campaign_dir(tmp_path, reps=2)
    summary = report.run_report(str(csv), str(tmp_path / "rep"), figures=False)
    for metric, reason in (("R", "4 of 4 cells have 2 runs"), ("S", "4 of 4 cells have zero variance")):
        tests = {a["test"]: a for a in summary["metrics"][metric]["assumptions"]}
        for name in ("Levene (mean)", "Brown-Forsythe (median)"):
            assert tests[name]["ok"] is None and tests[name]["statistic"] is None and tests[name]["p"] is None
            assert tests[name]["note"].startswith("cannot be run: ") and reason in tests[name]["note"]
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "homogeneity of variance rejected" not in md and "| not run | cannot be run: " in md


def test_missing_declared_factor_warns_once(tmp_path, caplog):
    csv = _campaign_dir(tmp_path, factors=("m", "mu", "d"), drop=["d"])
    with caplog.at_level(logging.WARNING, logger="wbc_jax"):
        summary = report.run_report(str(csv), str(tmp_path / "rep"), figures=False)
    [record] = caplog.records
    msg = record.getMessage()
    assert "\n" not in msg and msg.startswith("warning: ") and "results.csv lacks the factor column(s) d" in msg
    assert msg.endswith("that its manifest.json declares (spec sweeps/t.toml): analysing m, mu only")
    assert list(summary["factors"]) == ["m", "mu"] and msg[len("warning: "):] in summary["warnings"]


# ---------------------------------------------------------------- figures


def _factorial(n_factors: int, n_metrics: int, reps: int = 2) -> tuple[pd.DataFrame, list[str], list[str]]:
    """2 levels per factor, ``reps`` runs per cell, metrics with a main effect of the first factor."""
    factors = [f"f{i}" for i in range(n_factors)]
    df = pd.MultiIndex.from_product([[0.1, 0.2]] * n_factors + [range(reps)], names=[*factors, "rep"]).to_frame(
        index=False).assign(success=True)
    rng = np.random.default_rng(n_factors)
    metrics = [f"y{k}" for k in range(n_metrics)]
    for k in metrics:
        df[k] = 10 * df["f0"] + rng.standard_normal(len(df))
    return df, factors, metrics


@pytest.mark.parametrize("shape", ["planted", (1, 1), (2, 1), (5, 2)])
def test_figures_are_readable_grids(shape):
    """Every figure 600-2400 px wide with sides at most 3 apart (no 2112 x 275 strip); means.png plots the
    per-level EMMs with their 95 % CIs from the pooled MSE (balanced design: the level means)."""
    from scipy import stats as sps

    from wbc_jax.analysis import figures
    from wbc_jax.analysis.report.figure_jobs import figure_jobs
    from wbc_jax.analysis.report.model import analyze_table, beyond_anova

    df, factors, metrics = (planted(seed=1), FACTORS, ["R", "T"]) if shape == "planted" else _factorial(*shape)
    data = stats.prepare(df, factors, metrics)
    res = analyze_table(data, factors, metrics, alpha=0.05, ss_type=3, order=2)
    jobs = figure_jobs(res, beyond_anova(data, factors, 0.05), factors, metrics, {m: m for m in metrics})
    for name, (fn, args) in jobs.items():
        png = getattr(figures, fn)(*args)
        width, height = struct.unpack(">II", png[16:24])
        assert 600 <= width <= 2400 and max(width / height, height / width) <= 3, (name, width, height)
    fit = res["metrics"][metrics[0]]["fit"]
    emm = jobs["means.png"][1][0][metrics[0]][factors[0]]
    means = data.groupby(factors[0])[metrics[0]].agg(["mean", "size"])
    half = sps.t.ppf(0.975, fit.df_resid) * np.sqrt(fit.mse / means["size"].to_numpy())
    np.testing.assert_allclose(emm["emm"], means["mean"], rtol=1e-9)
    np.testing.assert_allclose(emm["ci_high"] - emm["emm"], half, rtol=1e-9)
