"""Run the CPU-sized campaign (54 runs on flat ground), then print the mean of R, T, S per friction level.

    python examples/quick_campaign.py [OUT_DIR]

On a CPU most of the time goes to compiling the rollout; the persistent compilation cache keeps it for the
next run.
"""

import sys

import wbc_jax

out = sys.argv[1] if len(sys.argv) > 1 else "out/quick_campaign"
manifest = wbc_jax.run_campaign("sweeps/quick.toml", out)
df = wbc_jax.load_results(out)
ok = df[df["success"]]
print(f"{len(ok)}/{len(df)} runs succeeded on {manifest['device']['kind']}")
print(ok.groupby("mu")[["R", "T", "S"]].mean().to_string())
print(f"ANOVA report: {out}/report/report.md")
