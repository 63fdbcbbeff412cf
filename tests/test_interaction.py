"""Interaction shape (ordinal / disordinal), the paper's exact model (one run per cell, three-way interaction as
error) and the zero-perturbation warning. Pure statistics on hand-made tables: no simulation."""

import json

import numpy as np
import pandas as pd
import pytest

from wbc_jax.analysis.interaction import emm_table, interaction_shape, interaction_views, shapes
from wbc_jax.analysis.report import run_report
from wbc_jax.campaign.runner import zero_noise_warning
from wbc_jax.campaign.spec import SWEEPS, design, load_spec, parse_spec

SS_RTOL = 1e-9  # residual SS vs the hand-computed three-way interaction SS (double precision least squares)


@pytest.mark.parametrize("table, shape", [
    ([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], "ordinal"),  # parallel lines
    ([[1.0, 2.0], [3.0, 5.0], [5.0, 9.0]], "ordinal"),  # diverging, never crossing
    ([[1.0, 2.0], [3.0, 3.0], [5.0, 4.0]], "disordinal"),  # line order reverses: crossing inside the range
    ([[1.0, 2.0], [2.0, 2.0], [3.0, 3.0]], "ordinal"),  # touching without reversing
    ([[1.0, 2.0, 0.5], [2.0, 3.0, 2.5]], "disordinal"),  # lines 1 and 3 cross (1 and 2 do not)
    ([[1.0, np.nan], [2.0, 1.0], [3.0, 4.0]], "disordinal"),  # a missing cell is ignored
    ([[2.0, 1.0], [2.0, 1.0 + 1e-12]], "ordinal"),  # a difference below SHAPE_RTOL is a tie
])
def test_interaction_shape_by_hand(table, shape):
    assert interaction_shape(table) == shape


def test_both_orientations_can_differ():
    """A on x with lines per B is ordinal while B on x with lines per A is disordinal (and the views come in that
    order): B's order (b1 < b2) never reverses, A's order (a1 < a2 at b1, a1 > a2 at b2) does."""
    t = pd.DataFrame(dict(A=["a1", "a1", "a2", "a2"], B=["b1", "b2", "b1", "b2"], emm=[1.0, 5.0, 2.0, 3.0]))
    assert interaction_views(["A:B"]) == [("A:B", "A", "B"), ("A:B", "B", "A")]
    np.testing.assert_array_equal(emm_table(t, "A", "B").to_numpy(), [[1.0, 5.0], [2.0, 3.0]])
    assert [s["shape"] for s in shapes({"A:B": t})] == ["ordinal", "disordinal"]


def _table(levels: dict, y) -> pd.DataFrame:
    grid = pd.MultiIndex.from_product(list(levels.values()), names=list(levels)).to_frame(index=False)
    return grid.assign(rep=0, success=True, R=y)


@pytest.mark.parametrize("n_levels, df_resid", [(2, 1), (3, 8)])
def test_one_rep_report_pools_the_three_way_interaction(tmp_path, n_levels, df_resid):
    """One run per cell: the report's model is main effects + two-way interactions; the residual is the three-way
    interaction: df (n-1)^3 (1 for 2 x 2 x 2, 8 for the paper's 27 runs) and, for 2 x 2 x 2, SS = 8 c^2 with c the
    three-way contrast sum(y a b c) / 8 (effect codes +-1)."""
    lv = {"m": [0.2, 0.3, 0.4][:n_levels], "mu": [0.4, 0.7, 1.0][:n_levels], "d": [0.06, 0.08, 0.1][:n_levels]}
    rng = np.random.default_rng(7)
    df = _table(lv, 0.0)
    code = {f: df[f].map({v: i for i, v in enumerate(lv[f])}).to_numpy() for f in lv}
    y = 1.0 + code["m"] + 0.5 * code["mu"] * code["d"] + 0.1 * rng.standard_normal(len(df))
    df["R"] = y
    df["run"] = np.arange(len(df))
    df["min_clearance_mm"] = 10.0 + np.arange(len(df))  # the first run of each cell's group is the smallest...
    df.loc[1, "min_clearance_mm"] = -1.5  # ...except one penetration
    df["min_clearance_s"] = 0.5
    df["min_clearance_pair"] = "FL_shank (body FL_calf) / floor"
    csv = tmp_path / "results.csv"
    df.to_csv(csv, index=False)
    out = run_report(str(csv), str(tmp_path / "rep"), metrics=["R"], figures=False)
    fit = out["metrics"]["R"]
    assert fit["df_resid"] == df_resid
    resid = [r for r in fit["anova"] if r["source"] == "Residual"][0]
    assert resid["df"] == df_resid
    if n_levels == 2:
        s = {f: 2 * code[f] - 1 for f in lv}
        c = float(np.sum(y * s["m"] * s["mu"] * s["d"]) / 8)
        assert resid["sum_sq"] == pytest.approx(8 * c * c, rel=SS_RTOL)
    md = (tmp_path / "rep" / "report.md").read_text()
    assert f"(interactions of order > 2 pooled into the error); residual df R {df_resid}." in md
    assert "Interaction shapes" in md
    assert "## Clearance (all runs)" in md and "| -1.500 | 1 | 0.500 | FL_shank (body FL_calf) / floor |" in md
    assert len(json.loads((tmp_path / "rep" / "anova.json").read_text())["metrics"]["R"]["interaction_shapes"]) == 6


def test_paper_exact_spec_and_zero_noise_warning():
    spec = load_spec(SWEEPS / "paper_exact.toml")
    dz = design(spec)
    assert spec.reps == 1 and dz.n == 27 and spec.zero_noise
    assert np.all(dz.push_force == 0) and np.all(dz.obj_dx == 0) and np.all(dz.v0 == 0)
    assert zero_noise_warning(spec) is None  # one run per cell: deterministic by design
    twice = parse_spec(dict(factors=spec.factors, campaign=dict(reps=2)), "zero.toml")
    assert "repetitions are identical" in zero_noise_warning(twice)
    noisy = load_spec(SWEEPS / "paper_campaign.toml")
    assert zero_noise_warning(noisy) is None
