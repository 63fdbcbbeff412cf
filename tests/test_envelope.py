"""The envelope and claims analyses on synthetic results tables, against hand-computed test values, and the envelope
spec (no simulation)."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pandas as pd
import pytest

from wbc_jax.analysis import claims, envelope
from wbc_jax.analysis.report.document import Doc
from wbc_jax.analysis.report.envelope_section import claims_section, envelope_section
from wbc_jax.campaign import build, size, spec
from wbc_jax.campaign.design import design

REPS = 6
TOL = 1e-12
# Fisher's exact test on [[6, 0], [0, 6]] and the exact Mann-Whitney U test of 6 values all below 6 others, two-sided:
# the observed table (and its mirror) are 2 of the C(12, 6) equally likely arrangements
P_SEPARATED = 2 / math.comb(12, 6)


def _table() -> pd.DataFrame:
    """variant x mu x obj_accel x REPS; only (mu 0.2, obj_accel 4) differs: full good, no_tray_cone slides 6-11 mm
    and fails."""
    rows = []
    for variant in ("full", "no_tray_cone"):
        for mu in (0.2, 0.6):
            for accel in (1.0, 4.0):
                for rep in range(REPS):
                    hard = variant == "no_tray_cone" and mu == 0.2 and accel == 4.0
                    slip = 6.0 + rep if hard else 0.1 * (rep + 1)
                    rows.append(dict(variant=variant, mu=mu, obj_accel=accel, rep=rep, success=not hard,
                                     max_slip_mm=slip, R=0.1 * mu, T=0.001, S=1.0))
    return pd.DataFrame(rows)


FACTORS = ["variant", "mu", "obj_accel"]


def test_region_tests_against_hand_values():
    df = _table()
    res = envelope.analyse(df, FACTORS)
    assert res["axes"] == ("mu", "obj_accel")
    cmp = res["comparisons"][0]
    assert cmp.variant == "no_tray_cone"
    hard = cmp.table[(cmp.table.mu == 0.2) & (cmp.table.obj_accel == 4.0)].iloc[0]
    assert (hard.good_ref, hard.runs_ref, hard.good, hard.runs) == (REPS, REPS, 0, REPS)
    assert abs(hard.fisher_p - P_SEPARATED) < TOL
    assert abs(hard.fisher_p_bonf - 4 * P_SEPARATED) < TOL  # 4 regions
    assert hard.mwu_u == 0.0 and abs(hard.mwu_p - P_SEPARATED) < TOL
    easy = cmp.table[(cmp.table.mu == 0.6)]
    assert (easy.fisher_p == 1.0).all()
    assert len(cmp.found) == 1 and cmp.found.iloc[0].mu == 0.2
    assert "1 of 4 regions" in envelope.verdict(cmp, "mu", "obj_accel")


def test_against_scipy():
    from scipy import stats as sps

    df = _table()
    df.loc[(df.variant == "full") & (df.mu == 0.2) & (df.obj_accel == 4.0) & (df.rep < 2), "success"] = False
    cmp = envelope.compare_regions(df, "mu", "obj_accel", "no_tray_cone")
    hard = cmp.table[(cmp.table.mu == 0.2) & (cmp.table.obj_accel == 4.0)].iloc[0]
    assert abs(hard.fisher_p - sps.fisher_exact([[4, 2], [0, 6]])[1]) < TOL
    ref = df[(df.variant == "full") & (df.mu == 0.2) & (df.obj_accel == 4.0)].max_slip_mm
    other = df[(df.variant == "no_tray_cone") & (df.mu == 0.2) & (df.obj_accel == 4.0)].max_slip_mm
    assert abs(hard.mwu_p - sps.mannwhitneyu(ref, other, alternative="two-sided").pvalue) < TOL


def test_boundary():
    t = envelope.regions(_table(), "mu", "obj_accel")
    b = envelope.boundary(t, "mu", "obj_accel").set_index(["variant", "mu"])
    assert b.loc[("full", 0.2), "holds_to"] == 4.0 and np.isnan(b.loc[("full", 0.2), "stops_at"])
    assert b.loc[("no_tray_cone", 0.2), "holds_to"] == 1.0 and b.loc[("no_tray_cone", 0.2), "stops_at"] == 4.0


def test_no_region_is_stated():
    df = _table()
    df["success"] = True
    df["max_slip_mm"] = 0.2
    cmp = envelope.analyse(df, FACTORS)["comparisons"][0]
    assert not len(cmp.found)
    assert envelope.verdict(cmp, "mu", "obj_accel").startswith("No region")


def test_report_sections_render():
    d = Doc()
    envelope_section(d, _table(), FACTORS)
    claims_section(d, _table(), FACTORS, 0.05)
    md = d.markdown()
    assert "Envelope" in md and "full against no_tray_cone" in md and "The paper's claims" in md
    d = Doc()
    envelope_section(d, _table().drop(columns="variant"), ["mu", "obj_accel"])
    assert d.markdown().strip() == ""


def test_eta_squared_by_hand():
    # groups (1, 3) and (5, 7): grand mean 4, SS_total 20, SS_between 2 * 4 * 2 = 16
    assert abs(claims.eta_squared(np.array([1.0, 3.0, 5.0, 7.0]), np.array([0, 0, 1, 1])) - 0.8) < TOL


def test_mu_claim_finds_the_reversed_region():
    t = claims.answer_claims(_table(), FACTORS).set_index("factor")
    # in the hard region mu 0.2 fails and mu 0.6 succeeds: a larger mu is beneficial everywhere
    assert t.loc["mu", "answer"] == "holds"
    assert t.loc["m", "answer"] == "not tested"
    df = _table()
    df.loc[df.mu == 0.6, "max_slip_mm"] += 20.0  # now the larger mu slides further in every region
    assert claims.answer_claims(df, FACTORS).set_index("factor").loc["mu", "answer"] == "contradicted"


def test_d_claim_negligible_and_not():
    df = pd.DataFrame(dict(d=np.repeat([0.06, 0.1], 20), success=True, R=np.tile(np.arange(20.0), 2),
                           T=np.tile(np.arange(20.0), 2), S=np.tile(np.arange(20.0), 2)))
    assert claims.answer_claims(df, ["d"]).set_index("factor").loc["d", "answer"] == "holds"
    df["T"] = np.repeat([0.0, 10.0], 20)
    assert claims.answer_claims(df, ["d"]).set_index("factor").loc["d", "answer"] == "contradicted for T"


def test_envelope_spec():
    s = spec.load_spec(spec.SWEEPS / "envelope.toml")
    assert set(s.factors) == {"variant", "mu", "obj_accel", "speed", "push_N"}
    assert set(s.factors["variant"]) == {"full", "no_tray_cone", "no_observer"}
    assert min(s.factors["mu"]) <= 0.2
    n = size.n_runs_of(s)
    assert n == design(s).n and n <= 1500


def test_obj_accel_ramps():
    s = spec.parse_spec({"campaign": dict(speed=0.2, reps=1), "factors": dict(obj_accel=[0.0, 2.0], mu=[0.4, 0.7])})
    ramps = build.speed_ramps(s, design(s))  # cells mu x obj_accel (design order)
    np.testing.assert_allclose(ramps, [1.0, 0.2, 1.0, 0.2])  # 2 x 0.2 m/s / 2 m/s^2; 0: the planner's 1 s
    plain = spec.parse_spec({"factors": dict(mu=[0.4, 0.7])})
    assert build.speed_ramps(plain, design(plain)) is None
    with pytest.raises(Exception, match="obj_accel"):
        spec.parse_spec({"campaign": dict(obj_accel=30.0), "factors": dict(mu=[0.4, 0.7])})
    with open(spec.SWEEPS / "paper_campaign.toml", "rb") as f:
        paper = tomllib.load(f)
    assert spec.parse_spec(paper).hash == spec.parse_spec({**paper, "campaign": {**paper["campaign"],
                                                                                "obj_accel": 0.0}}).hash


def test_obj_accel_is_the_plans_peak_acceleration():
    import jax
    import jax.numpy as jnp

    from wbc_jax.planner.spline import eval_path
    from wbc_jax.planner.transport import straight_plan
    from wbc_jax.robot.model import Robot

    s = spec.parse_spec({"campaign": dict(reps=1, scene="flat", distance=0.5, speed=0.2),
                         "factors": dict(obj_accel=[1.0, 4.0])})
    robot = Robot("flat")
    for accel, ramp in zip((1.0, 4.0), build.speed_ramps(s, design(s))):
        plan = straight_plan(robot, robot.home_qpos(0.08), distance=0.5, speed=0.2, ramp=float(ramp))
        t = jnp.linspace(0.0, float(plan.obj_path.t_knots[-1]), 8001)
        a = jax.vmap(eval_path, in_axes=(None, 0))(plan.obj_path, t)[2]
        assert abs(float(jnp.max(jnp.linalg.norm(a, axis=1))) - accel) < 0.02 * accel


def test_report_of_an_envelope_table(tmp_path):
    from wbc_jax.api import report

    csv = tmp_path / "results.csv"
    _table().to_csv(csv, index=False)
    report(csv, tmp_path / "rep", factors=FACTORS, metrics=["R", "max_slip_mm"], figures=False)
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "## Envelope: where each controller variant succeeds" in md
    assert "1 of 4 regions" in md
    assert "## The paper's claims" in md


@pytest.mark.slow
def test_tiny_envelope_spec_builds():
    """A tiny envelope (variant x obj_accel x speed, 8 runs on flat ground) builds: each run's plan has its speed's
    duration and its obj_accel's ramps, and its variant and push."""
    import dataclasses

    from wbc_jax.planner.spline import path_end_time

    s = spec.load_spec(spec.SWEEPS / "envelope.toml")
    s = dataclasses.replace(s, campaign={**s.campaign, "reps": 1, "distance": 0.3},
                            factors={"variant": ["full", "no_tray_cone"], "obj_accel": [0.5, 4.0],
                                     "speed": [0.13, 0.25]})
    built = build.build(s)
    dz = built.design
    ends = np.array([float(path_end_time(p)) for p in _plans(built.batch.plan, dz.n)])
    ramps = build.speed_ramps(s, dz)
    # rest-to-rest: start time + distance / speed + one ramp (half a ramp's distance on each side at cruise speed)
    t_start = ends - 0.3 / dz.speed - ramps
    np.testing.assert_allclose(t_start, t_start[0], atol=1e-4)
    np.testing.assert_array_equal(np.asarray(built.batch.state.cs.variant.tray_cone), dz.variant[:, 0])


def _plans(plan, n):
    from wbc_jax.rollout import runs

    return [runs.take(plan.obj_path, i) for i in range(n)]
