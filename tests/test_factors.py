"""Factors beyond the paper (wbc_jax.campaign.factors) and the controller variants (wbc_jax.control.variants):
spec validation, design, the paper specs' hashes, per-run batching, one batched rollout mixing the four variants,
two tiny 2-factor campaigns end to end, and the report's success-rate and ablation sections."""

import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from wbc_jax.campaign import factors
from wbc_jax.campaign.spec import SWEEPS, design, load_spec, parse_spec
from wbc_jax.errors import SpecError

# the spec hashes checkpoints and regress baselines are keyed on: new keys at their defaults must not change them
# (a changed default that changes the behaviour, e.g. qp_iters or com_plan, changes them on purpose)
PAPER_HASHES = {
    "sweeps/paper_campaign.toml": "3501d5692d4940bfb38de032d01421970031d4450b540da37fcf05e4d1e8d431",
    "sweeps/paper_exact.toml": "5d461b6e9beeed1a757197d656952316ad1b7272628b1bbeeab74079d7f40379",
    "sweeps/quick.toml": "b8310fc2f2f5e793797a3ec48062571166a24698a54f63fe8d6efe9f3465889c",
    "reports/baseline/spec.toml": "654ac4b816ec9952866d7c292c7b7f16465bda8ef005664d4b52627da5172bdf",
}
# a tiny flat-ground campaign: 4 runs x 0.06 s (3 chunks of one log each); every test rollout here has this shape
# and runs one compiled chunk program: where ground_mu and speed are not factors, SAME_SHAPE sets them in
# [campaign] to the flat scene's own foot friction (1.0: the same physics, but per-run friction of the factor's
# array type) and to the ground_mu x speed campaign's slower speed (whose plan has the most knots)
TINY = """[campaign]
reps = 1
seed = 5
scene = "flat"
distance = 0.1
extra_seconds = 0.0
max_seconds = 0.06
chunk_seconds = 0.02
{campaign}
[factors]
{factors}
[perturbations]
{perturbations}
"""


SAME_SHAPE = "ground_mu = 1.0\nspeed = 0.05"


def tiny(tmp_path, name="tiny.toml", campaign="", factors="", perturbations=""):
    p = tmp_path / name
    p.write_text(TINY.format(campaign=campaign, factors=factors, perturbations=perturbations))
    return p


# ---------------------------------------------------------------- specs and design (no JAX)


@pytest.mark.parametrize("rel", sorted(PAPER_HASHES))
def test_paper_spec_hashes_unchanged(rel):
    s = load_spec(SWEEPS.parent / rel)
    assert s.hash == PAPER_HASHES[rel]
    assert list(s.factors) == ["m", "mu", "d"]


def test_qp_first_test_key_default_hash_and_sim():
    """campaign.qp_first_test: -1 by default, hash-neutral there (existing specs, baselines and checkpoints keep
    their hash), another value changes the hash, is refused outside -1..1000 with a line naming the key, and
    reaches the controller's QP settings (QPSettings.warm_first_test) of the campaign's Sim."""
    from wbc_jax.campaign.build import _sim, qp_changes

    base = dict(factors=dict(m=[0.2, 0.3], mu=[0.4, 1.0], d=[0.06, 0.1]))
    s0, s1, s2 = (parse_spec(dict(base, campaign=c)) for c in ({}, dict(qp_first_test=-1), dict(qp_first_test=0)))
    assert s0.campaign["qp_first_test"] == -1 and s0.hash == s1.hash != s2.hash
    with pytest.raises(SpecError, match="campaign.qp_first_test"):
        parse_spec(dict(base, campaign=dict(qp_first_test=-2)))
    assert _sim("flat", 4, qp=qp_changes(s2)).cfg.qp.warm_first_test == 0
    assert _sim("flat", 4, qp=qp_changes(s0)).cfg.qp.warm_first_test == -1


def test_qp_alpha_key_default_hash_and_sim():
    """campaign.qp_alpha: 0 (the controller's own over-relaxation) by default and hash-neutral there, another value
    changes the hash, is refused outside 0..1.95 with a line naming the key, and becomes the controller's
    QPSettings.alpha."""
    from wbc_jax.campaign.build import _sim, qp_changes

    base = dict(factors=dict(m=[0.2, 0.3], mu=[0.4, 1.0], d=[0.06, 0.1]))
    s0, s1, s2 = (parse_spec(dict(base, campaign=c)) for c in ({}, dict(qp_alpha=0.0), dict(qp_alpha=1.3)))
    assert s0.campaign["qp_alpha"] == 0.0 and s0.hash == s1.hash != s2.hash
    with pytest.raises(SpecError, match="campaign.qp_alpha"):
        parse_spec(dict(base, campaign=dict(qp_alpha=2.0)))
    assert dict(qp_changes(s0)) == {"warm_first_test": -1}
    assert dict(qp_changes(s2)) == {"warm_first_test": -1, "alpha": 1.3}
    assert _sim("flat", 4, qp=qp_changes(s2)).cfg.qp.alpha == 1.3
    assert _sim("flat", 4, qp=qp_changes(s0)).cfg.qp.alpha == 1.6


def test_qp_reuse_factors_key_default_hash_and_sim():
    """campaign.qp_reuse_factors: 0 by default and hash-neutral there, 1 changes the hash and, with Warp physics,
    becomes the transport controller's QPSettings.reuse_factors (the solver keeps it where the fused kernels run,
    drops it on the XLA path: this CPU's controller state carries no factors); with JAX physics it is not applied
    (a note says so); refused outside 0..1 and with the centroidal controller, one line naming the key."""
    from wbc_jax.campaign.build import _sim, check_qp, qp_changes, with_backend
    from wbc_jax.campaign.preflight import notes
    from wbc_jax.control.transport import initial_factors

    base = dict(factors=dict(m=[0.2, 0.3], mu=[0.4, 1.0], d=[0.06, 0.1]))
    s0, s1, s2 = (parse_spec(dict(base, campaign=c)) for c in ({}, dict(qp_reuse_factors=0),
                                                                 dict(qp_reuse_factors=1, backend="warp")))
    assert s0.hash == s1.hash != s2.hash and "reuse_factors" not in dict(qp_changes(s0))
    on_jax = with_backend(s2, "jax")
    assert "reuse_factors" not in dict(qp_changes(on_jax))
    assert [n for n in notes(on_jax, "jax", False) if "qp_reuse_factors = 1 applies with Warp physics only" in n]
    assert not [n for n in notes(s2, "warp", False) if "qp_reuse_factors" in n]
    with pytest.raises(SpecError, match="campaign.qp_reuse_factors"):
        parse_spec(dict(base, campaign=dict(qp_reuse_factors=2)))
    cfg = _sim("flat", 4, qp=qp_changes(s2)).cfg
    assert cfg.qp.reuse_factors and initial_factors(cfg) is None  # the XLA path here: nothing to carry
    assert initial_factors(dataclasses.replace(cfg, qp=cfg.qp._replace(kernel="fused"))).Ki.shape == (64, 64)
    trot = parse_spec(dict(campaign=dict(controller="centroidal", scene="flat", qp_reuse_factors=1),
                           factors=dict(mass_error=[0.0, 0.1])))
    with pytest.raises(SpecError, match="campaign.qp_reuse_factors = 1 with the centroidal controller"):
        check_qp(trot)


def test_qp_rho_key_default_hash_and_sim():
    """campaign.qp_rho: 0 (the transport controller's own rho, 3) by default and hash-neutral there, another value
    changes the hash, becomes the controller's QPSettings.rho and its first warm start's rho (the solve starts from
    it and passes it on: not adapted); refused outside 0..1000 and with the centroidal controller (which adapts
    rho), one line naming the key."""
    from wbc_jax.campaign.build import _sim, check_qp, qp_changes
    from wbc_jax.control.transport import init_control_state

    base = dict(factors=dict(m=[0.2, 0.3], mu=[0.4, 1.0], d=[0.06, 0.1]))
    s0, s1, s2 = (parse_spec(dict(base, campaign=c)) for c in ({}, dict(qp_rho=0.0), dict(qp_rho=2.0)))
    assert s0.hash == s1.hash != s2.hash and "rho" not in dict(qp_changes(s0))
    with pytest.raises(SpecError, match="campaign.qp_rho"):
        parse_spec(dict(base, campaign=dict(qp_rho=1001.0)))
    cfg0, cfg2 = (_sim("flat", 4, qp=qp_changes(s)).cfg for s in (s0, s2))
    assert cfg0.qp.rho == 3.0 and cfg2.qp.rho == 2.0
    dyn, ids = SimpleNamespace(h_G=np.zeros(6), q=np.zeros(40)), SimpleNamespace(act_qpos=np.arange(18))
    assert [float(init_control_state(c, dyn, ids).warm.rho) for c in (cfg0, cfg2)] == [3.0, 2.0]
    trot = parse_spec(dict(campaign=dict(controller="centroidal", scene="flat", qp_rho=2.0),
                           factors=dict(mass_error=[0.0, 0.1])))
    with pytest.raises(SpecError, match="campaign.qp_rho = 2.0 with the centroidal controller"):
        check_qp(trot)


def test_qp_max_iters_key_caps_the_controllers_solves():
    """campaign.qp_max_iters: 0 (the controller's 200) by default and hash-neutral there; another value changes the
    hash and becomes both controllers' QPSettings.max_iters, which caps a real solve: a random QP that needs more
    than 8 iterations from a cold start converges under the controller's settings and stops at 8, flagged
    FLAG_MAX_ITER, under qp_max_iters = 8; refused (parsing) below qp_iters and above 1000, one line naming the key."""
    from wbc_jax.campaign.build import _sim, check_qp, qp_changes
    from wbc_jax.qp import solve_qp
    from wbc_jax.qp.settings import FLAG_MAX_ITER

    base = dict(factors=dict(m=[0.2, 0.3], mu=[0.4, 1.0], d=[0.06, 0.1]))
    s0, s1, s8 = (parse_spec(dict(base, campaign=dict(qp_iters=8, **c)))
                  for c in ({}, dict(qp_max_iters=0), dict(qp_max_iters=8)))
    assert s0.hash == s1.hash != s8.hash and "max_iters" not in dict(qp_changes(s0))
    with pytest.raises(SpecError, match="campaign.qp_max_iters"):
        parse_spec(dict(base, campaign=dict(qp_max_iters=1001)))
    with pytest.raises(SpecError, match="campaign.qp_max_iters: = 4 is below campaign.qp_iters = 8"):
        parse_spec(dict(base, campaign=dict(qp_iters=8, qp_max_iters=4)))
    trot = parse_spec(dict(campaign=dict(controller="centroidal", scene="flat", qp_max_iters=50),
                           factors=dict(mass_error=[0.0, 0.1])))
    check_qp(trot)
    assert _sim("flat", 4, controller="centroidal", qp=qp_changes(trot)).cfg.qp.max_iters == 50
    rng = np.random.default_rng(3)
    n, m = 12, 18
    G = rng.standard_normal((n, n))
    P, q, A = G @ G.T + 0.1 * np.eye(n), rng.standard_normal(n), rng.standard_normal((m, n))
    l, u = -np.abs(rng.standard_normal(m)) * 0.1, np.abs(rng.standard_normal(m)) * 0.1
    results = []
    for spec in (s0, s8):
        qp = _sim("flat", 8, qp=qp_changes(spec)).cfg.qp._replace(eq_rows=0, box_rows=0)
        results.append(solve_qp(P, q, A, l, u, settings=qp))
    free, capped = results
    assert int(free.flag) == 0 and int(free.iters) > 8
    assert int(capped.flag) == FLAG_MAX_ITER and int(capped.iters) == 8


def test_qp_launch_order_key():
    """campaign.qp_launch_order: "batch" by default and hash-neutral there; "predicted" changes the hash and becomes
    the controller's QPSettings.launch_order; another value is refused, one line naming the key."""
    from wbc_jax.campaign.build import _sim, qp_changes
    from wbc_jax.campaign.spec import LAUNCH_ORDERS
    from wbc_jax.qp.settings import LAUNCH_ORDERS as QP_LAUNCH_ORDERS

    base = dict(factors=dict(m=[0.2, 0.3], mu=[0.4, 1.0], d=[0.06, 0.1]))
    s0, s1, s2 = (parse_spec(dict(base, campaign=c)) for c in ({}, dict(qp_launch_order="batch"),
                                                                 dict(qp_launch_order="predicted")))
    assert s0.hash == s1.hash != s2.hash and "launch_order" not in dict(qp_changes(s0))
    assert _sim("flat", 4, qp=qp_changes(s2)).cfg.qp.launch_order == "predicted"
    assert LAUNCH_ORDERS == QP_LAUNCH_ORDERS  # the spec's JAX-free copy
    with pytest.raises(SpecError, match="campaign.qp_launch_order"):
        parse_spec(dict(base, campaign=dict(qp_launch_order="random")))


def test_qp_first_test_refused_where_the_qp_refactors(tmp_path, capsys):
    """A centroidal spec whose QP refactors within a control step (qp_iters above its adapt_every) cannot use
    campaign.qp_first_test: `wbc-jax campaign` exits 2 with one line naming the key and writes nothing."""
    from wbc_jax import cli

    p = tmp_path / "bad.toml"
    p.write_text('[campaign]\ncontroller = "centroidal"\nscene = "flat"\nqp_iters = 12\nqp_first_test = 0\n'
                 "[factors]\nspeed = [0.2, 0.4]\n")
    out = tmp_path / "out"
    assert cli.main(["campaign", "--spec", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "campaign.qp_first_test" in err[0] and str(p) in err[0]
    assert not out.exists()


def test_shipped_studies_load():
    abl, rob = load_spec(SWEEPS / "ablation.toml"), load_spec(SWEEPS / "robustness.toml")
    assert abl.factors["variant"] == ["full", "no_tray_cone", "no_observer", "no_posture"]
    assert abl.campaign["scene"] == "transport" and abl.perturbations["push_max_N"] > 0
    assert set(rob.factors) == {"push_N", "speed", "m"} and rob.factors["push_N"][0] == 0.0
    dz = design(rob)
    assert dz.n == 5 * 3 * 2 * rob.reps
    np.testing.assert_array_equal(np.linalg.norm(dz.push_force, axis=1), dz.levels["push_N"])
    np.testing.assert_array_equal(dz.push_force[:, 1:], 0.0)  # push_dir_deg 0: along world +x
    assert set(np.unique(dz.speed)) == set(rob.factors["speed"]) and np.all(dz.mu == rob.campaign["mu"])


def test_design_order_ignores_the_file_order(tmp_path):
    a = parse_spec(dict(factors=dict(variant=["full", "no_posture"], speed=[0.1, 0.2]), campaign=dict(reps=1)))
    b = parse_spec(dict(factors=dict(speed=[0.1, 0.2], variant=["full", "no_posture"]), campaign=dict(reps=1)))
    assert a.hash == b.hash and list(a.factors) == list(b.factors) == ["speed", "variant"]
    da, db = design(a), design(b)
    np.testing.assert_array_equal(da.speed, [0.1, 0.1, 0.2, 0.2])
    np.testing.assert_array_equal(da.levels["variant"], db.levels["variant"])
    np.testing.assert_array_equal(da.variant, [[1, 1, 1], [1, 1, 0], [1, 1, 1], [1, 1, 0]])


def test_levels_are_normalised_and_switches_combine():
    s = parse_spec(dict(factors=dict(observer=[True, False], variant=["full", "no_tray_cone"]),
                        campaign=dict(reps=1, m=0.25)))
    assert s.factors["observer"] == [1, 0]
    dz = design(s)
    # observer x variant, variant fastest: (1, full) (1, no_tray_cone) (0, full) (0, no_tray_cone)
    np.testing.assert_array_equal(dz.variant, [[1, 1, 1], [0, 1, 1], [1, 0, 1], [0, 0, 1]])
    assert np.all(dz.m == 0.25) and np.all(dz.mu == 0.7) and np.all(dz.d == 0.08)
    assert s.zero_noise


def test_gain_leaves_match_the_controller_and_multiply():
    from wbc_jax.campaign.build import run_gains
    from wbc_jax.control.transport import TransportGains, default_gains

    assert factors.GAIN_LEAVES == TransportGains._fields
    dz = design(parse_spec(dict(factors={"gain.kp_com": [0.5, 2.0], "gain.k_obs": [0.0, 1.0]},
                                campaign=dict(reps=1))))
    g = run_gains(None, dz)
    base = default_gains()
    np.testing.assert_allclose(np.asarray(g.kp_com), np.asarray(base.kp_com)[None] * np.array([.5, .5, 2, 2])[:, None])
    np.testing.assert_allclose(np.asarray(g.k_obs), float(base.k_obs) * np.array([0, 1, 0, 1]))
    np.testing.assert_array_equal(np.asarray(g.kd_com), np.broadcast_to(base.kd_com, (4, 3)))
    assert run_gains(base, design(load_spec(SWEEPS / "quick.toml"))) is base  # no gain factor: unbatched as given


def test_push_n_factor_is_a_fixed_push():
    s = parse_spec(dict(factors=dict(push_N=[0.0, 40.0], mu=[0.4, 1.0]), campaign=dict(reps=2),
                        perturbations=dict(push_dir_deg=90.0, push_window=[0.3, 0.5], push_duration_s=0.1)))
    dz = design(s)
    np.testing.assert_allclose(dz.push_force[:, 1], dz.levels["push_N"])
    np.testing.assert_allclose(dz.push_force[:, 0], 0.0, atol=1e-14)
    np.testing.assert_array_equal(dz.push_duration, np.where(dz.levels["push_N"] > 0, 0.1, 0.0))
    assert np.all((dz.push_frac >= 0.3) & (dz.push_frac <= 0.5)) and not s.zero_noise


# (name, [factors] / other tables, expected key in the message, expected text)
BAD = [
    ("unknown_factor", dict(factors=dict(wind=[1.0, 2.0])), "factors.wind", "unknown factor; expected one of m, mu"),
    ("unknown_gain_leaf", dict(factors={"gain.kp_nope": [1.0, 2.0]}), "factors.gain.kp_nope", "unknown factor"),
    ("bad_variant", dict(factors=dict(variant=["full", "no_arm"])), "factors.variant",
     "level 'no_arm': expected one of full, no_tray_cone, no_observer, no_posture"),
    ("bad_observer", dict(factors=dict(observer=[1, 2])), "factors.observer", "level 2: expected true, false, 1 or 0"),
    ("observer_twice", dict(factors=dict(observer=[1, True])), "factors.observer", "levels must be distinct"),
    ("negative_push", dict(factors=dict(push_N=[-1.0, 10.0])), "factors.push_N", "out of range"),
    ("speed_range", dict(factors=dict(speed=[0.1, 0.9])), "factors.speed", "out of range"),
    ("gain_range", dict(factors={"gain.kp_obj": [1.0, 500.0]}), "factors.gain.kp_obj", "out of range"),
    ("one_level", dict(factors=dict(ground_mu=[0.5])), "factors.ground_mu", "at least 2 levels"),
    ("string_number", dict(factors=dict(ground_mu=["a", 1.0])), "factors.ground_mu", "expected a number"),
    ("six_factors", dict(factors=dict(m=[.2, .3], mu=[.4, .7], d=[.06, .1], speed=[.1, .2], push_N=[0., 1.],
                                      ground_mu=[.5, 1.])), "factors", "6 factors: expected 1 to 5"),
    ("no_factor", dict(factors={}), "factors", "0 factors: expected 1 to 5"),
    ("fixed_and_varied", dict(factors=dict(speed=[0.1, 0.2]), campaign=dict(speed=0.2)), "campaign.speed",
     "the factor speed is varied"),
    ("random_and_fixed_push", dict(factors=dict(push_N=[0.0, 10.0]), perturbations=dict(push_max_N=5.0)),
     "perturbations.push_max_N", "the factor push_N is varied"),
    ("direction_without_push", dict(factors=dict(m=[0.2, 0.3]), perturbations=dict(push_dir_deg=45.0)),
     "perturbations.push_dir_deg", "used only with the push_N factor"),
    ("bad_campaign_variant", dict(factors=dict(m=[0.2, 0.3]), campaign=dict(variant="none")), "campaign.variant",
     "expected one of full"),
    ("bad_order", dict(factors=dict(m=[0.2, 0.3]), analysis=dict(order=0)), "analysis.order", "out of range"),
    ("unknown_analysis_key", dict(factors=dict(m=[0.2, 0.3]), analysis=dict(terms="all")), "analysis.terms",
     "unknown key"),
]


@pytest.mark.parametrize("name, data, key, text", BAD, ids=[b[0] for b in BAD])
def test_bad_factor_is_one_line(name, data, key, text):
    with pytest.raises(SpecError) as e:
        parse_spec(data, "bad.toml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"bad.toml: {key}: ") and text in msg, msg


# ---------------------------------------------------------------- report (no JAX)


def _ablation_table(seed=0):
    """variant (full / no_tray_cone) x mu x 8 reps: no_tray_cone slips 3 mm more and fails half its runs."""
    rng = np.random.default_rng(seed)
    rows = [dict(variant=v, mu=mu, rep=r) for v in ("full", "no_tray_cone") for mu in (0.4, 1.0) for r in range(8)]
    df = pd.DataFrame(rows)
    off = (df["variant"] == "no_tray_cone").to_numpy()
    df.insert(0, "run", np.arange(len(df)))
    df["m"], df["d"], df["seed"] = 0.3, 0.08, 0
    df["success"] = ~off | (df["rep"] % 2 == 0).to_numpy()
    df["R"] = 0.5 + 0.01 * rng.standard_normal(len(df))
    df["T"], df["S"] = rng.random(len(df)), rng.random(len(df))
    df["max_slip_mm"] = 1.0 + 3.0 * off + 0.2 * rng.standard_normal(len(df))
    df["fail_reason"] = np.where(df["success"], "", "dropped")
    return df


def test_report_answers_the_ablation_with_named_tests(tmp_path):
    from wbc_jax.analysis.report import run_report

    df = _ablation_table()
    df.to_csv(tmp_path / "results.csv", index=False)
    out = run_report(str(tmp_path / "results.csv"), str(tmp_path / "rep"), factors=["variant", "mu"], figures=True)
    t = pd.DataFrame(out["ablation"])
    slip = t[(t.metric == "max_slip_mm")].set_index("test")
    assert slip.loc["Welch t (mean)", "differs"] and slip.loc["Mann-Whitney U (median)", "differs"]
    assert slip.loc["Welch t (mean)", "value"] > slip.loc["Welch t (mean)", "value_ref"] + 2
    succ = t[t.metric == "success"].iloc[0]
    assert succ["test"] == "Fisher exact (rate)" and succ["value"] == 0.5 and succ["value_ref"] == 1.0
    assert succ["differs"]  # 8/16 vs 16/16: Fisher p = 0.002
    r = t[(t.metric == "R") & (t.test == "Welch t (mean)")].iloc[0]
    assert not r["differs"]
    lv = pd.DataFrame(out["success"]["by_level"]).set_index(["factor", "level"])
    assert lv.loc[("variant", "no_tray_cone"), "rate"] == 0.5
    assert len(out["success"]["by_pair"]["variant:mu"]) == 4  # the factors in the order given
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "## Controller variants against the reference" in md and "### variant × mu" in md
    assert "variant = no_tray_cone against variant = full: changes max slip [mm] (Welch t (mean)" in md
    assert (tmp_path / "rep" / "figures" / "success_pairs.png").stat().st_size > 1000


def test_report_reads_the_campaigns_factors_from_its_manifest(tmp_path):
    from wbc_jax.analysis.report import run_report

    df = _ablation_table()
    df.to_csv(tmp_path / "results.csv", index=False)
    spec = dict(factors=dict(variant=["full", "no_tray_cone"], mu=[0.4, 1.0]), analysis=dict(order=1, alpha=0.05))
    (tmp_path / "manifest.json").write_text(json.dumps(dict(command="wbc-jax campaign", spec=spec)))
    out = run_report(str(tmp_path / "results.csv"), str(tmp_path / "rep"), figures=False)
    assert list(out["factors"]) == ["variant", "mu"] and out["model_order"] == 1


# ---------------------------------------------------------------- rollouts (JAX, one compiled shape)


@pytest.fixture(scope="module")
def variants_run(tmp_path_factory):
    """The four variants side by side in one batched rollout (4 runs, 0.06 s, no perturbations; SAME_SHAPE)."""
    from wbc_jax.campaign import runner as C

    spec = load_spec(tiny(tmp_path_factory.mktemp("variants"), campaign=SAME_SHAPE,
                          factors='variant = ["full", "no_tray_cone", "no_observer", "no_posture"]'))
    sim, dz, b, _, logs_per_chunk, n_chunks = C.build(spec)
    fn = C.chunk_fn(sim, b.in_axes, logs_per_chunk)
    state = b.state
    for _ in range(n_chunks):
        state, _ = fn(b.model, state, b.plan, b.om, b.gains, b.push, b.mu_ground)
    return sim, dz, b, state


def test_variants_differ_where_they_should(variants_run):
    import jax

    sim, dz, b, state = variants_run
    names = list(dz.levels["variant"])
    assert names == ["full", "no_tray_cone", "no_observer", "no_posture"]
    full, cone, obs, post = range(4)
    cs = jax.device_get(state.cs)
    np.testing.assert_array_equal(np.stack(cs.variant, axis=1), dz.variant)  # the switches ride in the state
    r = np.asarray(cs.obs.r)
    assert np.all(r[obs] == 0.0) and np.abs(r[full]).max() > 1e-3  # observer off: its estimate stays zero
    # the object's contact multipliers (rows of their bounds, the tray cone): pinned to 0 without the cone
    cfg = sim.cfg
    nb = cfg.k * 4  # the last rows of the QP
    lam_b = np.asarray(cs.warm.z)[:, cfg.n_con - nb:]
    assert np.all(lam_b[cone] == 0.0) and lam_b[full].sum() > 0.1
    qpos = np.asarray(state.d.qpos)
    for k in (cone, obs, post):  # every variant changes the motion
        assert np.abs(qpos[k] - qpos[full]).max() > 0, names[k]


def test_push_and_variant_campaign_end_to_end(variants_run, tmp_path):
    """push_N x variant, 2 x 2, through run_campaign and its report (the rollout shape of variants_run)."""
    from wbc_jax.campaign.runner import run_campaign

    spec = tiny(tmp_path, campaign=SAME_SHAPE, factors='push_N = [0.0, 30.0]\nvariant = ["full", "no_observer"]',
                perturbations="push_duration_s = 0.02\npush_window = [0.0, 0.1]\npush_dir_deg = 90.0")
    man = run_campaign(str(spec), str(tmp_path / "out"), progress=False)
    df = pd.read_csv(tmp_path / "out" / "results.csv")
    assert list(df["push_N"]) == [0.0, 0.0, 30.0, 30.0] and list(df["variant"]) == ["full", "no_observer"] * 2
    assert man["n_runs"] == 4 and man["n_cells"] == 4 and man["spec"]["factors"]["variant"] == ["full", "no_observer"]
    rep = json.loads((tmp_path / "out" / "report" / "anova.json").read_text())
    assert list(rep["factors"]) == ["push_N", "variant"]
    assert {r["metric"] for r in rep["ablation"]} == {"max_slip_mm", "R", "success"}
    md = (tmp_path / "out" / "report" / "report.md").read_text()
    assert "### push_N × variant" in md and "variant = no_observer against variant = full" in md


def test_ground_friction_and_speed_campaign_end_to_end(variants_run, tmp_path):
    """ground_mu x speed, 2 x 2: per-run foot friction in the physics and the controller, per-run plans (the
    rollout shape of variants_run, whose compiled chunk function it reuses)."""
    from wbc_jax.campaign import runner as C

    spec = tiny(tmp_path, factors="ground_mu = [0.5, 1.2]\nspeed = [0.05, 0.2]")
    sim, dz, b, *_ = C.build(load_spec(spec))
    feet = np.asarray(sim.robot.ids.foot_pair).ravel()
    pf = np.asarray(b.model.pair_friction)
    np.testing.assert_allclose(pf[:, feet, 0], np.repeat(dz.ground_mu[:, None], len(feet), 1), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(b.mu_ground), dz.ground_mu, rtol=1e-6)
    t_end = np.asarray(b.plan.obj_path.t_knots)[:, -1]
    assert t_end[0] > t_end[1] and t_end[0] == t_end[2]  # (0.5, 0.05) (0.5, 0.2) (1.2, 0.05) (1.2, 0.2)
    man = C.run_campaign(str(spec), str(tmp_path / "out"), progress=False, report=False)
    df = pd.read_csv(tmp_path / "out" / "results.csv")
    assert list(df.columns[:6]) == ["run", "m", "mu", "d", "ground_mu", "speed"]
    assert list(df["ground_mu"]) == [0.5, 0.5, 1.2, 1.2] and list(df["speed"]) == [0.05, 0.2] * 2
    assert man["n_cells"] == 4 and np.isfinite(df["R"]).all()


@pytest.mark.parametrize("key, default, other", [("terrain", "known", "blind"), ("com_plan", "zmp", "spline"),
                                                 ("sensing", "auto", "delayed")])
def test_option_keys(key, default, other):
    """campaign.terrain ("known" | "blind"), campaign.com_plan ("spline" | "zmp") and campaign.sensing ("auto" |
    "delayed"): the default is hash-neutral,
    the other value changes the hash, anything else is a SpecError naming the key."""
    base = dict(factors=dict(m=[0.2, 0.4]), campaign=dict(reps=1))
    plain = parse_spec(base)
    assert plain.campaign[key] == default
    assert parse_spec(dict(base, campaign={"reps": 1, key: default})).hash == plain.hash
    assert parse_spec(dict(base, campaign={"reps": 1, key: other})).hash != plain.hash
    with pytest.raises(SpecError, match=f"campaign.{key}"):
        parse_spec(dict(base, campaign={"reps": 1, key: "dark"}))
