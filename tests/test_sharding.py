"""The run axis sharded over (fake) devices gives the same rollout as one device.

The sharded rollout runs in a subprocess because the device count (``--xla_force_host_platform_device_count``)
must be set before JAX starts. The single-device reference runs in this process (one device) on the batch of the
CI baseline campaign (reports/baseline/spec.toml: 8 runs, perturbed starts, pushes, velocity noise) with the
campaign's compiled chunk function, which tests/test_campaign.py and tests/test_tune.py compile anyway; the
subprocess gets the first N_RUNS runs of that batch (sharding pads them to 4) and compiles only the sharded program.
"""

import pickle
import subprocess
import sys
import textwrap

import jax
import numpy as np

from wbc_jax.campaign import runner as C
from wbc_jax.campaign.spec import SWEEPS, load_spec

BASELINE_SPEC = SWEEPS.parent / "reports" / "baseline" / "spec.toml"
N_CHUNKS = 2  # campaign chunks compared (2 x 40 control steps)
N_RUNS = 3  # padded to 4: 2 runs per fake device (with 3 or more per device the sharded program deadlocks on
#             2 cores: each device's batched LAPACK triangular solve waits for slices queued on the intra-op pool
#             that both devices' programs occupy; tests/test_distributed.py's docstring)
QPOS_TOL = 1e-3  # [m, rad] after N_CHUNKS chunks with contacts, float32 (measured 6.1e-5)
SLIP_TOL = 1e-5  # [m] (measured 4.2e-6)

SCRIPT = textwrap.dedent("""
    import os, sys, pickle
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    import numpy as np, jax
    from wbc_jax.runtime import jaxcfg; jaxcfg.configure
    from wbc_jax.campaign import runner as C
    from wbc_jax.rollout import simulate
    from wbc_jax.rollout.sharding import shard_batch
    assert len(jax.devices()) == 2
    with open(sys.argv[1], "rb") as f:
        a = pickle.load(f)
    b = a["batch"]
    sim = C._sim(*a["sim_key"])  # the campaign's Sim (same settings as the reference's)
    bs, n = shard_batch(b)
    assert n == 3 and bs.mu_ground.shape == (4,)
    assert len(bs.state.d.qpos.sharding.device_set) == 2
    log_dt = sim.dt_control * sim.log_every
    st, logs = simulate(sim, bs.model, bs.in_axes, bs.state, bs.plan, bs.om, bs.gains, bs.push, bs.mu_ground,
                        (a["n_logs"] - 0.5) * log_dt, chunk_seconds=a["logs_per_chunk"] * log_dt)
    assert logs.t.shape[1] == a["n_logs"]
    assert len(st.d.qpos.sharding.device_set) == 2
    from wbc_jax.rollout import loop
    assert [f._cache_size() for f in loop._CHUNK_FNS.values()] == [1]  # chunk 2 reused chunk 1's program
    np.savez(sys.argv[2], qpos=np.asarray(st.d.qpos)[:n], max_slip=np.asarray(st.acc.max_slip)[:n], n=n)
""")


def test_sharded_rollout_matches_single_device(tmp_path):
    spec = load_spec(BASELINE_SPEC)
    sim, _, b, _, logs_per_chunk, _ = C.build(spec)
    fn = C.chunk_fn(sim, b.in_axes, logs_per_chunk)  # the campaign's (one device)
    s1 = b.state
    for _ in range(N_CHUNKS):
        s1, _ = fn(b.model, s1, b.plan, b.om, b.gains, b.push, b.mu_ground)
    n = N_RUNS
    first = lambda tree: jax.tree_util.tree_map(lambda x: np.asarray(x)[:n], jax.device_get(tree))  # noqa: E731
    model = jax.tree_util.tree_map(lambda a, x: x if a is None else np.asarray(x)[:n], b.in_axes,
                                   jax.device_get(b.model), is_leaf=lambda v: v is None)
    batch = b._replace(model=model, state=first(b.state), plan=first(b.plan), om=first(b.om), gains=first(b.gains),
                       push=first(b.push), mu_ground=first(b.mu_ground), factors=first(b.factors))
    c = spec.campaign
    args = dict(batch=batch, n_logs=N_CHUNKS * logs_per_chunk, logs_per_chunk=logs_per_chunk,
                sim_key=(c["scene"], c["qp_iters"], sim.sensor_noise, c["control_substeps"]))
    with open(tmp_path / "batch.pkl", "wb") as f:
        pickle.dump(args, f)
    res = tmp_path / "sharded.npz"
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path / "batch.pkl"), str(res)],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    with np.load(res) as z:
        qpos, slip, n_real = z["qpos"], z["max_slip"], int(z["n"])
    assert n_real == n
    dq = np.abs(np.asarray(s1.d.qpos)[:n] - qpos).max()
    ds = np.abs(np.asarray(s1.acc.max_slip)[:n] - slip).max()
    moved = np.abs(np.asarray(s1.d.qpos)[:n] - np.asarray(b.state.d.qpos)[:n]).max()
    print("RESULT", dq, ds, moved)
    assert moved > 1e-3  # the runs really moved (a frozen rollout would match trivially)
    assert dq < QPOS_TOL and ds < SLIP_TOL
