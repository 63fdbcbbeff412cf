"""wbc_jax: batched whole-body control of legged manipulators in MuJoCo MJX.

Python entry points (``wbc_jax.api``; loaded on first use, so ``import wbc_jax`` stays light and does not
import JAX):

- :func:`run_campaign` (spec_path, out): a factorial campaign as one batched rollout, with its report;
- :func:`load_spec` (path): a validated campaign spec;
- :func:`load_results` (path): a campaign's ``results.csv`` as a DataFrame;
- :func:`report` (results_csv, out): the ANOVA report of a results table.
"""

import os as _os

# Offscreen rendering (wbc_jax.analysis.video) on a headless machine: MuJoCo picks its OpenGL backend when it is
# first imported, so the default has to be set before that. An explicit MUJOCO_GL always wins.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "egl"

from wbc_jax.version import __version__  # noqa: E402, F401  (re-exported)

__all__ = ["load_results", "load_spec", "report", "run_campaign"]


def __getattr__(name: str):
    if name in __all__:
        from wbc_jax import api

        return getattr(api, name)
    raise AttributeError(f"module 'wbc_jax' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
