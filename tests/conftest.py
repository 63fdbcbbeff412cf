"""Shared pytest configuration: persistent JAX compile cache, float32 by default; the tiny campaign of
reports/baseline/spec.toml, run once per session (tests/test_campaign.py, tests/test_distributed.py)."""

import pytest

from wbc_jax.campaign.spec import SWEEPS
from wbc_jax.runtime import jaxcfg

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
