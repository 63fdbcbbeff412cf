"""``wbc-jax regress``: CI regression of per-cell metric means against a stored baseline.

A baseline folder holds ``spec.toml`` (the spec rerun) and ``baseline.json`` (per-cell means over successful runs,
success counts, tolerance bands and, when stored on a CPU, each cell's rounding noise from reruns with XLA's CPU
code generation capped at older instruction sets).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import jax
import numpy as np

from wbc_jax.campaign.runner import run_campaign, run_in_fresh_process
from wbc_jax.campaign.spec import load_spec
from wbc_jax.errors import InputError, SpecError, WbcJaxError
from wbc_jax.io_utils import read_capped, write_json_atomic

REGRESS_METRICS = ("R", "T", "S", "max_slip_mm")
DEFAULT_TOL = {"R": (0.02, 1e-3), "T": (0.05, 2e-5), "S": (0.05, 1e-3), "max_slip_mm": (0.10, 0.05)}  # (rel, abs)
# Rounding probes of `regress --update` on the CPU: the baseline spec rerun with XLA's CPU code generation capped at
# these instruction sets. Another machine's CPU (vector width, FMA contraction) rounds float32 differently, which in
# short runs with sliding contacts moves some cell means by more than the tolerance; the probes' spread is stored per
# cell and metric and widens that cell's band.
ROUNDING_PROBE_ISAS = ("SSE4_2", "AVX", "AVX2")
NOISE_FACTOR = 2.0  # band = rel |baseline| + abs + NOISE_FACTOR x the probes' largest deviation from their mean


def _rounding_probes(spec_p: Path) -> list[list[dict]]:
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
            out.append(cell_means(pd.read_csv(run / "results.csv")))
    return out


def _with_noise(cells: list[dict], probes: list[list[dict]]) -> list[dict]:
    """``cells`` with each metric replaced by its mean over this run and the probes, and ``noise``: per metric the
    largest |run - mean| (None where a metric is undefined in some run). Success counts stay this run's."""
    runs = [cells] + probes
    out = []
    for i, c in enumerate(cells):
        c = dict(c)
        noise = {}
        for k in REGRESS_METRICS:
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



def cell_means(df) -> list[dict]:
    """Per-cell means of the regression metrics over successful runs, and success counts."""
    rows = []
    for (m, mu, d), g in df.groupby(["m", "mu", "d"]):
        ok = g[g.success.astype(bool)]
        rows.append(dict(m=float(m), mu=float(mu), d=float(d), runs=int(len(g)), n_success=int(len(ok)),
                         **{k: (float(ok[k].mean()) if len(ok) else None) for k in REGRESS_METRICS}))
    return rows


def compare(baseline: dict, cells: list[dict]) -> list[dict]:
    """Rows that moved: a metric mean outside |new - old| <= rel |old| + abs + NOISE_FACTOR x noise (the cell's
    rounding noise, ``old["noise"][metric]``, 0 where the baseline has none), a success count change or a
    missing cell."""
    tol = baseline["tolerance"]
    new = {(c["m"], c["mu"], c["d"]): c for c in cells}
    moved = []
    for old in baseline["cells"]:
        noise = old.get("noise") or {}
        key = (old["m"], old["mu"], old["d"])
        c = new.get(key)
        if c is None:
            moved.append(dict(cell=key, metric="(cell)", baseline="present", now="missing", band=""))
            continue
        if c["n_success"] != old["n_success"]:
            moved.append(dict(cell=key, metric="n_success", baseline=old["n_success"], now=c["n_success"],
                              band="exact"))
        for k in REGRESS_METRICS:
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


def load_baseline(base_p: Path) -> dict:
    """Read and check ``baseline.json``: a ``tolerance`` (rel, abs >= 0 per metric of REGRESS_METRICS), a list of
    ``cells`` (m, mu, d, n_success and each metric a number or null) and the ``spec_hash``.

    Raises:
        WbcJaxError: one line naming the file and the first problem.
    """
    def bad(what):
        return WbcJaxError(f"{base_p}: not a valid baseline file ({what}); recreate it with wbc-jax regress "
                           f"--baseline {base_p.parent} --update")

    def num(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)

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
    for k in REGRESS_METRICS:
        t = b["tolerance"].get(k)
        if not (isinstance(t, dict) and num(t.get("rel")) and num(t.get("abs")) and t["rel"] >= 0 and t["abs"] >= 0):
            raise bad(f"tolerance.{k}: expected rel and abs numbers >= 0")
    for i, c in enumerate(b["cells"]):
        if not (isinstance(c, dict) and all(num(c.get(k)) for k in ("m", "mu", "d", "n_success"))
                and all(c.get(k) is None or num(c.get(k)) for k in REGRESS_METRICS)
                and (c.get("noise") is None or isinstance(c["noise"], dict))):
            raise bad(f"cells[{i}]: expected m, mu, d, n_success numbers and metric numbers or null")
    return b


def run_regress(baseline_dir: str, update: bool = False, gains=None, out: str | None = None) -> tuple[int, list]:
    """Rerun the baseline's stored spec (``DIR/spec.toml``) and compare per-cell metric means with
    ``DIR/baseline.json`` (means + tolerance band). Returns (exit code: 0 pass / 1 moved, moved rows).
    ``update``: rewrite baseline.json (tolerances kept) and return 0; on the CPU the spec also runs once per
    :data:`ROUNDING_PROBE_ISAS` entry in a subprocess (:func:`_rounding_probes`): the stored means are the mean
    over all runs and each cell's ``noise`` the largest deviation from it."""
    bdir = Path(baseline_dir)
    spec_p = bdir / "spec.toml"
    if not spec_p.exists():
        raise SpecError(f"{bdir}: no spec.toml in the baseline directory")
    base_p = bdir / "baseline.json"
    baseline = None
    if base_p.exists():  # checked before anything is rerun
        baseline = load_baseline(base_p)
    elif not update:
        raise WbcJaxError(f"{base_p}: missing; create it with wbc-jax regress --baseline {bdir} --update")
    spec = load_spec(spec_p)
    if baseline is not None and not update and baseline["spec_hash"] != spec.hash:
        raise WbcJaxError(f"{spec_p}: spec changed since the baseline was stored; rerun with --update")
    with tempfile.TemporaryDirectory() as td:
        run_dir = Path(out) if out else Path(td) / "run"
        run_campaign(str(spec_p), str(run_dir), report=False, progress=False, gains=gains)
        import pandas as pd

        cells = cell_means(pd.read_csv(run_dir / "results.csv"))
    if update:
        tol = baseline["tolerance"] if baseline else {k: dict(rel=r, abs=a) for k, (r, a) in DEFAULT_TOL.items()}
        probes = _rounding_probes(spec_p) if jax.default_backend() == "cpu" else []
        cells = _with_noise(cells, probes)
        write_json_atomic(base_p, dict(spec_hash=spec.hash, tolerance=tol, cells=cells,
                                       rounding_probes=["native"] + [f"xla_cpu_max_isa={i}" for i in
                                                                     ROUNDING_PROBE_ISAS[:len(probes)]],
                                       note="per-cell means over successful runs (mean over the rounding probes); "
                                            "a metric moved when |now - baseline| > rel |baseline| + abs + "
                                            f"{NOISE_FACTOR} x noise"))
        print(f"baseline written to {base_p} ({len(cells)} cells)")
        return 0, []
    moved = compare(baseline, cells)
    if moved:
        print(f"REGRESSION: {len(moved)} metric mean(s) left the tolerance band of {base_p}:")
        print(f"{'m':>5} {'mu':>5} {'d':>5}  {'metric':<12} {'baseline':>12} {'now':>12}  band")
        for r in moved:
            fmt = lambda v: f"{v:12.6g}" if isinstance(v, float) else f"{v!s:>12}"  # noqa: E731
            print(f"{r['cell'][0]:5.2f} {r['cell'][1]:5.2f} {r['cell'][2]:5.2f}  {r['metric']:<12} "
                  f"{fmt(r['baseline'])} {fmt(r['now'])}  {r['band']}")
        return 1, moved
    print(f"regress: all {len(cells)} cells within the tolerance band of {base_p}")
    return 0, []
