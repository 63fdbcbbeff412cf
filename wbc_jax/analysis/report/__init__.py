"""The ANOVA report of a results table (``wbc-jax report RESULTS.csv --out DIR``).

Reads the CSV, checks it, runs :func:`wbc_jax.analysis.stats.analyze`, and writes into DIR:

- ``report.md``: a title naming the campaign's spec (from the ``manifest.json`` beside the table), warnings
  first, for a campaign's table the definitions of R, T, S (formula, unit, direction), summary of significant
  terms, design, per metric the ANOVA table, assumption tests, simple main effects and descriptives, cell means,
  figures, method. A campaign's T is shown in mm throughout (results.csv keeps metres; ``anova.json`` ``units``).
- ``report.html``: the same, self-contained (figures embedded as base64 PNG).
- ``anova.json``: ``metrics`` maps each metric to ``anova`` (a list of rows with keys
  source, sum_sq, df, mean_sq, F, p, partial_eta_sq; the last row is Residual),
  ``f_tests_reliable``, ``significant``, ``assumptions``, ``simple_effects``, ``warnings`` and ``sensitivity``
  (the smallest main effect detected with 80 % power, :mod:`wbc_jax.analysis.sensitivity`); plus ``alpha``,
  ``ss_type``, ``factors`` (levels), table-wide ``warnings``, ``design`` and ``manifest``. NaN is written as null.
- ``anova.tex``: the ANOVA tables as LaTeX (``booktabs``, one per metric, significant terms bold) and the metrics'
  mean +- SD per factor level (:mod:`~.latex`).
- for a campaign's table with failed runs: a table of them (reason, instant, first non-foot contact) with each
  run's replay command (``wbc-jax replay DIR --run N``, :mod:`~.failed_runs`).
- for a campaign's table with ``R_plan``: a section (and ``anova.json`` ``r_sources``) with R from the simulator's
  and from the QP's planned object forces per cell and the boundary rule's share of each (:func:`r_sources`).
- ``design.csv``, ``cell_means.csv`` (mean, sd, n per cell and metric; CI baselines).
- ``manifest.json``: input path and SHA-256, arguments, package versions, wall time.
- ``figures/means.png`` (EMM +- 95 % CI per factor level), ``figures/interactions_<metric>.png`` (one per
  metric: EMM +- 95 % CI per two-way interaction, both orientations side by side), ``figures/qq.png`` (residual
  Q-Q plots),
  ``figures/success_levels.png`` and ``figures/success_pairs.png`` (success rate per factor level and per
  pair of factors, :mod:`wbc_jax.analysis.success`).

Besides the ANOVA: success rates per factor level and per pair of factors (all runs; ``anova.json``
``success``), and for a ``variant`` or ``observer`` factor each level against the reference controller
(:mod:`wbc_jax.analysis.ablation`: Welch t and Mann-Whitney U on max slip and R, Fisher's exact test on
success; ``anova.json`` ``ablation``).

Factors and model order: as given; else, for a campaign's ``results.csv`` with its ``manifest.json`` beside it,
the spec's factors and ``[analysis] order`` (a declared factor missing from the table: a warning, logged on one
line, and the others analysed); else m, mu, d and order 2. Refused with a one-line InputError: a run id (column
``run`` or ``run_id``) appearing twice, a JSON file (e.g. the manifest itself), a CSV separated by semicolons or
tabs.

Nothing partial is left in DIR: everything is built in memory, written to a temporary
sibling directory, and renamed into place. DIR must be new or empty, or (``force``) hold an
earlier report (:func:`wbc_jax.io_utils.check_out_dir`); it is never the folder of the input.

A table the statistics cannot fully model still gets a report, with the reason among its
warnings: a metric with values too large for sums of squares (|value| >= ``HUGE``) or one
whose model cannot be fitted (e.g. no residual degrees of freedom in a 1-rep table with a
missing value) is fitted with main effects only or left out; a table without successful
runs gets the design table only.

Modules: :mod:`~wbc_jax.analysis.report.run` (the command), :mod:`~.inputs` (reading and checking the table),
:mod:`~.model` (the statistics), :mod:`~.document` (Markdown / HTML), :mod:`~.sections`,
:mod:`~.metric_section`, :mod:`~.campaign_sections` and :mod:`~.failed_runs` (the document's sections),
:mod:`~.figure_jobs` (the figures and their captions), :mod:`~.output` (``anova.json``, ``manifest.json``, the
atomic write).
"""

from wbc_jax.analysis.report.campaign_sections import r_sources
from wbc_jax.analysis.report.inputs import CAMPAIGN_METRICS, read_campaign, read_results
from wbc_jax.analysis.report.output import COMMAND, SCHEMA, write_dir_atomic
from wbc_jax.analysis.report.run import run_report

__all__ = ["CAMPAIGN_METRICS", "COMMAND", "SCHEMA", "r_sources", "read_campaign", "read_results", "run_report",
           "write_dir_atomic"]
