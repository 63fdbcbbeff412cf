"""A replayed run against its row of the campaign's ``results.csv``: R, T, S, success, failure reason and instant."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

METRICS = ("R", "T", "S")
REPLAY_RTOL = 1e-6  # largest relative difference of R, T, S accepted as float rounding (a different device's)


class Check(NamedTuple):
    """One run's replay against the campaign.

    Attributes:
        run: the run id.
        equal: success, fail_reason and the failure instant exactly the campaign's, R, T, S within
            :data:`REPLAY_RTOL`.
        bit_for_bit: ``equal`` and R, T, S exactly the campaign's.
        max_rel: the largest relative difference of R, T, S (0 where both are NaN).
        differences: one phrase per field that differs, e.g. "success True (campaign False)".
        campaign: the campaign's values (R, T, S, success, fail_reason, failure_s where recorded).
        replay: the replay's values of the same fields.
    """

    run: int
    equal: bool
    bit_for_bit: bool
    max_rel: float
    differences: list
    campaign: dict
    replay: dict


def _float(x) -> float:
    return float(np.asarray(x, dtype=float))


def relative_difference(a: float, b: float) -> float:
    """|a - b| / max(|a|, |b|): 0 for equal values (NaN and NaN included), inf for a NaN against a number."""
    if math.isnan(a) or math.isnan(b):
        return 0.0 if math.isnan(a) and math.isnan(b) else math.inf
    if a == b:
        return 0.0
    return abs(a - b) / max(abs(a), abs(b))


def compare(run: int, row, result: dict) -> Check:
    """Check a replayed run's ``result`` (the run's :func:`wbc_jax.rollout.final_results` entries) against ``row``
    (its row of results.csv, floats read back exactly). ``failure_s`` is compared where both have it."""
    campaign = {k: _float(row[k]) for k in METRICS}
    replay = {k: _float(result[k]) for k in METRICS}
    campaign.update(success=bool(row["success"]), fail_reason=str(row["fail_reason"]))
    replay.update(success=bool(result["success"]), fail_reason=str(result["fail_reason"]))
    if "failure_s" in row.index and "failure_s" in result:
        campaign["failure_s"], replay["failure_s"] = _float(row["failure_s"]), _float(result["failure_s"])
    rel = {k: relative_difference(replay[k], campaign[k]) for k in METRICS}
    max_rel = max(rel.values())
    differences = [f"{k} {replay[k]!r} (campaign {campaign[k]!r}, relative difference {rel[k]:.3g})"
                   for k in METRICS if rel[k] > REPLAY_RTOL]
    for k in ("success", "fail_reason"):
        if replay[k] != campaign[k]:
            differences.append(f"{k} {replay[k]!r} (campaign {campaign[k]!r})")
    if "failure_s" in campaign and relative_difference(replay["failure_s"], campaign["failure_s"]) > 0:
        differences.append(f"failed at {replay['failure_s']:.6g} s (campaign {campaign['failure_s']:.6g} s)")
    equal = not differences
    return Check(run, equal, equal and max_rel == 0.0, max_rel, differences, campaign, replay)


def outcome(values: dict) -> str:
    """"success" or "failed[ at T s]: REASON" of a run's values (:attr:`Check.campaign` or :attr:`Check.replay`)."""
    if values["success"]:
        return "success"
    at = values.get("failure_s", math.nan)
    return f"failed{'' if math.isnan(at) else f' at {at:.3f} s'}: {values['fail_reason'] or 'unknown'}"


def line(check: Check, levels: str, folder) -> str:
    """The console line of one run: its levels, outcome, the R, T, S agreement and where its files are."""
    if check.equal:
        agreement = ("R, T, S equal bit for bit" if check.bit_for_bit
                     else f"R, T, S equal to float rounding (largest relative difference {check.max_rel:.2g})")
        return f"run {check.run} ({levels}): {outcome(check.replay)}, as in the campaign; {agreement} -> {folder}"
    return (f"run {check.run} ({levels}): MISMATCH with the campaign's results.csv: " + "; ".join(check.differences)
            + f" -> {folder}")
