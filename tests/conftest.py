"""Shared pytest configuration: XLA's CPU compile settings of the tests, persistent JAX compile cache, float32 by
default; the tiny campaign of reports/baseline/spec.toml, run once per session (tests/test_campaign.py,
tests/test_distributed.py)."""

import os

import pytest

from wbc_jax.campaign.spec import SWEEPS
from wbc_jax.runtime import jaxcfg

# Where no CUDA backend can start, the tests' programs are compiled with XLA's elemental fusion emitters instead of
# its newer MLIR ones: a CPU test run is mostly XLA compiling MJX programs, which the elemental emitters do in a
# fraction of the time, while the short horizons simulated here hardly feel the difference in run time. Set before
# JAX starts (XLA reads XLA_FLAGS then); subprocesses inherit it; a flag already in XLA_FLAGS is kept as given.
TEST_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
if not jaxcfg._cuda_plugin_installed():
    _given = os.environ.get("XLA_FLAGS", "")
    _added = [f for f in TEST_XLA_FLAGS if f.partition("=")[0] not in _given]
    os.environ["XLA_FLAGS"] = " ".join([*_added, _given]).strip()

jaxcfg.configure()


@pytest.fixture(scope="session")
def tiny_spec():
    return SWEEPS.parent / "reports" / "baseline" / "spec.toml"


@pytest.fixture(scope="session")
def full_run(tiny_spec, tmp_path_factory):
    """(out folder, manifest) of the tiny campaign run in this process (one device)."""
    from wbc_jax.campaign.runner import run_campaign

    out = tmp_path_factory.mktemp("camp") / "full"
    manifest = run_campaign(str(tiny_spec), str(out), progress=False)
    return out, manifest
