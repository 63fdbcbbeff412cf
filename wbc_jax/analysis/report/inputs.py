"""The report's input: the results CSV, read and checked, and the campaign's ``manifest.json`` beside it."""

from __future__ import annotations

import io
import json
import logging
from pathlib import Path
from typing import NamedTuple

import pandas as pd

from wbc_jax.analysis import stats
from wbc_jax.errors import InputError
from wbc_jax.io_utils import read_capped

CAMPAIGN_METRICS = ("R", "T", "S")  # the metrics of a campaign's report (its results.csv has more columns)
TROT_METRICS = ("speed_mps", "cp_err_x_rms_mm", "cp_err_y_rms_mm", "roll_amp_deg", "pitch_amp_deg")  # the
#                                                                        centroidal controller's campaign report
CAMPAIGN_COMMAND = "wbc-jax campaign"
RESULTS_LIMIT = 64 << 20  # largest results CSV read [bytes] (16384 runs: about 6 MB)
MANIFEST_LIMIT = 16 << 20  # largest manifest.json read [bytes]
RUN_ID_COLUMNS = ("run", "run_id")  # columns naming each run once
SHOWN_IDS = 10  # duplicated run ids named in an error at most

log = logging.getLogger(__name__)


class Campaign(NamedTuple):
    """What the ``manifest.json`` beside a results table says about the command that wrote it."""

    command: str  # e.g. "wbc-jax campaign"
    spec_path: str | None  # the spec file the campaign ran
    spec_hash: str | None  # sha256 of the validated spec
    name: str | None  # the spec's campaign name
    factors: list[str]  # the factors the spec declares (empty: none declared)
    order: int  # the spec's [analysis] order (2 when not given)


class Table(NamedTuple):
    """A results table read for a report."""

    raw: bytes  # the file's bytes (its SHA-256 goes into the manifest)
    frame: pd.DataFrame  # the parsed table, one row per run
    factors: list[str]  # factor columns
    metrics: list[str]  # metric columns
    order: int  # highest interaction order of the model
    campaign: Campaign | None  # the manifest beside the table, when one is there
    is_campaign: bool  # a campaign's results table: R, T, S are the transport paper's metrics
    warnings: list[str]  # table-wide warnings about the input


def load_table(results_csv: str, factors: list[str] | None, metrics: list[str] | None,
               order: int | None) -> Table:
    """Read ``results_csv`` and settle its factors, metrics and model order: as given, else the campaign's (the
    factors its manifest declares that are columns of the table; a declared factor missing from the table is a
    warning, logged and returned), else the defaults of :mod:`wbc_jax.analysis.stats`.

    Raises:
        InputError: unreadable or malformed input, duplicated run ids (one-line message naming the problem).
    """
    raw, df = read_results(results_csv)
    check_run_ids(df, results_csv)
    campaign = read_campaign(results_csv)
    warnings = []
    if factors is None and campaign is not None and campaign.factors:
        present = [f for f in campaign.factors if f in df.columns]
        missing = [f for f in campaign.factors if f not in df.columns]
        if missing:
            warnings.append(f"{results_csv} lacks the factor column(s) {', '.join(missing)} that its manifest.json "
                            f"declares (spec {campaign.spec_path}): "
                            + (f"analysing {', '.join(present)} only" if present else "default factors used"))
            log.warning("warning: %s", warnings[-1])
        factors = present or None
    factors = stats.infer_factors(df, factors)
    order = order if order is not None else (campaign.order if campaign is not None else 2)
    check_categorical(df, factors)
    is_campaign = "fail_reason" in df.columns or (campaign is not None and campaign.command == CAMPAIGN_COMMAND)
    if metrics is None and "fail_reason" in df.columns:  # a campaign's results.csv: the campaign report's metrics
        metrics = ([m for m in CAMPAIGN_METRICS if m in df.columns] or [m for m in TROT_METRICS if m in df.columns]
                   or None)
    metrics = stats.infer_metrics(df, factors, metrics)
    return Table(raw, df, factors, metrics, order, campaign, is_campaign, warnings)


def read_campaign(results_csv: str) -> Campaign | None:
    """The ``manifest.json`` beside ``results_csv`` (None when absent, unreadable or naming no command); a
    campaign's declares the spec's factors and ``[analysis] order``."""
    try:
        man = json.loads(read_capped(Path(results_csv).parent / "manifest.json", MANIFEST_LIMIT, what="manifest"))
        command = man["command"]
        spec = man.get("spec", {}) if command == CAMPAIGN_COMMAND else {}
        factors = [str(f) for f in spec.get("factors", {})]
        order = spec.get("analysis", {}).get("order", 2)
        name = spec.get("campaign", {}).get("name")
    except (OSError, ValueError, TypeError, AttributeError, KeyError, InputError):
        return None
    if not isinstance(command, str):
        return None
    order = int(order) if isinstance(order, int) and order >= 1 else 2
    return Campaign(command, _text(man.get("spec_path")), _text(man.get("spec_hash")), _text(name), factors, order)


def _text(value) -> str | None:
    return value if isinstance(value, str) and value else None


def check_run_ids(df: pd.DataFrame, path: str) -> None:
    """Each run once: a run id column (:data:`RUN_ID_COLUMNS`) with a repeated id is an InputError."""
    for col in RUN_ID_COLUMNS:
        if col not in df.columns:
            continue
        ids = df[col][df[col].duplicated(keep=False) & df[col].notna()]
        if len(ids):
            dup = list(pd.unique(ids))
            shown = ", ".join(stats.plain(i) for i in dup[:SHOWN_IDS]) + (
                f", ... ({len(dup)} in all)" if len(dup) > SHOWN_IDS else "")
            raise InputError(f"{path}: run ids appear more than once in column '{col}': {shown} "
                             "(each run once; was a table appended twice?)")


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
    _check_format(raw, path)
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


def _check_format(raw: bytes, path: str) -> None:
    """A JSON file (e.g. a campaign's manifest.json) or a CSV separated by semicolons or tabs: an InputError
    naming the cause."""
    start = raw.lstrip()[:1]
    if start in (b"{", b"["):
        beside = Path(path).parent / "results.csv"
        raise InputError(f"{path} is a JSON file, not a results CSV" + (
            f" (a campaign's manifest.json? its table is {beside})" if Path(path).name.endswith(".json") else ""))
    header = raw.lstrip().split(b"\n", 1)[0]
    for sep, name in ((b";", "semicolons"), (b"\t", "tabs")):
        if sep in header and b"," not in header:
            raise InputError(f"{path} separates its columns with {name}, not commas: write it as comma-separated "
                             "CSV (e.g. pandas to_csv with its default sep=',')")


def one_line(e: Exception) -> str:
    """An exception's message on one line (runs of whitespace, newlines included, as one space)."""
    return " ".join(str(e).split())
