"""What MuJoCo's constraint-solver iteration cap (``opt.iterations``, ``campaign.solver_iterations``) does to the
campaign metrics (issue 21): one campaign spec run at several caps and physics backends, each in a fresh process,
then per setting the success count, the metric means, Warp's share of physics steps that ended at the cap
(``solver_cap_fraction``) and the cell means that leave the regress tolerance band
(``wbc_jax.campaign.regress.DEFAULT_TOL``: rel |ref| + abs) of the reference setting (the first cap, same backend)
and of the other backend at the same cap. Usage::

    PYTHONPATH=$PWD python tools/solver_iters.py --spec sweeps/quick.toml --iterations 4,20,100 \
        --backends jax,warp [--reps 1] [--max-seconds 3] [--out DIR]

``--reps`` and ``--max-seconds`` shrink the spec for a CPU (0: keep the spec's). Writes DIR/<backend>_<cap>/
(each campaign's results.csv and manifest.json) and DIR/summary.json; prints the tables as Markdown.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np
import pandas as pd

METRICS = ("R", "T", "S", "max_slip_mm")


def spec_variant(text: str, iters: int, backend: str, reps: int, max_seconds: float) -> str:
    """The spec's TOML with ``campaign.solver_iterations`` and ``campaign.backend`` set (and reps / max_seconds
    when > 0): keys of ``[campaign]`` replaced or added at its top."""
    sets = dict(solver_iterations=str(iters), backend=f'"{backend}"')
    if reps > 0:
        sets["reps"] = str(reps)
    if max_seconds > 0:
        sets["max_seconds"] = repr(float(max_seconds))
    head, sep, rest = text.partition("[campaign]\n")
    if not sep:
        raise SystemExit("the spec has no [campaign] table")
    body, nxt, tail = rest.partition("\n[")
    lines = [ln for ln in body.splitlines() if not re.match(rf"\s*({'|'.join(sets)})\s*=", ln)]
    body = "\n".join([f"{k} = {v}" for k, v in sets.items()] + lines)
    return head + sep + body + nxt + tail


def moved(ref: pd.DataFrame, new: pd.DataFrame) -> list[str]:
    """Cell means of ``new`` outside the regress band around ``ref``'s, and success count changes
    (``wbc_jax.campaign.regress.compare`` with ``ref`` as the baseline and DEFAULT_TOL, no rounding noise)."""
    from wbc_jax.campaign.regress import DEFAULT_TOL, cell_means, compare

    base = dict(tolerance={k: dict(rel=rel, abs=ab) for k, (rel, ab) in DEFAULT_TOL.items()}, cells=cell_means(ref))
    return [f"{r['cell']} {r['metric']} {r['baseline']:.4g} -> {r['now']:.4g}" if r["metric"] in METRICS
            else f"{r['cell']} {r['metric']} {r['baseline']} -> {r['now']}" for r in compare(base, cell_means(new))]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default="sweeps/quick.toml")
    ap.add_argument("--iterations", default="4,20,100", help="caps, comma-separated; the first is the reference")
    ap.add_argument("--backends", default="jax", help="jax, warp or jax,warp")
    ap.add_argument("--reps", type=int, default=0, help="repetitions per cell (0: the spec's)")
    ap.add_argument("--max-seconds", type=float, default=0.0, help="simulated seconds per run (0: the spec's)")
    ap.add_argument("--out", default="out/solver_iters")
    args = ap.parse_args(argv)

    from wbc_jax.campaign.runner import run_in_fresh_process

    caps = [int(x) for x in args.iterations.split(",")]
    backends = args.backends.split(",")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    text = Path(args.spec).read_text()
    runs, rows = {}, []
    for be in backends:
        for it in caps:
            name = f"{be}_{it}"
            spec_p = out / f"{name}.toml"
            spec_p.write_text(spec_variant(text, it, be, args.reps, args.max_seconds))
            t0 = time.perf_counter()
            run_in_fresh_process(spec_p, out / name)
            wall = time.perf_counter() - t0
            df = pd.read_csv(out / name / "results.csv")
            runs[name] = df
            ok = df[df.success.astype(bool)]
            rows.append(dict(backend=be, cap=it, wall_s=round(wall, 1), success=f"{len(ok)}/{len(df)}",
                             **{k: float(ok[k].mean()) for k in METRICS},
                             solver_cap_fraction=float(df.solver_cap_fraction.mean()),
                             moved_vs_first_cap=moved(runs[f"{be}_{caps[0]}"], df) if it != caps[0] else []))
            print(f"{name}: {rows[-1]['success']} in {wall:.0f} s", flush=True)
    cross = {}
    if len(backends) == 2:
        for it in caps:
            cross[str(it)] = moved(runs[f"{backends[0]}_{it}"], runs[f"{backends[1]}_{it}"])
    (out / "summary.json").write_text(json.dumps(dict(spec=args.spec, reps=args.reps, max_seconds=args.max_seconds,
                                                      rows=rows, cross_backend=cross), indent=1))
    print("| backend | cap | success | R | T [mm] | S | max slip [mm] | steps at the cap | cell means moved vs "
          f"cap {caps[0]} | wall [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        cap_share = "n/a" if np.isnan(r["solver_cap_fraction"]) else f"{100 * r['solver_cap_fraction']:.1f} %"
        print(f"| {r['backend']} | {r['cap']} | {r['success']} | {r['R']:.4f} | {1e3 * r['T']:.3f} | {r['S']:.4f} | "
              f"{r['max_slip_mm']:.3f} | {cap_share} | {len(r['moved_vs_first_cap'])} | {r['wall_s']} |")
    for it, m in cross.items():
        print(f"cap {it}: {len(m)} cell means of {backends[1]} outside {backends[0]}'s bands: {m}")
    for r in rows:
        if r["moved_vs_first_cap"]:
            print(f"{r['backend']} cap {r['cap']}: {r['moved_vs_first_cap']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
