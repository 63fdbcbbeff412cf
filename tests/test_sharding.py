"""The run axis sharded over (fake) devices gives the same rollout as one device.

Runs in a subprocess because the device count (``--xla_force_host_platform_device_count``) must be set
before JAX starts.
"""

import subprocess
import sys
import textwrap

QPOS_TOL = 1e-3  # [m, rad] after 50 control steps with contacts, float32 (measured 1.7e-4)
SLIP_TOL = 1e-5  # [m]

SCRIPT = textwrap.dedent("""
    import os
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import numpy as np, jax
    from wbc_jax import jaxcfg; jaxcfg.configure()
    from wbc_jax.batch import prepare_batch
    from wbc_jax.control.transport import TransportConfig, control_qp_settings
    from wbc_jax.model import Robot
    from wbc_jax.planner.gait import GaitParams
    from wbc_jax.rollout import make_sim, simulate
    from wbc_jax.sharding import shard_batch
    assert len(jax.devices()) == 2
    robot = Robot("flat")
    sim = make_sim(robot, TransportConfig(qp=control_qp_settings(10)), log_every=10)
    b = prepare_batch(sim, [0.2, 0.3, 0.4], [0.4, 0.7, 1.0], [0.06, 0.08, 0.10],
                      plan_kwargs=dict(gait=GaitParams(t_start=0.02), distance=0.05))
    args = lambda b: (b.model, b.in_axes, b.state, b.plan, b.om, b.gains, b.push, b.mu_ground, 0.05)
    s1, _ = simulate(sim, *args(b), chunk_seconds=0.05)
    bs, n = shard_batch(b)
    assert n == 3 and bs.mu_ground.shape == (4,)
    assert len(bs.state.d.qpos.sharding.device_set) == 2
    s2, _ = simulate(sim, *args(bs), chunk_seconds=0.05)
    assert len(s2.d.qpos.sharding.device_set) == 2
    dq = np.abs(np.asarray(s1.d.qpos) - np.asarray(s2.d.qpos)[:n]).max()
    ds = np.abs(np.asarray(s1.acc.max_slip) - np.asarray(s2.acc.max_slip)[:n]).max()
    moved = np.abs(np.asarray(s1.d.qpos) - np.asarray(b.state.d.qpos)).max()
    print("RESULT", dq, ds, moved)
""")


def test_sharded_rollout_matches_single_device():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")][-1]
    dq, ds, moved = (float(x) for x in line.split()[1:])
    assert moved > 1e-3  # the runs really moved (a frozen rollout would match trivially)
    assert dq < QPOS_TOL and ds < SLIP_TOL
