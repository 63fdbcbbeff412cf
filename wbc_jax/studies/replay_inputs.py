"""A finished campaign's record, read and checked for a replay: its manifest, spec, results table and gains.

Each check that fails is one-line :class:`~wbc_jax.errors.InputError` (or ``SpecError``) naming the file, what
differs and what to do; nothing is simulated or written before they pass.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from wbc_jax.campaign.build import backend_of, sensing_of, with_backend
from wbc_jax.campaign.spec import Spec, load_spec, parse_spec
from wbc_jax.errors import InputError, SpecError
from wbc_jax.io_utils import read_capped

CAMPAIGN_COMMAND = "wbc-jax campaign"
MANIFEST_LIMIT = 64 << 20  # largest manifest.json read [bytes] (its seeds list grows with the runs)
RESULTS_LIMIT = 64 << 20  # largest results.csv read [bytes]
CHECKED_MEANS = ("R", "T", "S")  # the manifest's metric means checked against the table (float64 columns)
MEANS_RTOL = 1e-9  # the table's metric means against the manifest's (the same sums of the same numbers)
# floats read back exactly: pandas 3 does so by default (and deprecates the option), pandas 2 with "round_trip"
EXACT_FLOATS = {} if int(pd.__version__.split(".")[0]) >= 3 else {"float_precision": "round_trip"}


class Recorded(NamedTuple):
    """A finished campaign as a replay needs it.

    Attributes:
        folder: the campaign's folder.
        manifest: its ``manifest.json``.
        spec: its spec, checked against the manifest (or the one the manifest records), with the campaign's
            physics backend.
        results: its ``results.csv``, one row per run (floats read back exactly).
        gains: the controller gains it ran (unbatched TransportGains), None for the defaults.
    """

    folder: Path
    manifest: dict
    spec: Spec
    results: pd.DataFrame
    gains: object


def read_campaign(folder, spec_path=None, gains_path=None) -> Recorded:
    """Read and check a finished campaign.

    Args:
        folder: the campaign's folder (``manifest.json`` and ``results.csv``).
        spec_path: the spec file (default: the manifest's ``spec_path``; where that is not here, the spec the
            manifest records).
        gains_path: the gains TOML it ran with (needed when the manifest says it did not run the defaults).

    Raises:
        InputError: a missing or unreadable file, a table that does not match the manifest, gains missing or
            different from the campaign's.
        SpecError: the spec differs from the one the campaign ran, or its backend or sensing cannot be rebuilt.
    """
    folder = Path(folder)
    manifest = read_manifest(folder)
    spec = _spec(folder, manifest, spec_path)
    results = _results(folder, manifest)
    return Recorded(folder, manifest, spec, results, _gains(manifest, gains_path))


def read_manifest(folder: Path) -> dict:
    """A campaign folder's ``manifest.json``, checked to be a campaign's with the keys a replay needs."""
    path = folder / "manifest.json"
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder; name a finished campaign's folder (wbc-jax campaign --out)")
    try:
        man = json.loads(read_capped(path, MANIFEST_LIMIT, what="manifest"))
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror or e}); is {folder} a finished campaign's "
                         "folder?") from None
    except ValueError as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(man, dict) or man.get("command") != CAMPAIGN_COMMAND:
        command = man.get("command") if isinstance(man, dict) else None
        raise InputError(f"{path}: written by {command!r}, not {CAMPAIGN_COMMAND!r}; replay takes a campaign's folder")
    missing = [k for k in ("spec_path", "spec_hash", "spec_file_sha256", "n_runs", "seeds", "physics_backend",
                           "sensing", "gains_hash") if k not in man]
    if missing:
        raise InputError(f"{path}: lacks {', '.join(missing)} (written by an older version); rerun the campaign")
    return man


def _spec(folder: Path, manifest: dict, spec_path) -> Spec:
    """The campaign's spec: the file (``spec_path``, else the manifest's ``spec_path``) whose sha256 and validated
    content equal the manifest's, or, where the manifest's path does not exist here, the spec the manifest records
    (its hash checked); with the campaign's physics backend, its sensing as the campaign resolved it."""
    path = Path(spec_path if spec_path is not None else manifest["spec_path"])
    if path.is_file():
        spec = _spec_file(folder, manifest, path)
    elif spec_path is None and isinstance(manifest.get("spec"), dict):
        spec = parse_spec(manifest["spec"], f"{folder}/manifest.json spec")
        _check_plugin(folder, manifest, spec)
        if spec.hash != manifest["spec_hash"]:
            raise SpecError(f"{folder}/manifest.json: its spec does not hash to its spec_hash (edited?); pass --spec "
                            "with the spec the campaign ran")
        print(f"note: {path} (manifest.json spec_path) is not here: the spec {folder}/manifest.json records is used",
              flush=True)
    else:
        where = "--spec" if spec_path is not None else f"{folder}/manifest.json spec_path"
        raise SpecError(f"{path} ({where}): no such file; pass --spec with the spec the campaign ran")
    if spec.campaign["controller"] != "transport":  # the log, plots and checks read the transport's log fields
        raise SpecError(f"{spec.path}: campaign.controller {spec.campaign['controller']!r}: replay re-simulates "
                        "transport campaigns only (controller = \"transport\")")
    spec = with_backend(spec, manifest["physics_backend"])
    if backend_of(spec) != manifest["physics_backend"]:
        raise SpecError(f"{folder}/manifest.json physics_backend {manifest['physics_backend']!r}: resolves to "
                        f"{backend_of(spec)!r} on this machine; replay on a machine that has it")
    if sensing_of(spec) != manifest["sensing"]:
        raise SpecError(f"{spec.path}: campaign.sensing resolves to {sensing_of(spec)!r}, the campaign ran "
                        f"{manifest['sensing']!r} ({folder}/manifest.json sensing)")
    return spec


def _spec_file(folder: Path, manifest: dict, path: Path) -> Spec:
    """The spec file ``path``, refused unless its bytes and content are those the campaign ran."""
    recorded_backend = (manifest.get("spec") or {}).get("campaign", {}).get("backend")
    spec = with_backend(load_spec(path), recorded_backend)  # a campaign's --backend flag is in its spec's hash
    _check_plugin(folder, manifest, spec)
    if spec.text_sha256 != manifest["spec_file_sha256"] or spec.hash != manifest["spec_hash"]:
        raise SpecError(f"{path}: sha256 {spec.text_sha256[:12]} differs from the spec campaign {folder} ran "
                        f"(manifest.json spec_file_sha256 {str(manifest['spec_file_sha256'])[:12]}): the spec changed "
                        "since; pass --spec with the campaign's own copy")
    return spec


def _check_plugin(folder: Path, manifest: dict, spec: Spec) -> None:
    """Refuse a spec whose plug-in's module file is not the one the campaign ran (``manifest.json``
    ``plugin_sha256``)."""
    ran = manifest.get("plugin_sha256")
    if spec.plugin and ran is not None and ran != spec.plugin_sha256:
        raise SpecError(f"{spec.path}: plugin.class {spec.plugin['class']!r}: its module file changed since campaign "
                        f"{folder} ran (sha256 {spec.plugin_sha256[:12]}, manifest.json plugin_sha256 {ran[:12]}); "
                        "replay needs the code the campaign ran")


def read_results(path: Path) -> pd.DataFrame:
    """A campaign's ``results.csv`` with its floats read back exactly (:data:`EXACT_FLOATS`) and an empty
    ``fail_reason`` as ""."""
    try:
        raw = read_capped(path, RESULTS_LIMIT, what="results")
        df = pd.read_csv(io.BytesIO(raw), **EXACT_FLOATS)
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror or e})") from None
    except (ValueError, pd.errors.ParserError) as e:
        raise InputError(f"{path}: not a readable CSV ({str(e).splitlines()[0]})") from None
    if "fail_reason" in df.columns:
        df["fail_reason"] = ["" if pd.isna(v) else str(v) for v in df["fail_reason"]]
    return df


def _results(folder: Path, manifest: dict) -> pd.DataFrame:
    """``results.csv``, checked against the manifest (runs, seeds, successes, failed runs, metric means)."""
    path = folder / "results.csv"
    df = read_results(path)
    problem = _results_problem(df, manifest)
    if problem:
        raise InputError(f"{path} does not match {folder}/manifest.json: {problem} (edited, or from another "
                         "campaign?)")
    return df


def _results_problem(df: pd.DataFrame, manifest: dict) -> str | None:
    """What in the table ``df`` contradicts the manifest (the first thing found), or None."""
    n = int(manifest["n_runs"])
    need = [c for c in ("run", "seed", "success", "fail_reason", "R", "T", "S") if c not in df.columns]
    if need:
        return f"no column {need[0]}"
    if len(df) != n or not np.array_equal(df["run"].to_numpy(), np.arange(n)):
        return f"{len(df)} rows with run ids {_span(df['run'])}, the campaign has runs 0..{n - 1}"
    if not np.array_equal(df["seed"].to_numpy(np.uint64), np.asarray(manifest["seeds"], np.uint64)):
        first = int(np.argmax(df["seed"].to_numpy(np.uint64) != np.asarray(manifest["seeds"], np.uint64)))
        return f"run {first} has seed {df['seed'].iloc[first]}, the manifest {manifest['seeds'][first]}"
    success = df["success"].astype(bool)
    if "n_success" in manifest and int(success.sum()) != int(manifest["n_success"]):
        return f"{int(success.sum())} successful runs, the manifest {manifest['n_success']}"
    recorded = {int(f["run"]): str(f.get("reason") or "") for f in manifest.get("failed_runs", [])}
    table = {int(r): str(why) for r, why in zip(df["run"][~success], df["fail_reason"][~success])}
    if "failed_runs" in manifest and table != recorded:
        run = min(set(table.items()) ^ set(recorded.items()))[0]
        return (f"run {run} failed with {table.get(run, '(no failure)')!r}, the manifest says "
                f"{recorded.get(run, '(no failure)')!r}")
    for k in CHECKED_MEANS:
        mean = (manifest.get("metric_means") or {}).get(k)
        if mean is None:
            continue
        here = float(df.loc[success, k].mean())
        if not np.isclose(here, float(mean), rtol=MEANS_RTOL, atol=0.0):
            return f"mean {k} of the successful runs is {here:.9g}, the manifest {float(mean):.9g}"
    return None


def _span(col: pd.Series) -> str:
    return f"{col.min()}..{col.max()}" if len(col) else "(none)"


def _gains(manifest: dict, gains_path):
    """The gains the campaign ran: the defaults (None) or the file's, whose hash must be the manifest's."""
    from wbc_jax.campaign.gains import load_gains
    from wbc_jax.campaign.manifest import gains_hash

    path = gains_path if gains_path is not None else manifest.get("gains_path")
    if path is None:
        if not manifest.get("default_gains", True):
            raise InputError(f"the campaign ran with gains other than the defaults (manifest.json gains_hash "
                             f"{str(manifest['gains_hash'])[:12]}); pass --gains with that gains file")
        gains = None
    else:
        gains = load_gains(path)
    found = gains_hash(gains)
    if found != manifest["gains_hash"]:
        what = f"gains {path}" if path is not None else "the default gains"
        raise InputError(f"{what}: hash {found[:12]} differs from the campaign's (manifest.json gains_hash "
                         f"{str(manifest['gains_hash'])[:12]}); pass --gains with the file the campaign ran")
    return gains


def select_runs(recorded: Recorded, runs: list[int] | None, failed: bool) -> list[int]:
    """The runs to replay, ascending: ``runs`` (each a run id of the campaign) or, with ``failed``, every failed run
    (possibly none).

    Raises:
        InputError: a run id outside the campaign's runs.
    """
    n = len(recorded.results)
    if failed:
        return [int(r) for r in recorded.results["run"][~recorded.results["success"].astype(bool)]]
    bad = [r for r in runs or [] if not 0 <= r < n]
    if bad:
        raise InputError(f"run {bad[0]}: the campaign {recorded.folder} has runs 0..{n - 1}")
    return sorted(set(runs or []))
