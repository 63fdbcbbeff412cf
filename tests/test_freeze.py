"""A failed run freezes: from the control step after its failure its state and metrics stop advancing.

Two runs on flat ground, one pushed with 200 N: the pushed run fails; its row holds its metrics up to the failure
instant (finite in every numeric column), the failure time and reason; the unpushed run's row equals, bit for bit,
the same run simulated beside a run that does not fail (a 1 N push instead of 200 N: same batch size and program).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from wbc_jax.campaign.runner import run_campaign

SPEC = """
[campaign]
name = "freeze"
reps = 1
seed = 5
scene = "flat"
distance = 0.1
extra_seconds = 0.0
max_seconds = {seconds}
chunk_seconds = 0.4
qp_iters = 20
{factors}
[perturbations]
push_duration_s = 0.2
push_window = [0.1, 0.1]
push_dir_deg = 0.0
"""
SECONDS = 1.2  # [s] simulated: the push starts at 0.1 x the plan's duration and lasts 0.2 s
METRICS = ("R", "T", "S", "R_plan", "max_slip_mm", "qp_flag_fraction", "qp_iters_mean", "window_s",
           "min_clearance_mm", "final_err_mm")
SLIP_BOUND_MM = 1000.0  # [mm] a frozen run's slip stays at its failure's; a run simulated on after dropping the
#                         object reports metres


def _campaign(tmp_path, name: str, factors: str) -> pd.DataFrame:
    spec = tmp_path / f"{name}.toml"
    spec.write_text(SPEC.format(seconds=SECONDS, factors=factors))
    run_campaign(str(spec), str(tmp_path / name), report=False, progress=False)
    return pd.read_csv(tmp_path / name / "results.csv")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("freeze")
    both = _campaign(tmp, "both", "[factors]\npush_N = [0.0, 200.0]\n")
    alone = _campaign(tmp, "alone", "[factors]\npush_N = [0.0, 1.0]\n")
    return both, alone


def test_failed_run_holds_its_metrics_up_to_failure(pair):
    both, _ = pair
    pushed = both[both.push_N > 0].iloc[0]
    assert not pushed.success
    assert pushed.fail_reason
    assert 0.0 < pushed.failure_s < SECONDS
    for k in METRICS:
        assert np.isfinite(pushed[k]), k
    assert pushed.max_slip_mm < SLIP_BOUND_MM
    # the metric window ends at the failure: at most one control step after it
    assert pushed.window_s <= pushed.failure_s + 0.0011


def test_other_run_is_untouched(pair):
    both, alone = pair
    unpushed = both[both.push_N == 0].iloc[0]
    ref = alone[alone.push_N == 0].iloc[0]
    assert unpushed.success and ref.success and alone.success.all()
    assert np.isnan(unpushed.failure_s)
    for k in METRICS:
        assert unpushed[k] == ref[k], k
