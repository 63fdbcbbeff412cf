"""The public API of ``wbc_jax`` (``wbc_jax.api``): its names, and that loading and reporting never import JAX."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_stats import planted

import wbc_jax

REPO = Path(__file__).resolve().parents[1]


def test_api_names():
    assert set(wbc_jax.__all__) == {"run_campaign", "load_spec", "load_results", "report"}
    for name in wbc_jax.__all__:
        assert callable(getattr(wbc_jax, name)) and name in dir(wbc_jax)
    with pytest.raises(AttributeError):
        wbc_jax.no_such_entry_point  # noqa: B018


def test_load_and_report_without_jax(tmp_path):
    """A fresh interpreter: import wbc_jax, load a spec and a results table, write a report; JAX stays unimported."""
    planted(seed=3).to_csv(tmp_path / "results.csv", index=False)
    code = (
        "import sys, wbc_jax\n"
        "assert wbc_jax.load_spec('sweeps/quick.toml').reps == 2\n"
        f"df = wbc_jax.load_results({str(tmp_path)!r})\n"
        f"s = wbc_jax.report({str(tmp_path / 'results.csv')!r}, {str(tmp_path / 'report')!r}, figures=False)\n"
        "assert len(df) > 0 and set(s['metrics']) >= {'R', 'T'}\n"
        "assert 'jax' not in sys.modules, 'wbc_jax imported JAX'\n"
        "wbc_jax.run_campaign  # resolving the name must not import JAX either\n"
        "assert 'jax' not in sys.modules\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "report" / "anova.json").exists()
