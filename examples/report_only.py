"""The ANOVA report of an existing results table, without JAX: print the significant terms per metric.

python examples/report_only.py RESULTS.csv [OUT_DIR]
"""

import sys

import wbc_jax

results = sys.argv[1]
out = sys.argv[2] if len(sys.argv) > 2 else "out/report"
summary = wbc_jax.report(results, out)
for metric, res in summary["metrics"].items():
    print(f"{metric}: significant at alpha {summary['alpha']}: {', '.join(res['significant']) or 'none'}")
print(f"report: {out}/report.md")
