"""Controllers from outside the package (a spec's ``[plugin]`` table): validation, the cache keys, a plug-in that
changes nothing against the built-in bit for bit, and examples/torque_lag.py against its equation."""

import shutil
import sys

import numpy as np
import pandas as pd
import pytest

from wbc_jax import cli
from wbc_jax.campaign.spec import load_spec, parse_spec
from wbc_jax.errors import SpecError

TINY = dict(m=[0.2, 0.4], mu=[0.4, 1.0], d=[0.06, 0.10])
LAG = "examples.torque_lag:TorqueLag"


def _spec(plugin, controller="transport"):
    data = dict(campaign=dict(reps=1, controller=controller), factors=TINY)
    if plugin is not None:
        data["plugin"] = plugin
    return parse_spec(data, "p.toml")


@pytest.mark.parametrize("plugin, key, expect", [
    (3, "plugin", "expected a table"),
    ({"time_constant": 0.1}, "plugin.class", "module:Class"),
    ({"class": "torque_lag"}, "plugin.class", "module:Class"),
    ({"class": "no_such_module_xyz:C"}, "plugin.class", "cannot import module 'no_such_module_xyz'"),
    ({"class": "examples.torque_lag:Nope"}, "plugin.class", "has no 'Nope'"),
    ({"class": "examples.torque_lag:LagState"}, "plugin.class", "subclass of wbc_jax.rollout.controllers.Transport"),
    ({"class": "tests.plugins:ByIdentity"}, "plugin.class", "eq=False"),
    ({"class": "tests.plugins:NoDefault"}, "plugin.class", "needs a default of type bool, int, float or str"),
    ({"class": "tests.plugins:TakenColumn"}, "plugin.class", "extra_columns = ('R',): expected a tuple of new column"),
    ({"class": LAG, "speed": 1.0}, "plugin.speed", "not a field of examples.torque_lag:TorqueLag; expected one of "
                                                   "time_constant"),
    ({"class": LAG, "time_constant": "fast"}, "plugin.time_constant", "expected a float like its default 0.02"),
    ({"class": LAG, "time_constant": True}, "plugin.time_constant", "expected a float"),
    ({"class": LAG, "time_constant": -0.01}, "plugin", "TorqueLag.time_constant = -0.01: expected >= 0"),
])
def test_bad_plugin_names_the_key(plugin, key, expect):
    with pytest.raises(SpecError) as e:
        _spec(plugin)
    msg = str(e.value)
    assert msg.startswith(f"p.toml: {key}: ") and expect in msg and "\n" not in msg, msg


def test_plugin_without_a_source_file_is_refused(monkeypatch):
    import dataclasses
    import types

    from wbc_jax.rollout.controllers import TransportController

    mod = types.ModuleType("plugin_without_file")  # as a class defined in an interactive session
    mod.Mine = dataclasses.dataclass(frozen=True, eq=False)(
        type("Mine", (TransportController,), {"__module__": mod.__name__}))
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    with pytest.raises(SpecError, match="p.toml: plugin.class: plugin_without_file:Mine: no source file to hash"):
        _spec({"class": "plugin_without_file:Mine"})


@pytest.mark.parametrize("plugin, levels, key, expect", [
    (None, [0.0, 0.01], "factors.plugin.time_constant", "add a [plugin] table"),
    ({"class": LAG}, [0.0, -0.01], "factors.plugin.time_constant", "TorqueLag.time_constant = -0.01: expected >= 0"),
    ({"class": LAG, "time_constant": 0.01}, [0.0, 0.02], "plugin.time_constant", "the factor plugin.time_constant "
                                                                                  "is varied; leave it out"),
    ({"class": "tests.plugins:NoParams"}, [1.0, 2.0], "factors.plugin.gain", "does not implement with_params"),
])
def test_bad_plugin_factor_names_the_key(plugin, levels, key, expect):
    field = "gain" if plugin and "NoParams" in plugin["class"] else "time_constant"
    data = dict(campaign=dict(reps=1), factors={**TINY, f"plugin.{field}": levels})
    if plugin is not None:
        data["plugin"] = plugin
    with pytest.raises(SpecError) as e:
        parse_spec(data, "p.toml")
    assert str(e.value).startswith(f"p.toml: {key}: ") and expect in str(e.value), str(e.value)


def test_unquoted_dotted_factor_is_named(tmp_path):
    p = tmp_path / "dotted.toml"
    p.write_text(f'[factors]\nm = [0.2, 0.4]\nplugin.time_constant = [0.0, 0.01]\n[plugin]\nclass = "{LAG}"\n')
    with pytest.raises(SpecError, match='factors.plugin.time_constant: a dotted factor name: quote it '
                                        '\\("plugin.time_constant" = '):
        load_spec(p)


def test_plugin_factor_of_an_unknown_field():
    data = dict(campaign=dict(reps=1), factors={**TINY, "plugin.tau": [0.0, 1.0]}, plugin={"class": LAG})
    with pytest.raises(SpecError, match="factors.plugin.tau: not a float or bool field of .*TorqueLag; expected one "
                                        "of plugin.time_constant"):
        parse_spec(data, "p.toml")
    ok = parse_spec(dict(data, factors={**TINY, "plugin.time_constant": [0, 0.02]}), "p.toml")
    assert list(ok.factors) == ["m", "mu", "d", "plugin.time_constant"]
    assert ok.factors["plugin.time_constant"] == [0.0, 0.02]


def test_plugin_must_subclass_the_spec_controller():
    with pytest.raises(SpecError, match="plugin.class: .*subclass of wbc_jax.rollout.controllers.CentroidalController"):
        _spec({"class": LAG}, controller="centroidal")


def test_plugin_fields_defaults_and_hash(tmp_path, monkeypatch):
    s = _spec({"class": LAG, "time_constant": 1})
    assert s.plugin == {"class": LAG, "time_constant": 1.0} and isinstance(s.plugin["time_constant"], float)
    assert _spec({"class": LAG}).plugin == {"class": LAG, "time_constant": 0.02}
    plain = _spec(None)
    assert plain.plugin == {} and "plugin" not in plain.canonical() and "plugin_sha256" not in plain.hashed()
    assert s.hash != _spec({"class": LAG, "time_constant": 0.05}).hash != plain.hash
    # the plug-in's source is in the hash, and an edited module file is imported again (the code that runs is the
    # code hashed, also in one Python session)
    mod = tmp_path / "lag_copy.py"
    shutil.copy("examples/torque_lag.py", mod)
    monkeypatch.syspath_prepend(str(tmp_path))
    before = _spec({"class": "lag_copy:TorqueLag"})
    text = mod.read_text()
    mod.write_text(text.replace("time_constant: float = 0.02", "time_constant: float = 0.03"))
    after = _spec({"class": "lag_copy:TorqueLag"})
    assert before.plugin["time_constant"] == 0.02 and after.plugin["time_constant"] == 0.03
    assert before.plugin_sha256 != after.plugin_sha256 and before.hash != after.hash
    mod.write_text(text)
    assert _spec({"class": "lag_copy:TorqueLag"}).hash == before.hash


def test_bad_plugin_cli_is_one_line_exit_2_nothing_written(tiny_spec, tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text(tiny_spec.read_text() + '\n[plugin]\nclass = "no_such_module_xyz:C"\n')
    out = tmp_path / "out"
    assert cli.main(["campaign", "--spec", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("wbc-jax campaign: error:") and "plugin.class" in err[0]
    assert not out.exists() and list(tmp_path.iterdir()) == [p]


def test_lag_equation_by_hand():
    from examples.torque_lag import lag

    prev, u = np.array([1.0, 2.0]), np.array([3.0, -2.0])
    # a = dt / (T + dt) = 0.002 / 0.02 = 0.1: tau = prev + 0.1 (u - prev)
    np.testing.assert_allclose(lag(prev, u, True, 0.002, 0.018), [1.2, 1.6], rtol=1e-6)  # float32
    np.testing.assert_array_equal(lag(prev, u, False, 0.002, 0.018), u)  # the first step: the QP's torque


def _run(tiny_spec, tmp_path, plugin: str):
    from wbc_jax.campaign.runner import run_campaign

    p = tmp_path / "spec.toml"
    p.write_text(tiny_spec.read_text() + plugin)
    out = tmp_path / "out"
    return out, run_campaign(str(p), str(out), progress=False)


def test_unchanged_plugin_equals_the_builtin_bit_for_bit(full_run, tiny_spec, tmp_path):
    from wbc_jax.campaign import build

    out, manifest = _run(tiny_spec, tmp_path, '\n[plugin]\nclass = "tests.plugins:Same"\n')
    ref = pd.read_csv(full_run[0] / "results.csv")
    got = pd.read_csv(out / "results.csv")
    pd.testing.assert_frame_equal(got, ref, check_exact=True)
    assert manifest["spec"]["plugin"] == {"class": "tests.plugins:Same"} and len(manifest["plugin_sha256"]) == 64
    sims = [s for s in build._SIMS.values() if type(s.controller).__name__ == "Same"]
    assert sims and not sims[0].exportable  # its programs are not kept as exported programs (sources not in the key)


def test_resume_refuses_an_edited_plugin(full_run, tiny_spec, tmp_path, monkeypatch):
    from wbc_jax.campaign import runner
    from wbc_jax.campaign.runner import run_campaign
    from wbc_jax.errors import CheckpointError

    mod = tmp_path / "same_copy.py"
    shutil.copy("tests/plugins.py", mod)
    monkeypatch.syspath_prepend(str(tmp_path))
    spec = tmp_path / "spec.toml"
    spec.write_text(tiny_spec.read_text() + '\n[plugin]\nclass = "same_copy:Same"\n')
    out = tmp_path / "out"
    after_chunk = runner.after_chunk

    def cut(done, n_chunks):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "after_chunk", cut)
    with pytest.raises(KeyboardInterrupt):
        run_campaign(str(spec), str(out), report=False, progress=False)
    monkeypatch.setattr(runner, "after_chunk", after_chunk)
    text = mod.read_text()
    mod.write_text(text + "\n# edited\n")
    with pytest.raises(CheckpointError, match="belongs to another run .spec_hash differ"):
        run_campaign(str(spec), str(out), resume=True, report=False, progress=False)
    mod.write_text(text)
    man = run_campaign(str(spec), str(out), resume=True, report=False, progress=False)
    assert man["resumed"]
    pd.testing.assert_frame_equal(pd.read_csv(out / "results.csv"), pd.read_csv(full_run[0] / "results.csv"),
                                  check_exact=True)


ZERO = "[perturbations]\nobject_xy_mm = 0.0\nobject_yaw_deg = 0.0\nbase_speed_std = 0.0\npush_max_N = 0.0\n" \
       "qvel_noise_std = 0.0\n"


def test_plugin_field_as_a_factor_equals_campaigns_of_one_value(tiny_spec, tmp_path):
    """``plugin.time_constant`` varied per run in one batch: each run's row equals, bit for bit, the same run of a
    campaign with that value in [plugin] (no perturbations, so a cell's repetitions equal its run; the same batch
    size: the varied campaign's 2 levels against 2 repetitions)."""
    from wbc_jax.campaign.runner import run_campaign

    head = tiny_spec.read_text().split("[perturbations]")[0]

    def run(name: str, text: str) -> pd.DataFrame:
        p = tmp_path / f"{name}.toml"
        p.write_text(text + ZERO)
        run_campaign(str(p), str(tmp_path / name), report=False, progress=False)
        return pd.read_csv(tmp_path / name / "results.csv")

    varied = run("varied", head.replace("[factors]", '[factors]\n"plugin.time_constant" = [0.0, 0.05]')
                 + f'[plugin]\nclass = "{LAG}"\n')
    assert list(varied["plugin.time_constant"]) == [0.0, 0.05] * 8
    metrics = ["m", "mu", "d", "success", "R", "T", "S", "max_slip_mm", "lag_err_rms_Nm"]
    outs = {}
    for tc in (0.0, 0.05):
        outs[tc] = run(f"static{tc}", head.replace("reps = 1", "reps = 2")
                       + f'[plugin]\nclass = "{LAG}"\ntime_constant = {tc}\n')
        rows = (varied["plugin.time_constant"] == tc).to_numpy()
        pd.testing.assert_frame_equal(varied.loc[rows, metrics].reset_index(drop=True),
                                      outs[tc].loc[rows, metrics].reset_index(drop=True), check_exact=True)
    assert np.all(outs[0.0]["T"].to_numpy() != outs[0.05]["T"].to_numpy())  # the field reaches the motors
    # the plug-in's own column (Controller.extra_columns): without a lag the motors receive the QP's torques exactly
    assert np.all(outs[0.0]["lag_err_rms_Nm"] == 0.0) and np.all(outs[0.05]["lag_err_rms_Nm"] > 0.0)


def test_lag_plugin_drives_the_motors(full_run, tiny_spec, tmp_path, capsys):
    out, manifest = _run(tiny_spec, tmp_path, f'\n[plugin]\nclass = "{LAG}"\ntime_constant = 0.05\n')
    # replay re-simulates a plug-in campaign's run (its spec names the plug-in) and finds it bit for bit
    assert cli.main(["replay", str(out), "--run", "3", "--out", str(tmp_path / "replay"), "--no-video",
                     "--no-progress"]) == 0
    assert "as in the campaign; R, T, S equal bit for bit" in capsys.readouterr().out
    ref = pd.read_csv(full_run[0] / "results.csv")
    got = pd.read_csv(out / "results.csv")
    # the family's columns, then the plug-in's own (Controller.extra_columns) before the perturbations
    cols = list(ref.columns)
    at = cols.index("obj_dx_mm")
    assert list(got.columns) == cols[:at] + ["lag_err_rms_Nm"] + cols[at:] and len(got) == len(ref)
    assert np.all(got["lag_err_rms_Nm"] > 0)
    # spec_controller.TABLE_COLUMNS (what extra_columns may not take) is the table's own columns besides the
    # controller's
    from wbc_jax.campaign.controllers import CONTROLLERS
    from wbc_jax.campaign.spec_controller import TABLE_COLUMNS

    assert set(ref.columns) - set(CONTROLLERS["transport"].columns) == set(TABLE_COLUMNS)
    assert np.all(np.isfinite(got[["R", "T", "S"]].to_numpy()))
    # the lagged torques change every run's tracking and smoothness
    assert np.all(got["T"].to_numpy() != ref["T"].to_numpy()) and np.all(got["S"].to_numpy() != ref["S"].to_numpy())
    assert manifest["spec"]["plugin"] == {"class": LAG, "time_constant": 0.05}
