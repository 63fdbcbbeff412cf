"""Shared pytest configuration: XLA's CPU compile settings of the tests, persistent JAX compile cache, float32 by
default; the tiny campaign of reports/baseline/spec.toml, run once per session (tests/test_campaign.py,
tests/test_distributed.py)."""

import os

import pytest

from wbc_jax.campaign.spec import SWEEPS
from wbc_jax.runtime import jaxcfg

# Where no CUDA backend can start, the tests' programs are compiled with XLA's elemental fusion emitters instead of
# its newer MLIR ones and, unless a selected test is marked `llvm_default`, with LLVM at -O0: a CPU test run is
# mostly XLA compiling MJX programs, which these settings do in a fraction of the time; the short horizons simulated
# here lose less to the slower code than the compile saves. A test whose result depends on LLVM's optimized code
# (-O0 forms no fused multiply-adds) is marked `llvm_default`: a session that selects one compiles at LLVM's default
# level. Set before JAX starts (XLA reads XLA_FLAGS then); subprocesses inherit them; a flag already in XLA_FLAGS is
# kept as given.
CPU_TEST = not jaxcfg._cuda_plugin_installed()
TEST_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
TEST_XLA_FLAGS_NO_FMA = ("--xla_backend_optimization_level=0",)


def _add_xla_flags(flags) -> None:
    given = os.environ.get("XLA_FLAGS", "")
    added = [f for f in flags if f.partition("=")[0] not in given]
    os.environ["XLA_FLAGS"] = " ".join([*added, given]).strip()


if CPU_TEST:
    _add_xla_flags(TEST_XLA_FLAGS)
jaxcfg.configure()


def pytest_configure(config):
    config.addinivalue_line("markers", "llvm_default: its result depends on LLVM's optimized code (e.g. fused "
                                       "multiply-adds): the session compiles at LLVM's default level (conftest.py)")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    """LLVM at -O0 for the session's programs unless a selected test is marked ``llvm_default`` (the selection is
    final here: ``-m``/``-k`` have deselected; JAX has not started, so XLA reads the flag)."""
    if CPU_TEST and not jaxcfg.backends_started() and not any(i.get_closest_marker("llvm_default") for i in items):
        _add_xla_flags(TEST_XLA_FLAGS_NO_FMA)


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
