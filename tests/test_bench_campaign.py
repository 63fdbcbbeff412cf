"""``bench rollout --campaign``: the campaign's own step timed beside the bench (``wbc_jax.bench.campaign_step``)."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax import cli
from wbc_jax.bench import campaign_step
from wbc_jax.campaign.build import build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.physics.backend import NACON_PER_RUN, warp_available
from wbc_jax.rollout import runs
from wbc_jax.rollout import step as step_module

TINY_SPEC = """[campaign]
name = "tiny"
reps = 1
seed = 7
scene = "flat"
distance = 0.15
speed = 0.13
extra_seconds = 0.0
qp_iters = 4
chunk_seconds = 0.2

[factors]
m = [0.2, 0.3]
mu = [0.7, 1.0]
d = [0.08, 0.10]

[perturbations]
push_max_N = 20.0
push_duration_s = 0.2
push_window = [0.2, 0.7]
qvel_noise_std = 0.02
"""


WARP_SPEC = TINY_SPEC.replace('scene = "flat"', 'scene = "flat"\nbackend = "warp"')
needs_warp = pytest.mark.skipif(not warp_available(), reason="warp-lang not installed")


@needs_warp
def test_warp_state_repeated_to_a_larger_batch_is_that_batch_s(tmp_path):
    """Warp: the spec's 8 runs repeated to 16 take the structure (static contact capacities) and shapes of the
    state of a campaign batch of 16 runs; the per-run leaves are the spec's runs, tiled."""
    path = tmp_path / "tiny.toml"
    path.write_text(WARP_SPEC)
    spec = load_spec(str(path))
    built, bigger = build(spec), build(dataclasses.replace(spec, campaign={**spec.campaign, "reps": 2}))
    assert built.design.n == 8 and bigger.design.n == 16
    fresh = campaign_step.fresh_state(built.sim, built.batch, 16)
    b = campaign_step.repeated(built.batch, built.batch.state, fresh, 16)
    assert int(b.state.d._impl.naconmax) == 16 * NACON_PER_RUN
    want = jax.tree_util.tree_structure(bigger.batch.state)
    assert jax.tree_util.tree_structure(b.state) == want
    assert [x.shape for x in jax.tree_util.tree_leaves(b.state)] == [
        x.shape for x in jax.tree_util.tree_leaves(bigger.batch.state)]
    assert jax.tree_util.tree_structure(b.state_axes) == jax.tree_util.tree_structure(bigger.batch.state_axes)
    leaves, _, axes = runs.leaves_and_axes(b.state, b.state_axes)
    source = jax.tree_util.tree_leaves(built.batch.state)
    for x, y, a in zip(leaves, source, axes):
        if a is not None:
            np.testing.assert_array_equal(np.asarray(x), np.tile(np.asarray(y), (2,) + (1,) * (y.ndim - 1)))
    assert campaign_step.fresh_state(built.sim, built.batch, 8) is built.batch.state


def test_ablations_are_sims():
    """Each ablation is the campaign's Sim with its monitors or its velocity noise changed, nothing else."""
    from types import SimpleNamespace

    from wbc_jax.rollout.config import MONITORS, Sim

    fields = {f.name: object() for f in dataclasses.fields(Sim)}
    sim = Sim(**{**fields, "monitors": "all", "sensor_noise": True})
    assert campaign_step.ablation_sim(sim, "campaign") is sim
    changed = {name: campaign_step.ablation_sim(sim, name) for name in campaign_step.ABLATIONS[1:]}
    assert (changed["no_clearance"].monitors, changed["no_monitors"].monitors) == ("no_clearance", "finite_only")
    assert changed["no_noise"].sensor_noise is False and changed["no_noise"].monitors == "all"
    assert {s.monitors for s in changed.values()} <= set(MONITORS)
    for s in changed.values():
        assert all(getattr(s, k) is v for k, v in fields.items() if k not in ("monitors", "sensor_noise"))
    with pytest.raises(KeyError):
        campaign_step.ablation_sim(SimpleNamespace(), "nothing")


def test_finite_only_still_counts_the_step():
    """The velocity noise's key and the metric window follow ``n_steps``: the ablation without the control-rate
    metrics keeps counting, or the noise would repeat and the QP would see another problem sequence."""
    from types import SimpleNamespace

    from wbc_jax.metrics.accumulate import init_accum

    acc = init_accum(jnp.float32(0.5))
    folded = step_module.fold_control(SimpleNamespace(monitors="finite_only"), acc, None, 0.001)
    assert int(folded.n_steps) == int(acc.n_steps) + 1
    assert float(folded.max_slip) == float(acc.max_slip)


def test_qp_iterations_per_step_by_hand():
    from types import SimpleNamespace

    def state(its):
        return SimpleNamespace(acc=SimpleNamespace(sum_qp_iters=np.asarray(its, np.int32)))

    assert campaign_step.qp_iterations(state([4, 8]), state([44, 128]), steps=10) == pytest.approx((4 + 12) / 2)


def test_solver_cap_share_by_hand():
    """Two runs, 50 physics steps apart: 5 and 0 more capped steps -> 5 / (2 x 50)."""
    from types import SimpleNamespace

    def state(caps):
        return SimpleNamespace(acc=SimpleNamespace(n_solver_cap=np.asarray(caps, np.int32)))

    assert campaign_step.solver_cap_share(state([3, 7]), state([8, 7]), physics_steps=50) == pytest.approx(0.05)


def test_batch_figures_by_hand():
    """Batch 10, 100 env-steps per call, two states: rates from the summed times; shares of the campaign's time."""
    first = dict(campaign=5.0, no_clearance=4.0, no_monitors=4.0, no_noise=3.0, physics=1.0)
    times = dict(campaign=[1.0, 3.0], no_clearance=[0.9, 2.7], no_monitors=[0.8, 2.4], no_noise=[0.5, 1.5],
                 physics=[0.5, 0.5])
    counts = dict(campaign=dict(qp_iters_per_step=[6.0, 10.0], solver_cap_share=[0.0, 0.5]))
    row = campaign_step.batch_figures(first, times, batch=10, n_env=100, counts=counts)
    assert row["noise_share"] == pytest.approx(0.5)
    assert row["campaign_qp_iters_per_step"] == pytest.approx(8.0)
    assert row["campaign_solver_cap_share"] == pytest.approx(0.25)
    assert row["campaign_steps_per_s"] == pytest.approx(10 * 100 * 2 / 4.0)
    assert row["campaign_steps_per_s_by_state"] == pytest.approx([1000.0, 1000.0 / 3.0])
    assert row["campaign_compile_s"] == pytest.approx(5.0 - 2.0)
    assert row["physics_share"] == pytest.approx(0.25)
    assert row["clearance_share"] == pytest.approx(0.1)
    assert row["monitors_share"] == pytest.approx(0.2)


@pytest.mark.slow
def test_campaign_step_bench_end_to_end(tmp_path):
    """A tiny flat spec (8 runs, 0.2 s chunks) on the CPU: the walk, the step at batch 3 (runs repeated) with its
    breakdown beside the bench's rows, and the JSON."""
    spec = tmp_path / "tiny.toml"
    spec.write_text(TINY_SPEC)
    out = tmp_path / "bench.json"
    assert cli.main(["bench", "rollout", "--campaign", str(spec), "--batches", "3", "--steps", "20", "--snapshots",
                     "2", "--rounds", "1", "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    step = got["campaign_step"]
    assert step["n_runs"] == 8 and step["snapshots_s"][0] == 0.0 and len(step["snapshots_s"]) == 2
    (row,) = step["batches"]
    assert row["batch"] == 3 and row["campaign_steps_per_s"] > 0 and len(row["campaign_steps_per_s_by_state"]) == 2
    assert {"clearance_share", "monitors_share", "physics_share"} <= set(row)
    assert row["campaign_solver_cap_share"] == 0.0  # MJX's JAX solver reports no iteration count
    bench_wbc = got["batches"][0]["wbc_steps_per_s"]
    assert got["batches"][0]["solver_cap_share"] == 0.0  # the bench's physics + WBC row; JAX: no count
    assert row["ratio_to_bench_wbc"] == pytest.approx(row["campaign_steps_per_s"] / bench_wbc)
    assert np.isfinite(row["no_monitors_steps_per_s"])


def test_time_batch_compiles_once_and_times_every_state(monkeypatch):
    """Every program compiled once (on state 0) and called once per state; batches made one at a time."""
    from types import SimpleNamespace

    calls, made = [], []
    monkeypatch.setattr(campaign_step, "compiled_chunk", lambda sim, b, n_logs, name: (
        lambda *args: (calls.append((name, args[1].i)), (args[1], None))[1]))
    monkeypatch.setattr(campaign_step, "qp_iterations", lambda before, after, steps: 4.0)
    monkeypatch.setattr(campaign_step, "solver_cap_share", lambda before, after, steps: 0.5 if steps == 20 else None)
    monkeypatch.setattr(campaign_step, "physics_only_fn", lambda b, n_env: (
        lambda model, d: calls.append(("physics", d))))

    def batch_at(i):
        made.append(i)
        state = SimpleNamespace(i=i, d=i)
        return SimpleNamespace(model=None, state=state, plan=None, om=None, gains=None, push=None, mu_ground=None)

    first, times, counts = campaign_step._time_batch(None, batch_at, 3, 1, campaign_step.ABLATIONS, 20)
    assert set(counts) == set(campaign_step.ABLATIONS) - {"no_monitors"}
    assert all(v == dict(qp_iters_per_step=[4.0] * 3, solver_cap_share=[0.5] * 3) for v in counts.values())
    assert made == [0, 1, 2] and set(first) == {*campaign_step.ABLATIONS, "physics"}
    assert all(len(t) == 3 for t in times.values())
    timed = calls[len(first):]  # after each program's first call
    assert timed == [(name, i) for i in range(3) for name in (*campaign_step.ABLATIONS, "physics")]


def test_time_batch_rounds_alternate_and_keep_the_median(monkeypatch):
    """With ``rounds`` = 3 every program is called three times per state, alternated with the others round by round;
    each state's time is the median of its three walls, and the counts are read once per state."""
    from types import SimpleNamespace

    calls, walls = [], iter(float(w * w) for w in range(1, 1000))  # squares: a median is not a mean
    monkeypatch.setattr(campaign_step, "compiled_chunk", lambda sim, b, n_logs, name: (
        lambda *args: (calls.append((name, args[1].i)), (args[1], None))[1]))
    monkeypatch.setattr(campaign_step, "qp_iterations", lambda before, after, steps: 4.0)
    monkeypatch.setattr(campaign_step, "solver_cap_share", lambda before, after, steps: 0.5)
    monkeypatch.setattr(campaign_step, "physics_only_fn", lambda b, n_env: (
        lambda model, d: calls.append(("physics", d))))
    monkeypatch.setattr(campaign_step, "timed", lambda f, *args: (f(*args), next(walls)))

    def batch_at(i):
        state = SimpleNamespace(i=i, d=i)
        return SimpleNamespace(model=None, state=state, plan=None, om=None, gains=None, push=None, mu_ground=None)

    names = (*campaign_step.ABLATIONS, "physics")
    first, times, counts = campaign_step._time_batch(None, batch_at, 2, 1, campaign_step.ABLATIONS, 20, rounds=3)
    k = len(names)
    assert calls[k:] == [(name, i) for i in range(2) for _ in range(3) for name in names]
    # the n-th wall handed out is n**2, in call order; 1 went to physics alone's first call (the programs' first
    # calls, which compile, are timed by the clock); the median of a state's three is its second round's
    for j, name in enumerate(names):
        for i in range(2):
            assert times[name][i] == float((2 + j + k * (3 * i + 1)) ** 2)
    assert all(v == dict(qp_iters_per_step=[4.0] * 2, solver_cap_share=[0.5] * 2) for v in counts.values())


@pytest.mark.slow
@needs_warp
def test_campaign_step_bench_warp_batch_larger_than_the_spec(tmp_path):
    """Warp, the tiny spec's 8 runs timed at batch 12 (runs repeated into a larger batch with its own contact
    list): the command completes and writes the row."""
    spec = tmp_path / "tiny.toml"
    spec.write_text(WARP_SPEC)
    out = tmp_path / "bench.json"
    assert cli.main(["bench", "rollout", "--backend", "warp", "--campaign", str(spec), "--batches", "12",
                     "--breakdown", "8", "--steps", "2", "--snapshots", "1", "--rounds", "1", "--json",
                     str(out)]) == 0
    (row,) = json.loads(out.read_text())["campaign_step"]["batches"]
    assert row["batch"] == 12 and row["campaign_steps_per_s"] > 0 and "monitors_share" not in row
    assert 0.0 <= row["campaign_solver_cap_share"] <= 1.0  # Warp counts its solver's iterations
