"""A failed run freezes: from the control step after its failure its state and metrics stop advancing.

Four runs on flat ground (push_N x variant), two pushed with 200 N: the pushed runs fail; their rows hold their
metrics up to the failure instant (finite in every numeric column), the failure time and reason; the unpushed runs'
rows equal, bit for bit, the same runs simulated beside runs that do not fail (a 1 N push instead of 200 N). The
campaigns have tests/test_factors.py's rollout shape (its push_N x variant campaign's factors, run length and chunk
length), so they run the chunk program that file compiles.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from test_factors import SAME_SHAPE, TINY

from wbc_jax.campaign.runner import run_campaign

SECONDS = 0.5  # [s] simulated: the push starts at once and lasts 0.2 s; the pushed runs fail at about 0.3 s and
#                stay frozen to the end (about 0.2 s)
PERTURBATIONS = "push_duration_s = 0.2\npush_window = [0.0, 0.0]\npush_dir_deg = 0.0"
METRICS = ("R", "T", "S", "R_plan", "max_slip_mm", "qp_flag_fraction", "qp_iters_mean", "window_s",
           "min_clearance_mm", "final_err_mm")
SLIP_BOUND_MM = 1000.0  # [mm] a frozen run's slip stays at its failure's; a run simulated on after dropping the
#                         object reports metres


def _campaign(tmp_path, name: str, factors: str) -> pd.DataFrame:
    spec = tmp_path / f"{name}.toml"
    assert "max_seconds = 0.06" in TINY
    spec.write_text(TINY.replace("max_seconds = 0.06", f"max_seconds = {SECONDS}").format(
        campaign=SAME_SHAPE, factors=factors, perturbations=PERTURBATIONS))
    run_campaign(str(spec), str(tmp_path / name), report=False, progress=False)
    return pd.read_csv(tmp_path / name / "results.csv")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("freeze")
    variants = 'variant = ["full", "no_observer"]'
    both = _campaign(tmp, "both", f"push_N = [0.0, 200.0]\n{variants}")
    alone = _campaign(tmp, "alone", f"push_N = [0.0, 1.0]\n{variants}")
    return both, alone


def test_failed_run_holds_its_metrics_up_to_failure(pair):
    both, _ = pair
    pushed = both[both.push_N > 0]
    assert len(pushed) == 2
    for _, run in pushed.iterrows():
        assert not run.success
        assert run.fail_reason
        assert 0.0 < run.failure_s < SECONDS
        for k in METRICS:
            assert np.isfinite(run[k]), k
        assert run.max_slip_mm < SLIP_BOUND_MM
        # the metric window ends at the failure: at most one control step after it
        assert run.window_s <= run.failure_s + 0.0011


def test_other_run_is_untouched(pair):
    both, alone = pair
    unpushed, ref = both[both.push_N == 0], alone[alone.push_N == 0]
    assert len(unpushed) == 2 and list(unpushed.variant) == list(ref.variant)
    assert unpushed.success.all() and alone.success.all()
    assert unpushed.failure_s.isna().all()
    for k in METRICS:
        np.testing.assert_array_equal(unpushed[k].to_numpy(), ref[k].to_numpy(), err_msg=k)


def test_frozen_run_keeps_its_controller_state_but_the_qp_warm_start():
    """Controller.freeze: a frozen run keeps its controller state leaf for leaf (the base rule); the transport's QP
    warm start (solution, multipliers, carried factors) follows the new step's, which no kept value depends on."""
    import jax.numpy as jnp

    from wbc_jax.control.transport import ControlState, TransportConfig, control_qp_settings, initial_factors
    from wbc_jax.control.variants import FULL, Variant
    from wbc_jax.qp import QPResult
    from wbc_jax.rollout.controllers.transport import TransportController

    cfg = TransportConfig(qp=control_qp_settings(kernel="fused", reuse_factors=True))
    f0 = initial_factors(cfg)

    def state(v):
        warm = QPResult(*(jnp.full((3,), v) for _ in range(8)), factors=f0._replace(c=jnp.asarray(v)))
        return ControlState(warm=warm, obs=jnp.full((2,), v), q_post=jnp.full((6,), v),
                            variant=Variant(*(jnp.asarray(x, float) for x in FULL)))

    old, new = state(1.0), state(2.0)
    ctl = TransportController(cfg)
    frozen, live = ctl.freeze(jnp.asarray(True), new, old), ctl.freeze(jnp.asarray(False), new, old)
    assert float(frozen.warm.x[0]) == 2.0 and float(frozen.obs[0]) == 1.0 and float(frozen.warm.factors.c) == 2.0
    assert float(frozen.q_post[0]) == 1.0 and float(frozen.warm.rho[0]) == 2.0
    assert float(live.warm.x[0]) == 2.0 and float(live.obs[0]) == 2.0 and float(live.warm.factors.c) == 2.0


def test_frozen_centroidal_run_keeps_its_state_but_the_qp_warm_start():
    import jax.numpy as jnp

    from wbc_jax.control.centroidal import CentroidalConfig, CentroidalState
    from wbc_jax.qp import QPResult
    from wbc_jax.rollout.controllers.centroidal import CentroidalController

    def state(v):
        return CentroidalState(warm=QPResult(*(jnp.full((3,), v) for _ in range(8))),
                               sw_int=jnp.full((4, 3), v), q_post=jnp.full((6,), v))

    old, new = state(1.0), state(2.0)
    ctl = CentroidalController(CentroidalConfig())
    frozen, live = ctl.freeze(jnp.asarray(True), new, old), ctl.freeze(jnp.asarray(False), new, old)
    assert float(frozen.warm.x[0]) == 2.0 and float(frozen.sw_int[0, 0]) == 1.0 and float(frozen.q_post[0]) == 1.0
    assert float(live.warm.y[0]) == 2.0 and float(live.sw_int[0, 0]) == 2.0 and float(live.q_post[0]) == 2.0
