"""The report's failed-runs table: each failed run of a campaign with its reason, instant and replay command."""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np
import pandas as pd

from wbc_jax.analysis.report.document import Doc, fmt
from wbc_jax.analysis.report.inputs import CAMPAIGN_COMMAND, Campaign

REPLAY_COMMAND = "wbc-jax replay"
FAILED_SHOWN = 100  # failed runs listed at most (the rest: wbc-jax replay DIR --failed, or results.csv)


def replay_command(campaign_dir: str, run: int | None = None) -> str:
    """``wbc-jax replay DIR --run N`` (``--failed`` for None), DIR quoted for a POSIX shell where needed."""
    return f"{REPLAY_COMMAND} {shlex.quote(str(campaign_dir))} " + ("--failed" if run is None else f"--run {run}")


def _failed_at(row: pd.Series) -> str:
    """When the run failed [s]: its ``failure_s``, else nothing."""
    return fmt(pd.to_numeric(row.get("failure_s", np.nan), errors="coerce"), ".3f")


def _first_contact(row: pd.Series) -> str:
    """The first non-foot contact and its time, e.g. "FR_shank (body FR_calf) / block2 at 14.475 s"."""
    pair = row.get("first_contact")
    if not isinstance(pair, str) or not pair:
        return ""
    at = fmt(pd.to_numeric(row.get("first_contact_s", np.nan), errors="coerce"), ".3f")
    return f"{pair} at {at} s" if at else pair


def failed_runs_section(d: Doc, df: pd.DataFrame, factors, campaign_dir: str | None) -> None:
    """A "Failed runs" section for a campaign's table with failed runs (nothing otherwise): per failed run its
    levels, repetition, reason, failure instant, first non-foot contact and, where ``campaign_dir`` (the folder of
    the table and its campaign manifest) is known, the command that replays it."""
    if "success" not in df.columns or "fail_reason" not in df.columns or "run" not in df.columns:
        return
    failed = df[~df["success"].astype(bool)]
    if failed.empty:
        return
    d.h(2, "Failed runs")
    text = f"{len(failed)} of {len(df)} runs failed"
    if campaign_dir is not None:
        text += (f". Each command re-simulates its run exactly as the campaign did, checks it against this table "
                 f"and writes a video, plots.png and trajectory.npz; `{replay_command(campaign_dir)}` replays them "
                 "all")
    if len(failed) > FAILED_SHOWN:
        text += f". The first {FAILED_SHOWN} are listed (all: results.csv, column success)"
    d.p(text + ".")
    rows = []
    for _, r in failed.head(FAILED_SHOWN).iterrows():
        row = [int(r["run"]), *(fmt(r[f], "g") for f in factors if f in failed.columns),
               fmt(r["rep"], "g") if "rep" in failed.columns else "", r["fail_reason"] or "", _failed_at(r),
               _first_contact(r)]
        rows.append(row + ([f"`{replay_command(campaign_dir, int(r['run']))}`"] if campaign_dir is not None else []))
    columns = ["run", *(f for f in factors if f in failed.columns), "rep", "reason", "failed at [s]",
               "first non-foot contact"] + (["replay"] if campaign_dir is not None else [])
    d.table(pd.DataFrame(rows, columns=columns))


def campaign_folder(results_csv: str, campaign: Campaign | None) -> str | None:
    """The folder of a campaign's ``results_csv`` (None unless the manifest beside it is a campaign's)."""
    return str(Path(results_csv).parent) if campaign is not None and campaign.command == CAMPAIGN_COMMAND else None
