"""The report's machine-readable outputs (``anova.json``, ``manifest.json``) and the atomic write of its folder."""

from __future__ import annotations

import hashlib
import json
import math
import platform
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from wbc_jax.analysis import interaction, sensitivity, stats
from wbc_jax.errors import WbcJaxError
from wbc_jax.io_utils import atomic_dir
from wbc_jax.version import __version__

SCHEMA = "wbc_jax.analysis.report/1"
COMMAND = "wbc-jax report"


class Request(NamedTuple):
    """What a report was asked for: its input and its settings."""

    results_csv: str  # the input path
    raw: bytes  # the input's bytes
    alpha: float  # significance level
    factors: list[str]  # factor columns
    ss_type: int  # sums-of-squares type: 1, 2 or 3
    order: int  # highest interaction order of the model
    started: float  # time.perf_counter() at the start [s]


def manifest(request: Request, rows: int, metrics: list[str]) -> dict:
    """``manifest.json`` without its wall time: input path and SHA-256, arguments, package versions."""
    return {
        "command": COMMAND, "input": str(request.results_csv), "sha256": hashlib.sha256(request.raw).hexdigest(),
        "rows": rows, "alpha": request.alpha, "factors": request.factors, "metrics": metrics,
        "ss_type": stats.SS_NAMES[request.ss_type], "order": request.order, "versions": versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def wall_s(request: Request) -> float:
    """Seconds since the report started, rounded to ms."""
    return round(time.perf_counter() - request.started, 3)


def summary(res: dict, data: pd.DataFrame, factors, alpha: float, manifest: dict) -> dict:
    """``anova.json`` (before :func:`clean`) of an analysis (:func:`~wbc_jax.analysis.report.model.analyze_table`)."""
    per = {}
    for m, r in res["metrics"].items():
        fit = r["fit"]
        per[m] = {
            "formula": fit.formula, "n": fit.n, "mse": fit.mse, "df_resid": fit.df_resid,
            "ss_type": fit.ss_type, "anova": fit.table, "f_tests_reliable": fit.reliable,
            "unreliable_reasons": fit.unreliable_reasons,
            "significant": r["significant"], "assumptions": r["assumptions"],
            "simple_effects": r["simple_effects"],
            "interaction_shapes": interaction.shapes(r["emms"]),
            "warnings": r["warnings"],
            "sensitivity": {"power": sensitivity.POWER, "main_effect_range": sensitivity.main_effect_ranges(
                fit, res["level_means"][res["level_means"]["metric"] == m], alpha)},
        }
    return {
        "schema": SCHEMA, "alpha": alpha, "ss_type": manifest["ss_type"],
        "contrasts": "sum-to-zero (C(x, Sum))", "model_order": manifest["order"],
        "factors": {f: stats.levels(data[f]) for f in factors}, "n_runs": res["n_runs"],
        "n_failed": res["n_failed"], "warnings": res["warnings"], "design": res["design"],
        "metrics": per, "manifest": manifest,
    }


def extra_json(extra: dict) -> dict:
    """The ``success`` and ``ablation`` entries of ``anova.json``
    (:func:`~wbc_jax.analysis.report.model.beyond_anova`)."""
    return {"success": {"by_level": extra["by_level"],
                        "by_pair": {":".join(p): t for p, t in extra["by_pair"].items()}},
            "ablation": extra["ablation"]}


def write_dir_atomic(out_dir: str, files: dict[str, bytes]) -> None:
    """Write ``files`` (relative path -> bytes) as directory ``out_dir``, all or nothing."""
    out = Path(out_dir).absolute()
    if out.exists() and not out.is_dir():
        raise WbcJaxError(f"output path exists and is not a directory: {out_dir}")
    try:
        with atomic_dir(out) as tmp:
            for rel, data in files.items():
                p = tmp / rel
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(data)
    except OSError as e:
        raise WbcJaxError(f"cannot write report to {out_dir}: {e.strerror or e}") from None


def versions() -> dict:
    """The versions of wbc_jax, Python and the statistics and plotting packages."""
    return {"wbc_jax": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": _version("scipy"), "pandas": pd.__version__, "statsmodels": _version("statsmodels"),
            "matplotlib": _version("matplotlib")}


def _version(name: str) -> str:
    """An installed package's version without importing it (an import of matplotlib alone is slow)."""
    from importlib import import_module, metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:  # not installed as a distribution: ask the module
        return import_module(name).__version__


def clean(x):
    """JSON-safe copy: numpy scalars to Python, NaN/inf to None, DataFrames to records."""
    if isinstance(x, pd.DataFrame):
        return [clean(r) for r in x.to_dict(orient="records")]
    if isinstance(x, dict):
        return {str(k): clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [clean(v) for v in x]
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer, int)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    return x


def dumps(obj) -> str:
    """``obj`` as indented, strict JSON (:func:`clean` first)."""
    return json.dumps(clean(obj), indent=1, allow_nan=False) + "\n"
