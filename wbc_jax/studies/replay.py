"""``wbc-jax replay CAMPAIGN_DIR --run N``: re-simulate runs of a finished campaign and look at them.

The runs (``--run N``, ``--runs N,M`` or ``--failed``) are simulated again exactly as the campaign simulated them
(:mod:`~wbc_jax.studies.replay_sim`: its spec, per-run draws, gains, variants, physics backend, sensing and XLA
settings, in a batch of its shape with its chunks), after its record is checked
(:mod:`~wbc_jax.studies.replay_inputs`: a spec, gains or results table that does not match ``manifest.json`` is a
one-line error and nothing is written). Each
run's R, T, S, success, failure reason and failure instant are compared with its row of ``results.csv``
(:mod:`~wbc_jax.studies.replay_check`); one line per run says whether they agree (bit for bit on the campaign's
device and backend). Per run, ``OUT/run_N/`` (its own output folder, :mod:`~wbc_jax.studies.replay_write`) holds
``trajectory.npz``, ``plots.png``, ``video.mp4`` (``video.gif`` without ffmpeg; none without an OpenGL backend)
and ``manifest.json``. An earlier replay's ``run_N`` is replaced only with ``--force``; other runs' folders stay.

Exit codes (:func:`main`): 0 every run agrees with the campaign, 1 some run does not (its line says which field; the
closing ``REPLAY MISMATCH`` line says what differed from the campaign's run, or that nothing did).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import NamedTuple

COMMAND = "wbc-jax replay"


class ReplaySummary(NamedTuple):
    """What a replay did: the output folder, each run's :class:`~wbc_jax.studies.replay_check.Check` and folder."""

    out: Path
    checks: list
    folders: dict

    @property
    def equal(self) -> bool:
        """Every replayed run agrees with the campaign's results."""
        return all(c.equal for c in self.checks)


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register the ``replay`` subcommand on ``subparsers`` (``ArgumentParser.add_subparsers``'s result)."""
    r = subparsers.add_parser("replay", help="re-simulate runs of a finished campaign (its spec, draws, gains, "
                                             "backend), check them against its results.csv, and write per run a "
                                             "video, plots.png and trajectory.npz")
    r.add_argument("campaign", metavar="CAMPAIGN_DIR", help="a finished campaign's folder (wbc-jax campaign --out)")
    which = r.add_mutually_exclusive_group(required=True)
    which.add_argument("--run", type=int, default=None, metavar="N", help="the run to replay (its run id in "
                                                                          "results.csv; default: none)")
    which.add_argument("--runs", default=None, metavar="N,M", help="comma-separated runs to replay (default: none)")
    which.add_argument("--failed", action="store_true", help="replay every failed run (default: off)")
    r.add_argument("--out", default=None, help="output folder, one run_N folder per run (default: "
                                               "CAMPAIGN_DIR/replay)")
    r.add_argument("--window", default=None, metavar="A,B",
                   help="render the video from A to B seconds of simulated time (default: the whole run; a failed "
                        "run: 5 s before to 1 s after its failure)")
    r.add_argument("--spec", default=None, help="the campaign's spec file (default: the manifest's spec_path); it "
                                                "must be the one the campaign ran")
    r.add_argument("--gains", default=None, help="the gains TOML the campaign ran with (default: none, the default "
                                                 "gains; needed when the campaign ran other gains)")
    r.add_argument("--whole-batch", action="store_true",
                   help="simulate the campaign's own runs in every slot of the batch instead of the requested runs "
                        "repeated (default: off; the exact batch, which Warp physics needs: its runs share one "
                        "contact list)")
    r.add_argument("--no-video", action="store_true", help="skip the video (default: off)")
    r.add_argument("--no-progress", action="store_true", help="no progress bar (default: off)")
    r.add_argument("--force", action="store_true", help="replace an earlier replay's run_N folders (default: off)")
    return r


def parse_runs(text: str) -> list[int]:
    """``"3,5"`` -> [3, 5]; a one-line InputError for anything else."""
    from wbc_jax.errors import InputError

    try:
        runs = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        runs = []
    if not runs or min(runs) < 0:
        raise InputError(f"--runs {text!r}: expected comma-separated run ids >= 0, e.g. --runs 3,17")
    return runs


def parse_window(text: str | None) -> tuple[float, float] | None:
    """``"14,15.5"`` -> (14.0, 15.5) [s]; None for None; a one-line InputError unless 0 <= A < B (finite)."""
    from wbc_jax.errors import InputError

    if text is None:
        return None
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        a = b = float("nan")
    if not 0.0 <= a < b < float("inf"):
        raise InputError(f"--window {text!r}: expected two times A,B in seconds with 0 <= A < B, e.g. --window 14,15")
    return a, b


def main(args: argparse.Namespace) -> int:
    """The ``replay`` subcommand: 0 when every run agrees with the campaign, 1 when one does not."""
    runs = [args.run] if args.run is not None else parse_runs(args.runs) if args.runs is not None else None
    summary = replay(args.campaign, runs, failed=args.failed, out=args.out, window=parse_window(args.window),
                     spec=args.spec, gains=args.gains, whole_batch=args.whole_batch, video=not args.no_video,
                     force=args.force, progress=not args.no_progress)
    return 0 if summary.equal else 1


def _check_outputs(out: Path, run_ids, force: bool, inputs) -> dict:
    """``out/run_N`` of each run, checked (new or empty, or an earlier replay's with ``force``) before any work."""
    from wbc_jax.io_utils import check_out_dir

    folders = {r: out / f"run_{r}" for r in run_ids}
    for folder in folders.values():
        check_out_dir(folder, COMMAND, force=force, inputs=inputs)
    return folders


def replay(campaign_dir, runs=None, *, failed: bool = False, out=None, window=None, spec=None, gains=None,
           whole_batch: bool = False, video: bool = True, force: bool = False, progress: bool = True) -> ReplaySummary:
    """Replay runs of a finished campaign and write their folders (module docstring).

    Args:
        campaign_dir: the campaign's folder.
        runs: run ids to replay (ignored with ``failed``).
        failed: replay every failed run (none: nothing is simulated or written).
        out: output folder (None: ``campaign_dir/replay``).
        window: (start, end) [s] of the video (None: the whole run; around a failed run's failure).
        spec, gains: the campaign's spec and gains files (None: the manifest's spec_path; the default gains).
        whole_batch: the campaign's own runs in every slot (:mod:`~wbc_jax.studies.replay_sim`).
        video: render the video.
        force: replace earlier replays' ``run_N`` folders.
        progress: show a progress bar on stderr.

    Raises:
        InputError, SpecError, OutputError: before anything is simulated (one line each).
    """
    from wbc_jax.errors import InputError
    from wbc_jax.io_utils import claim_out_dir, release_out_dir
    from wbc_jax.studies.replay_check import compare, line
    from wbc_jax.studies.replay_inputs import read_campaign, read_manifest, select_runs
    from wbc_jax.studies.replay_sim import adopt_xla, simulate_runs
    from wbc_jax.studies.replay_write import levels_text, write_run

    xla_notes = adopt_xla(read_manifest(Path(campaign_dir)))  # before JAX starts: XLA reads its flags then
    recorded = read_campaign(campaign_dir, spec, gains)
    run_ids = select_runs(recorded, runs, failed)
    out = Path(out) if out is not None else recorded.folder / "replay"
    if not run_ids:
        print(f"no run of {recorded.folder} failed; nothing to replay", flush=True)
        return ReplaySummary(out, [], {})
    simulated = float(recorded.manifest.get("simulated_s", float("inf")))
    if window is not None and window[0] >= simulated:
        raise InputError(f"--window {window[0]:g},{window[1]:g}: starts after the campaign's {simulated:g} s")
    inputs = [recorded.folder / "results.csv", recorded.folder / "manifest.json", recorded.spec.path, gains]
    claim_out_dir(out, COMMAND)
    try:
        folders = _check_outputs(out, run_ids, force, inputs)
        replayed = simulate_runs(recorded, run_ids, whole_batch=whole_batch, progress=progress)
        notes = xla_notes + replayed.notes
        for note in notes:
            print(f"note: {note}", flush=True)
        checks = []
        for r in run_ids:
            checks.append(compare(r, recorded.results.iloc[r], replayed.results[r]))
            note = write_run(folders[r], recorded, replayed, checks[-1], window, video)
            print(line(checks[-1], levels_text(recorded, r), folders[r]), flush=True)
            if note:
                print(f"  {note}", flush=True)
    finally:
        release_out_dir(out)
    print(verdict(checks, notes) + f"; written to {out}", flush=True)
    return ReplaySummary(out, checks, folders)


def verdict(checks: list, notes: list) -> str:
    """The closing line: how many runs reproduce the campaign's results; where some do not, whether the replay ran
    as the campaign did (then the difference is unexplained) or what differed (``notes``)."""
    differ = [c.run for c in checks if not c.equal]
    if not differ:
        return f"{len(checks)} of {len(checks)} runs reproduce the campaign's results"
    why = (f"the replay did not run exactly as the campaign did ({'; '.join(notes)})" if notes else
           "the replay ran as the campaign did (device, layout, XLA settings, versions): unexplained, please report "
           "it")
    return f"REPLAY MISMATCH: {len(differ)} of {len(checks)} runs differ from the campaign's results.csv " \
           f"({', '.join(map(str, differ))}); {why}"
