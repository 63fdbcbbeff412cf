"""The centroidal controller on the campaign engine: a tiny trot campaign (2 cells x 1 rep, 1.2 s) writes results,
manifest and report on both physics backends; its metrics equal ``wbc-jax trot``'s for the same settings (the same
code and batch); ``regress`` passes on the committed centroidal baseline; the spec refuses the other controller's
factors and keys."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from wbc_jax.campaign.controllers import CONTROLLERS
from wbc_jax.campaign.runner import run_campaign
from wbc_jax.campaign.spec import load_spec, parse_spec
from wbc_jax.errors import SpecError

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "sweeps" / "trot_quick.toml"
BASELINE = ROOT / "reports" / "baseline_trot"  # its spec.toml is SPEC
# trot_quick.toml as wbc-jax trot's settings: stride = speed x step_time, 2 half-cycles, the campaign's log interval
# and chunk length (the same chunk program; the study compiles it through wbc_jax.rollout.simulate, the campaign
# through its exported chunk function)
TROT = dict(stride=0.4 * 0.25, step_time=0.25, t_four=0.08, n_steps=2, mass_errors=(-0.1, 0.1), iters=40,
            log_every=20, t_start=0.5, t_settle=0.2)
CHUNK_SECONDS = 0.6


@pytest.fixture(scope="module")
def jax_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("trot") / "run"
    manifest = run_campaign(str(SPEC), str(out), progress=False, backend="jax")
    return out, manifest


def _check_outputs(out: Path, manifest: dict) -> pd.DataFrame:
    df = pd.read_csv(out / "results.csv")
    assert len(df) == 2 and list(df.mass_error) == [-0.1, 0.1]
    assert set(CONTROLLERS["centroidal"].columns) <= set(df.columns)
    assert manifest["spec"]["campaign"]["controller"] == "centroidal"
    assert set(manifest["metric_means"]) == set(CONTROLLERS["centroidal"].means)
    assert json.loads((out / "manifest.json").read_text())["n_runs"] == 2
    assert (out / "report" / "report.md").exists()
    return df


def test_trot_campaign_on_jax_equals_the_trot_study(jax_run):
    """results.csv, manifest and report; both runs walk; every metric equals wbc-jax trot's (run_study) exactly."""
    from wbc_jax.studies.trot import TrotSettings, run_study

    out, manifest = jax_run
    df = _check_outputs(out, manifest)
    assert df.success.all() and df.walked.all(), df[["success", "walked", "fail_reason"]]
    assert np.all(df.speed_mps > 0.1), df.speed_mps  # two half-cycles from rest: planned 0.1 m in 0.5 s
    study = run_study(TrotSettings(**TROT), chunk_seconds=CHUNK_SECONDS, verbose=False)
    for k in CONTROLLERS["centroidal"].columns:
        got, want = df[k].to_numpy(), study.results[k]
        if want.dtype == object:
            assert [str(x) if x == x else "" for x in got] == [str(x) for x in want], k
        else:  # results.csv holds each value's shortest text in its own dtype: read back in that dtype, exact
            np.testing.assert_array_equal(got.astype(want.dtype), want, err_msg=k)


@pytest.mark.slow
def test_trot_campaign_on_warp(tmp_path):
    """The same campaign with MuJoCo Warp's physics (on the CPU here) writes results, manifest and report."""
    pytest.importorskip("warp")
    out = tmp_path / "warp"
    manifest = run_campaign(str(SPEC), str(out), progress=False, backend="warp")
    assert manifest["physics_backend"] == "warp"
    df = _check_outputs(out, manifest)
    assert df.success.all(), df[["success", "fail_reason"]]


def test_regress_passes_on_the_trot_baseline(jax_run, capsys):
    from wbc_jax.campaign.regress import run_regress

    assert load_spec(BASELINE / "spec.toml").hash == load_spec(SPEC).hash
    code, moved = run_regress(str(BASELINE))
    assert code == 0, moved
    assert "within the tolerance band" in capsys.readouterr().out


def test_spec_keeps_each_controllers_factors_and_keys():
    base = {"campaign": {"controller": "centroidal"}, "factors": {"mass_error": [-0.1, 0.1]}}
    assert parse_spec(base).campaign["controller"] == "centroidal"
    for bad, key in (({"factors": {"variant": ["full", "no_posture"]}}, "factors.variant"),
                     ({"campaign": {"controller": "centroidal", "distance": 1.0}}, "campaign.distance"),
                     ({"campaign": {"controller": "centroidal", "four_foot": 0.3}}, "campaign.four_foot")):
        with pytest.raises(SpecError, match=key):
            parse_spec({**base, **bad})
    with pytest.raises(SpecError, match="factors.mass_error"):
        parse_spec({"factors": {"mass_error": [-0.1, 0.1]}})
    with pytest.raises(SpecError, match="campaign.step_time"):
        parse_spec({"campaign": {"step_time": 0.3}, "factors": {"m": [0.2, 0.3]}})


def test_unchanged_centroidal_plugin_equals_the_builtin_bit_for_bit(jax_run, tmp_path):
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC.read_text() + '\n[plugin]\nclass = "tests.plugins:SameTrot"\n')
    out = tmp_path / "run"
    manifest = run_campaign(str(spec), str(out), progress=False, backend="jax", report=False)
    pd.testing.assert_frame_equal(pd.read_csv(out / "results.csv"), pd.read_csv(jax_run[0] / "results.csv"),
                                  check_exact=True)
    assert manifest["spec"]["plugin"] == {"class": "tests.plugins:SameTrot"}
