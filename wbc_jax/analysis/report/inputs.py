"""The report's input: the results CSV, read and checked, and the campaign defaults beside it."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import NamedTuple

import pandas as pd

from wbc_jax.analysis import stats
from wbc_jax.errors import InputError
from wbc_jax.io_utils import read_capped

CAMPAIGN_METRICS = ("R", "T", "S")  # the metrics of a campaign's report (its results.csv has more columns)
RESULTS_LIMIT = 64 << 20  # largest results CSV read [bytes] (16384 runs: about 6 MB)


class Table(NamedTuple):
    """A results table read for a report."""

    raw: bytes  # the file's bytes (its SHA-256 goes into the manifest)
    frame: pd.DataFrame  # the parsed table, one row per run
    factors: list[str]  # factor columns
    metrics: list[str]  # metric columns
    order: int  # highest interaction order of the model


def load_table(results_csv: str, factors: list[str] | None, metrics: list[str] | None,
               order: int | None) -> Table:
    """Read ``results_csv`` and settle its factors, metrics and model order (given, else the campaign's
    (:func:`campaign_defaults`), else the defaults of :mod:`wbc_jax.analysis.stats`).

    Raises:
        InputError: unreadable or malformed input (one-line message naming the problem).
    """
    raw, df = read_results(results_csv)
    camp_factors, camp_order = campaign_defaults(results_csv, df)
    factors = stats.infer_factors(df, factors if factors is not None else camp_factors)
    order = order if order is not None else camp_order
    check_categorical(df, factors)
    if metrics is None and "fail_reason" in df.columns:  # a campaign's results.csv: the campaign report's metrics
        metrics = [m for m in CAMPAIGN_METRICS if m in df.columns] or None
    metrics = stats.infer_metrics(df, factors, metrics)
    return Table(raw, df, factors, metrics, order)


def campaign_defaults(results_csv: str, df: pd.DataFrame) -> tuple[list[str] | None, int]:
    """(factors, model order) of the campaign that wrote ``results_csv``: its ``manifest.json`` beside it
    (``wbc-jax campaign``: the spec's factors and ``[analysis] order``), the factors only if all are columns of
    ``df``; (None, 2) otherwise."""
    try:
        man = json.loads((Path(results_csv).parent / "manifest.json").read_text())
        spec = man["spec"] if man.get("command") == "wbc-jax campaign" else {}
        names = [str(f) for f in spec.get("factors", {})]
        order = spec.get("analysis", {}).get("order", 2)
    except (OSError, ValueError, TypeError, AttributeError, KeyError):
        return None, 2
    ok = bool(names) and all(f in df.columns for f in names)
    return (names if ok else None), (int(order) if isinstance(order, int) and order >= 1 else 2)


def check_categorical(df: pd.DataFrame, factors: list[str]) -> None:
    """A factor needs repeated levels: a column with about one row per value (a measurement) is refused."""
    for f in factors:
        n_lv = int(df[f].nunique(dropna=True))
        if n_lv > 2 and 2 * n_lv > len(df):
            raise InputError(f"factor '{f}' has {n_lv} distinct values in {len(df)} rows: a continuous column, "
                             "not a factor (name the factors with --factors)")


def read_results(path: str) -> tuple[bytes, pd.DataFrame]:
    """Raw bytes and parsed table of a results CSV; every failure is a one-line InputError."""
    try:
        raw = read_capped(path, RESULTS_LIMIT, what="results")
    except FileNotFoundError:
        raise InputError(f"results file not found: {path}") from None
    except IsADirectoryError:
        raise InputError(f"results path is a directory, not a file: {path}") from None
    except OSError as e:
        raise InputError(f"cannot read results file {path}: {e.strerror or e}") from None
    if not raw.strip():
        raise InputError(f"results file is empty: {path}")
    try:
        df = pd.read_csv(io.BytesIO(raw))
    except pd.errors.EmptyDataError:
        raise InputError(f"results file is empty: {path}") from None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as e:
        raise InputError(f"results file {path} is not a readable CSV: {one_line(e)}") from None
    df.columns = [str(c).strip() for c in df.columns]
    if df.empty:
        raise InputError(f"results file has a header but no rows: {path}")
    return raw, df


def one_line(e: Exception) -> str:
    """An exception's message on one line (runs of whitespace, newlines included, as one space)."""
    return " ".join(str(e).split())
