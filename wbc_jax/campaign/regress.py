"""``wbc-jax regress``: CI regression of per-cell metric means against a stored baseline.

A baseline folder holds ``spec.toml`` (the spec rerun) and ``baseline.json`` (per-cell means over successful runs,
success counts, tolerance bands and, when stored on a CPU, each cell's rounding noise from reruns with XLA's CPU
code generation capped at older instruction sets).
"""

from __future__ import annotations

import itertools
import json
import os
import tempfile
from pathlib import Path

import jax
import numpy as np

from wbc_jax.campaign import controllers
from wbc_jax.campaign.factors import OBJECT
from wbc_jax.campaign.runner import run_campaign, run_in_fresh_process
from wbc_jax.campaign.spec import load_spec
from wbc_jax.errors import InputError, SpecError, WbcJaxError
from wbc_jax.io_utils import read_capped, write_json_atomic

DEFAULT_TOL = controllers.CONTROLLERS["transport"].regress  # the transport's (rel, abs) bands; each controller's:
#                                                             wbc_jax.campaign.controllers (.regress)
REGRESS_METRICS = tuple(DEFAULT_TOL)
# Rounding probes of `regress --update` on the CPU: the baseline spec rerun with XLA's CPU code generation capped at
# these instruction sets. Another machine's CPU (vector width, FMA contraction) rounds float32 differently, which in
# short runs with sliding contacts moves some cell means by more than the tolerance; the probes' spread is stored per
# cell and metric and widens that cell's band.
ROUNDING_PROBE_ISAS = ("SSE4_2", "AVX", "AVX2")
NOISE_FACTOR = 2.0  # band = rel |baseline| + abs + NOISE_FACTOR x the probes' largest deviation from their mean


def _rounding_probes(spec_p: Path, factors, metrics) -> list[list[dict]]:
    """Cell means of the spec rerun in fresh processes with XLA's CPU codegen capped at each ROUNDING_PROBE_ISAS
    entry (one compile each, no persistent cache). A probe that fails is an error: the noise floor would be unknown."""
    import pandas as pd

    out = []
    for isa in ROUNDING_PROBE_ISAS:
        with tempfile.TemporaryDirectory() as td:
            print(f"rounding probe: {spec_p} with --xla_cpu_max_isa={isa}", flush=True)
            flags = (os.environ.get("XLA_FLAGS", "") + f" --xla_cpu_max_isa={isa}").strip()
            run = run_in_fresh_process(spec_p, Path(td) / "run", JAX_PLATFORMS="cpu", WBC_JAX_CACHE="off",
                                       XLA_FLAGS=flags)
            out.append(cell_means(pd.read_csv(run / "results.csv"), factors, metrics))
    return out


def _with_noise(cells: list[dict], probes: list[list[dict]], metrics=REGRESS_METRICS) -> list[dict]:
    """``cells`` with each metric replaced by its mean over this run and the probes, and ``noise``: per metric the
    largest |run - mean| (None where a metric is undefined in some run). Success counts stay this run's."""
    runs = [cells] + probes
    out = []
    for i, c in enumerate(cells):
        c = dict(c)
        noise = {}
        for k in metrics:
            vals = [r[i][k] for r in runs]
            if any(v is None for v in vals):
                noise[k] = None
                continue
            mean = float(np.mean(vals))
            c[k] = mean
            noise[k] = float(np.max(np.abs(np.asarray(vals) - mean)))
        c["noise"] = noise
        out.append(c)
    return out


def cell_means(df, factors=OBJECT, metrics=REGRESS_METRICS) -> list[dict]:
    """Per-cell means of the regression ``metrics`` over successful runs, and success counts; a cell is one
    combination of ``factors``' levels (the spec's factors: every one of them, so distinct cells never merge)."""
    rows = []
    for key, g in df.groupby(list(factors)):
        key = key if isinstance(key, tuple) else (key,)
        ok = g[g.success.astype(bool)]
        rows.append(dict(**{f: _plain_level(v) for f, v in zip(factors, key)}, runs=int(len(g)),
                         n_success=int(len(ok)),
                         **{k: (float(ok[k].mean()) if len(ok) else None) for k in metrics}))
    return rows


def _plain_level(v):
    """A factor level as JSON keeps it: a float for a number, the string for a choice."""
    v = v.item() if isinstance(v, np.generic) else v
    return v if isinstance(v, str) else float(v)


def _key(cell: dict, factors) -> tuple:
    return tuple(_plain_level(cell[f]) for f in factors)


def _label(key: tuple, factors) -> str:
    return " ".join(f"{f}={v:g}" if isinstance(v, float) else f"{f}={v}" for f, v in zip(factors, key))


def compare(baseline: dict, cells: list[dict], factors=None) -> list[dict]:
    """Rows that moved: a metric mean outside |new - old| <= rel |old| + abs + NOISE_FACTOR x noise (the cell's
    rounding noise, ``old["noise"][metric]``, 0 where the baseline has none), a success count change or a
    missing cell. Cells are matched on ``factors`` (default: the baseline's, else m, mu, d); the metrics are those
    of the baseline's ``tolerance``."""
    factors = list(factors or baseline.get("factors") or OBJECT)
    tol = baseline["tolerance"]
    new = {_key(c, factors): c for c in cells}
    moved = []
    for old in baseline["cells"]:
        noise = old.get("noise") or {}
        key = _key(old, factors)
        c = new.get(key)
        if c is None:
            moved.append(dict(cell=key, metric="(cell)", baseline="present", now="missing", band=""))
            continue
        if c["n_success"] != old["n_success"]:
            moved.append(dict(cell=key, metric="n_success", baseline=old["n_success"], now=c["n_success"],
                              band="exact"))
        for k in tol:
            a, b = old.get(k), c.get(k)
            rel, ab = tol[k]["rel"], tol[k]["abs"]
            if a is None or b is None:
                if (a is None) != (b is None):
                    moved.append(dict(cell=key, metric=k, baseline=a, now=b, band="defined"))
                continue
            band = rel * abs(a) + ab + NOISE_FACTOR * float(noise.get(k) or 0.0)
            if not abs(b - a) <= band:
                moved.append(dict(cell=key, metric=k, baseline=a, now=b, band=f"+-{band:.3g}"))
    return moved


def load_baseline(base_p: Path, factors=OBJECT, metrics=REGRESS_METRICS) -> dict:
    """Read and check ``baseline.json``: a ``tolerance`` (rel, abs >= 0 per metric of ``metrics``), a non-empty
    list of ``cells`` (each factor's level, n_success and each metric a number or null) and the ``spec_hash``.

    Raises:
        WbcJaxError: one line naming the file and the first problem.
    """
    def bad(what):
        return WbcJaxError(f"{base_p}: not a valid baseline file ({what}); recreate it with wbc-jax regress "
                           f"--baseline {base_p.parent} --update")

    try:
        b = json.loads(read_capped(base_p, what="baseline"))
    except (OSError, InputError) as e:
        raise bad(f"cannot read it: {getattr(e, 'strerror', None) or e}") from None
    except ValueError as e:
        raise bad(f"not JSON: {e}") from None
    if not isinstance(b, dict) or not isinstance(b.get("tolerance"), dict) or not isinstance(b.get("cells"), list):
        raise bad("expected keys tolerance, cells")
    if not isinstance(b.get("spec_hash"), str):
        raise bad("expected key spec_hash")
    for k in metrics:
        t = b["tolerance"].get(k)
        if not (isinstance(t, dict) and _num(t.get("rel")) and _num(t.get("abs")) and t["rel"] >= 0 and t["abs"] >= 0):
            raise bad(f"tolerance.{k}: expected rel and abs numbers >= 0")
    if not b["cells"]:
        raise bad("no cells: it would compare nothing")
    for i, c in enumerate(b["cells"]):
        if not (isinstance(c, dict) and all(_num(c.get(f)) or isinstance(c.get(f), str) for f in factors)
                and _num(c.get("n_success")) and all(c.get(k) is None or _num(c.get(k)) for k in metrics)
                and (c.get("noise") is None or isinstance(c["noise"], dict))):
            raise bad(f"cells[{i}]: expected {', '.join(factors)} levels, an n_success number and metric numbers "
                      "or null")
    return b


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def check_coverage(baseline: dict, spec, base_p: Path) -> None:
    """The baseline's cells are exactly the cells of the spec's design (every combination of its factors' levels).

    Raises:
        WbcJaxError: a design cell without a baseline cell, a baseline cell outside the design, or a cell twice.
    """
    factors = list(spec.factors)
    design = {tuple(_plain_level(v) for v in combo) for combo in itertools.product(*spec.factors.values())}
    keys = [_key(c, factors) for c in baseline["cells"]]
    missing = sorted(design - set(keys), key=str)
    extra = sorted(set(keys) - design, key=str)
    twice = len(keys) != len(set(keys))
    if missing or extra or twice:
        what = (f"missing {_label(missing[0], factors)}" if missing else
                f"{_label(extra[0], factors)} is not in the design" if extra else "a cell appears twice")
        raise WbcJaxError(f"{base_p}: its cells do not cover the {len(design)} cells of {spec.path}'s design "
                          f"({len(design & set(keys))} covered; {what}); recreate it with wbc-jax regress --baseline "
                          f"{base_p.parent} --update")


def _check_writable(base_p: Path) -> None:
    """``--update`` can write ``base_p`` (a file without write permission counts as read-only, whoever runs):
    checked before the rerun, which takes minutes."""
    if base_p.exists() and not base_p.stat().st_mode & 0o222:
        raise WbcJaxError(f"{base_p}: read-only (mode {base_p.stat().st_mode & 0o777:04o}); make it writable to "
                          "update the baseline")
    try:
        fd, probe = tempfile.mkstemp(prefix=".probe-", dir=base_p.parent)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise WbcJaxError(f"{base_p.parent}: read-only ({e.strerror or e}); make it writable to update the "
                          "baseline") from None


def run_regress(baseline_dir: str, update: bool = False, gains=None, out: str | None = None) -> tuple[int, list]:
    """Rerun the baseline's stored spec (``DIR/spec.toml``) and compare per-cell metric means with
    ``DIR/baseline.json`` (means + tolerance band; cells: every combination of the spec's factors). Returns (exit
    code: 0 pass / 1 moved, moved rows). ``update``: rewrite baseline.json (tolerances kept) and return 0; on the
    CPU the spec also runs once per :data:`ROUNDING_PROBE_ISAS` entry in a subprocess (:func:`_rounding_probes`):
    the stored means are the mean over all runs and each cell's ``noise`` the largest deviation from it.

    Raises:
        SpecError, WbcJaxError: before the rerun: no spec, a missing or invalid baseline, a changed spec, cells that
            do not cover the design, a read-only baseline with ``update``.
    """
    bdir = Path(baseline_dir)
    spec_p = bdir / "spec.toml"
    if not spec_p.exists():
        raise SpecError(f"{bdir}: no spec.toml in the baseline directory")
    spec = load_spec(spec_p)
    factors = list(spec.factors)
    metrics = tuple(controllers.info(spec.campaign).regress)
    base_p = bdir / "baseline.json"
    baseline = None
    if base_p.exists():  # checked before anything is rerun
        baseline = load_baseline(base_p, factors, metrics)
    elif not update:
        raise WbcJaxError(f"{base_p}: missing; create it with wbc-jax regress --baseline {bdir} --update")
    if update:
        _check_writable(base_p)
    elif baseline["spec_hash"] != spec.hash:
        raise WbcJaxError(f"{spec_p}: spec{' or its plug-in' if spec.plugin else ''} changed since the baseline was "
                          "stored; rerun with --update")
    else:
        check_coverage(baseline, spec, base_p)
    with tempfile.TemporaryDirectory() as td:
        run_dir = Path(out) if out else Path(td) / "run"
        run_campaign(str(spec_p), str(run_dir), report=False, progress=False, gains=gains)
        import pandas as pd

        cells = cell_means(pd.read_csv(run_dir / "results.csv"), factors, metrics)
    if update:
        _write_baseline(spec, base_p, baseline, cells)
        return 0, []
    moved = compare(baseline, cells, factors)
    if moved:
        _print_moved(moved, factors, base_p)
        return 1, moved
    print(f"regress: all {len(baseline['cells'])} cells within the tolerance band of {base_p}")
    return 0, []


def _finished_campaign(folder: str) -> tuple:
    """(results table, the spec's factors, its campaign table) of a finished campaign's folder; InputError naming
    the file otherwise."""
    from wbc_jax.analysis.report.inputs import MANIFEST_LIMIT, read_results
    from wbc_jax.campaign.manifest import COMMAND

    man_p = Path(folder) / "manifest.json"
    try:
        man = json.loads(read_capped(man_p, MANIFEST_LIMIT, what="manifest"))
        spec = man["spec"] if man.get("command") == COMMAND else None
    except OSError as e:
        raise InputError(f"{man_p}: cannot read ({e.strerror or e}); name a finished campaign's folder "
                         "(wbc-jax campaign --out)") from None
    except (ValueError, KeyError, TypeError, AttributeError):
        spec = None
    if not isinstance(spec, dict) or not isinstance(spec.get("factors"), dict):
        raise InputError(f"{man_p}: not a campaign's manifest (no spec with factors); name a finished campaign's "
                         "folder (wbc-jax campaign --out)")
    _, df = read_results(str(Path(folder) / "results.csv"))
    factors = [str(f) for f in spec["factors"]]
    missing = [c for c in factors + ["success"] if c not in df.columns]
    if missing:
        raise InputError(f"{Path(folder) / 'results.csv'}: lacks the column(s) {', '.join(missing)}")
    return df, factors, spec.get("campaign", {})


def compare_campaigns(before: str, after: str) -> tuple[int, list]:
    """``regress --compare BEFORE AFTER``: two finished campaigns' per-cell metric means and success counts,
    ``after``'s against ``before``'s, with the regress bands of ``before``'s controller
    (:mod:`wbc_jax.campaign.controllers`; no rounding noise): e.g. a change's GPU campaign against the one before
    it (GPU runs are not bit-reproducible), or 27,000 runs against 270. Cells: every combination of the factors'
    levels in ``before``; success counts compare exactly, as rates where the campaigns' repetitions differ. Returns
    (0 every cell within / 1 some moved, moved rows) and prints the table of what moved.

    Raises:
        InputError: a folder that is not a finished campaign's, or campaigns of other factors or controllers.
    """
    (a, factors, camp), (b, factors_b, camp_b) = _finished_campaign(before), _finished_campaign(after)
    if factors != factors_b or controllers.info(camp) is not controllers.info(camp_b):
        raise InputError(f"{after}: factors {factors_b} ({camp_b.get('controller', 'transport')} controller) where "
                         f"{before} has {factors} ({camp.get('controller', 'transport')}); compare campaigns of one "
                         "design")
    bands = controllers.info(camp).regress
    metrics = tuple(k for k in bands if k in a.columns and k in b.columns)
    old, new = cell_means(a, factors, metrics), cell_means(b, factors, metrics)
    if {c["runs"] for c in old} != {c["runs"] for c in new}:  # other repetitions: success rates, not counts
        for c in old + new:
            c["n_success"] = c["n_success"] / c["runs"]
    baseline = dict(tolerance={k: dict(rel=bands[k][0], abs=bands[k][1]) for k in metrics}, cells=old)
    moved = compare(baseline, new, factors)
    if moved:
        _print_moved(moved, factors, Path(before))
        return 1, moved
    print(f"regress: all {len(baseline['cells'])} cells of {after} within the tolerance band of {before}")
    return 0, []


def _write_baseline(spec, base_p: Path, baseline: dict | None, cells: list[dict]) -> None:
    """baseline.json from this run's ``cells`` (tolerances kept), with the rounding probes' noise on the CPU."""
    bands = controllers.info(spec.campaign).regress
    tol = baseline["tolerance"] if baseline else {k: dict(rel=r, abs=a) for k, (r, a) in bands.items()}
    metrics = tuple(bands)
    probes = (_rounding_probes(base_p.parent / "spec.toml", list(spec.factors), metrics)
              if jax.default_backend() == "cpu" else [])
    cells = _with_noise(cells, probes, metrics)
    try:
        write_json_atomic(base_p, dict(spec_hash=spec.hash, factors=list(spec.factors), tolerance=tol, cells=cells,
                                       rounding_probes=["native"] + [f"xla_cpu_max_isa={i}" for i in
                                                                     ROUNDING_PROBE_ISAS[:len(probes)]],
                                       note="per-cell means over successful runs (mean over the rounding probes); "
                                            "a metric moved when |now - baseline| > rel |baseline| + abs + "
                                            f"{NOISE_FACTOR} x noise"))
    except OSError as e:
        raise WbcJaxError(f"{base_p}: cannot write it ({e.strerror or e})") from None
    print(f"baseline written to {base_p} ({len(cells)} cells)")


def _print_moved(moved: list[dict], factors, base_p: Path) -> None:
    """The table of what moved: cell, metric, baseline, now, band."""
    print(f"REGRESSION: {len(moved)} metric mean(s) left the tolerance band of {base_p}:")
    labels = [_label(r["cell"], factors) for r in moved]
    width = max(len(x) for x in [*labels, "cell"])
    print(f"{'cell':<{width}}  {'metric':<12} {'baseline':>12} {'now':>12}  band")
    for label, r in zip(labels, moved):
        fmt = lambda v: f"{v:12.6g}" if isinstance(v, float) else f"{v!s:>12}"  # noqa: E731
        print(f"{label:<{width}}  {r['metric']:<12} {fmt(r['baseline'])} {fmt(r['now'])}  {r['band']}")
