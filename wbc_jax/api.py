"""The Python entry points: run a campaign from a spec, load its results, write the ANOVA report.

They are what the ``wbc-jax campaign`` and ``wbc-jax report`` commands call, and are re-exported as
``wbc_jax.run_campaign``, ``wbc_jax.load_spec``, ``wbc_jax.load_results`` and ``wbc_jax.report``. Only
:func:`run_campaign` imports JAX (when it is called); loading results and reporting do not. Example::

    import wbc_jax

    wbc_jax.run_campaign("sweeps/quick.toml", "out/campaign")   # results.csv, report/, manifest.json
    df = wbc_jax.load_results("out/campaign")                   # one row per run
    summary = wbc_jax.report("out/campaign/results.csv", "out/report")
"""

from __future__ import annotations

import contextlib
import re
from pathlib import Path

from wbc_jax.campaign.interrupts import Interrupted
from wbc_jax.errors import WbcJaxError

SWITCHES = ("force", "resume", "allow-large")  # CLI flags without a value: keyword=True in Python


def python_wording(message: str) -> str:
    """A CLI message in the Python API's terms: ``--force`` -> ``force=True``, ``--out DIR`` -> ``out=DIR``,
    ``--allow-large`` -> ``allow_large=True``; any other ``--flag`` -> ``flag``. A quoted ``wbc-jax`` command line
    (up to the next ``;``) stays as it is."""

    def keyword(match: re.Match) -> str:
        name = match.group(1)
        return f"{name.replace('-', '_')}=True" if name in SWITCHES else name.replace("-", "_")

    def convert(part: str) -> str:
        return re.sub(r"--([a-z][a-z-]*)", keyword, re.sub(r"--(out|backend) ", r"\1=", part))

    parts = re.split(r"(wbc-jax [^;]*)", message)
    return "".join(part if i % 2 else convert(part) for i, part in enumerate(parts))


@contextlib.contextmanager
def _python_errors():
    """Re-raise a user error or an interruption with its message in Python wording (:func:`python_wording`)."""
    try:
        yield
    except Interrupted as error:
        raise Interrupted(error.signum, python_wording(error.where)) from None
    except WbcJaxError as error:
        raised = type(error).__new__(type(error))
        raised.__dict__.update(error.__dict__)
        raised.args = (python_wording(str(error)),) + error.args[1:]
        raise raised from None


def load_spec(path: str | Path):
    """Read and validate a campaign spec (``sweeps/*.toml``; keys in ``docs/specs.md``).

    Returns:
        The validated :class:`wbc_jax.campaign.spec.Spec` (defaults filled in).

    Raises:
        wbc_jax.errors.SpecError: one line naming the file, the key and the expected range.
    """
    from wbc_jax.campaign.spec import load_spec as _load

    return _load(path)


def run_campaign(spec_path: str | Path | None, out: str | Path, *, gains: str | Path | None = None,
                 **options) -> dict:
    """Run a campaign spec as one batched rollout and write ``out`` (``wbc-jax campaign``).

    Args:
        spec_path: campaign spec; None picks ``sweeps/quick.toml`` on a CPU-only machine and
            ``sweeps/paper_campaign.toml`` when an accelerator is present.
        out: output directory: ``results.csv``, ``report/``, ``manifest.json`` (replaced atomically on success).
        gains: optional gains TOML (``best_gains.toml`` of ``wbc-jax tune``) instead of the default gains.
        **options: passed to :func:`wbc_jax.campaign.runner.run_campaign`, e.g. ``resume=True``,
            ``report=False``, ``progress=False``; ``dry_run=True``: check and describe the campaign without running
            it (:func:`wbc_jax.campaign.dry_run.dry_run`; ``report`` and ``progress`` do not apply).

    Returns:
        The campaign manifest (the content of ``manifest.json``); with ``dry_run=True`` what it would run.

    Raises:
        wbc_jax.errors.SpecError: a bad spec or gains file, before anything runs.
        wbc_jax.errors.OutputError: ``out`` is in use by another command, not this command's, or beside a
            checkpoint of finished chunks (pass ``resume=True`` or ``force=True``), before anything runs.
        wbc_jax.campaign.interrupts.Interrupted: SIGINT or SIGTERM (a KeyboardInterrupt); its message says what was
            kept (the checkpoint of finished chunks: continue with ``resume=True``).
    """
    from wbc_jax.campaign.runner import run_campaign as _run

    if gains is not None:
        from wbc_jax.campaign.gains import load_gains

        options["gains"] = load_gains(gains)
    with _python_errors():
        if options.pop("dry_run", False):
            from wbc_jax.campaign.dry_run import dry_run

            options = {k: v for k, v in options.items() if k not in ("report", "progress")}
            return dry_run(None if spec_path is None else str(spec_path), str(out), **options)
        return _run(None if spec_path is None else str(spec_path), str(out), **options)


def load_results(path: str | Path):
    """A campaign's results table as a pandas DataFrame, one row per run.

    Args:
        path: a ``results.csv`` or a campaign output directory holding one.

    Raises:
        wbc_jax.errors.InputError: the file is missing, empty or not a CSV.
    """
    from wbc_jax.analysis.report import read_results

    p = Path(path)
    _, df = read_results(str(p / "results.csv" if p.is_dir() else p))
    return df


def report(results_csv: str | Path, out: str | Path, **options) -> dict:
    """Write the ANOVA report of a results table into ``out`` (``wbc-jax report``).

    Args:
        results_csv: results table, one row per run (a campaign's ``results.csv``).
        out: output directory (``report.md``, ``report.html``, ``anova.json``, figures; replaced atomically).
        **options: passed to :func:`wbc_jax.analysis.report.run_report`: ``alpha``, ``factors``,
            ``metrics``, ``figures``, ``ss_type``, ``order``.

    Returns:
        The content of ``anova.json``: per metric the ANOVA rows, significant terms, assumption tests.

    Raises:
        wbc_jax.errors.InputError: the table is missing or malformed.
        wbc_jax.errors.OutputError: ``out`` is not new, empty or an earlier report (``force=True`` replaces one).
    """
    from wbc_jax.analysis.report import run_report

    with _python_errors():
        return run_report(str(results_csv), str(out), **options)
