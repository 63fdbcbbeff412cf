"""``docs/specs.md``: every spec key with its type, default, unit and range, generated from the validators' tables.

The key tables that :func:`wbc_jax.campaign.spec.parse_spec` (campaign specs, ``sweeps/*.toml``) and
:func:`wbc_jax.studies.tune_spec.parse_tune_spec` (tuning specs) validate against are the single source: type,
default, range and unit come from there; this module adds one line of meaning per key and fails if a key has
none, so a new key cannot reach the docs without a description. ``tests/test_spec_docs.py`` checks that the
committed ``docs/specs.md`` equals :func:`render`.

Usage::

    python -m wbc_jax.studies.spec_docs            # rewrite docs/specs.md
    python -m wbc_jax.studies.spec_docs --check    # exit 1 if docs/specs.md is out of date
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from wbc_jax.campaign import factors, spec
from wbc_jax.studies import tune_spec as tune

DOCS = Path(__file__).resolve().parents[2] / "docs" / "specs.md"

# One line of meaning per key; type, default, range and unit come from the validators' tables.
CAMPAIGN_MEANING = {
    "name": "free text, copied to the manifest",
    "reps": "repetitions per cell",
    "seed": "base seed; run i gets `SeedSequence([seed, i])`",
    "scene": "`transport` (the obstacle course) or `flat`",
    "distance": "object travel along the path",
    "speed": "cruise speed of the rest-to-rest speed profile",
    "cone": "MuJoCo's friction cone of every contact (`opt.cone`): `scene` keeps the scene file's (pyramidal)",
    "impratio": "MuJoCo's frictional-to-normal impedance ratio (`opt.impratio`); 0 keeps the scene's (10)",
    "obj_accel": "peak acceleration of the object's start and stop: speed ramps of 2 speed / obj_accel; 0 keeps the "
                 "planner's 1 s ramps",
    "extra_seconds": "simulated time after the planned path ends",
    "max_seconds": "cap on the simulated time (a capped run stops mid-path)",
    "qp_iters": "ADMM iterations per control step (static: one compile per value)",
    "qp_first_test": "`QPSettings.warm_first_test` of the controller's QP: >= 0, a control step's first convergence "
                     "check comes after the previous step's ADMM iterations minus this (in blocks of 4, at most 12 "
                     "past `qp_iters`): fewer checks where each step needs about as many iterations as the last "
                     "(velocity noise; docs/performance.md); -1 checks after `qp_iters`",
    "qp_reuse_factors": "`QPSettings.reuse_factors` of the transport controller's QP: 1, a control step whose "
                        "predecessor factored reuses its factors, scaling and rho where no row changed kind (the "
                        "fused GPU kernels, with Warp physics only: with JAX physics the step gains nothing; the XLA "
                        "path, e.g. on a CPU, factors every step)",
    "qp_max_iters": "`QPSettings.max_iters` of the controller's QP: after `qp_iters`, blocks of 4 more ADMM "
                    "iterations while unconverged, up to this many in a control step (a solve still unconverged "
                    "then is applied and flagged `FLAG_MAX_ITER`); 0 keeps the controller's (200); at least "
                    "`qp_iters`",
    "qp_launch_order": "`QPSettings.launch_order` of the controller's QP on the fused GPU kernels: `\"batch\"` "
                       "(the runs' order) or `\"predicted\"` (the iterations kernel's programs started longest-"
                       "predicted first, so that a long solve does not start last; the same arithmetic per problem; "
                       "docs/performance.md, the launch order); the XLA path ignores it",
    "qp_alpha": "`QPSettings.alpha` of the controller's QP (ADMM over-relaxation, in (0, 2)); 0 keeps the "
                "controller's (1.6)",
    "qp_rho": "`QPSettings.rho` of the transport controller's QP (its ADMM step size, which it does not adapt: the "
              "first control step starts from it and each step passes it on); 0 keeps the controller's (3)",
    "control_substeps": "physics steps per control step, zero-order hold; the metrics still sample every "
                        "physics step",
    "chunk_seconds": "the most simulated seconds per jit call and checkpoint: the fewest such chunks that cover the "
                     "horizon, made equal and as short as cover it",
    "solver_iterations": "MuJoCo constraint-solver iterations per physics step (`opt.iterations`); 0 keeps the "
                         "scene's (4 in the shipped scenes)",
    "backend": "MJX physics implementation: \"warp\" (MuJoCo Warp kernels, NVIDIA GPUs; needs the cuda extra) or "
               "\"jax\" (any device); \"auto\" is Warp on a CUDA GPU with warp-lang installed, else JAX (the same "
               "statistics on both: docs/performance.md); `--backend` overrides",
    "m": "object mass of every run when `m` is not a factor",
    "mu": "tray friction of every run when `mu` is not a factor",
    "d": "object side of every run when `d` is not a factor",
    "ground_mu": "foot/ground friction of every run when `ground_mu` is not a factor (0: the scene's, 1.0 in the "
                 "shipped scenes)",
    "variant": "controller variant of every run when `variant` is not a factor (docs/method.md, \"Controller "
               "variants\")",
    "terrain": "what the planner knows of the ground: `known` (footholds on the blocks' tops, off their edges, "
               "from the scene file) or `blind` (footholds at the floor's height; the touchdown rules handle the "
               "blocks; the object's path over the wall is planned in both)",
    "com_plan": "the CoM's horizontal reference: `spline` (the object's path + the start offset) or `zmp` (replanned "
                "at the start of every footstep, one cubic per support phase, so that the cart-table ZMP stays on the "
                "stance pair's line in two-foot support; the default, as in the paper: docs/method.md, \"ZMP-based "
                "CoM replanning\")",
    "sensing": "what the controller reads on the Warp backend: `exact` (Warp's position and velocity stages give it "
               "the current state: two Warp calls, one forward pass per control step) or `delayed` (it reads the "
               "fields Warp's `step` left, which belong to the state one physics step old: one call per step; needs "
               "`backend = \"warp\"` and `control_substeps = 1`); `auto`: `delayed` where it applies, else `exact` "
               "(the same statistics, less wall time: docs/performance.md)",
    "controller": "the controller every run uses: `transport` (the object-transport WBC on the object-path plan; "
                  "metrics R, T, S) or `centroidal` (the centroidal-momentum WBC on a capture-point trot; metrics "
                  "speed, CP error, attitude, torque, foot slip: see \"The centroidal controller\" below)",
    "mass_error": "centroidal: the controller's model mass error of every run when `mass_error` is not a factor",
    "walk_seconds": "centroidal: walking time after 0.5 s of standing (`round(walk_seconds / step_time)` "
                    "half-cycles)",
    "step_time": "centroidal: the trot's half-cycle",
    "four_foot": "centroidal: the four-foot support at the start of each half-cycle",
}
FACTOR_MEANING = {
    "m": "object mass",
    "mu": "tray (object/tray) friction",
    "d": "object side (the robot's tray narrows it further)",
    "ground_mu": "foot/ground friction: the physics' foot pairs and the controller's ground cone",
    "speed": "cruise speed of the plan (the push start and metric window follow each run's own plan)",
    "obj_accel": "peak acceleration of the object's reference at start and stop (the speed ramps last 2 speed / "
                 "obj_accel)",
    "push_N": "one trunk push of this magnitude per run, direction `perturbations.push_dir_deg`, duration "
              "`push_duration_s`, start drawn in `push_window` (0: no push); `perturbations.push_max_N` must stay 0",
    "qvel_noise_std": "controller-view velocity noise std; `perturbations.qvel_noise_std` must stay 0",
    "observer": "momentum observer on (true / 1) or off (false / 0); combined with `variant` (off if either "
                "turns it off)",
    "variant": "controller variant: `full`, `no_tray_cone`, `no_observer`, `no_posture` (docs/method.md)",
    "mass_error": "centroidal: the controller's model mass error, a fraction (-0.2: every body mass and inertia of "
                  "its model 20 % too light; the centroidal paper's Fig. 12)",
    "gain.<leaf>": "multiplier of that `TransportGains` leaf of the campaign's gains (defaults or `--gains`), "
                   "e.g. `gain.kp_obj`",
    "plugin.<field>": "a float (any finite value) or bool field of the `[plugin]` class, per run (the class keeps "
                      "it in its state: `with_params`); e.g. `\"plugin.time_constant\"` (quoted in TOML)",
}
PERTURB_MEANING = {
    "object_xy_mm": "object placement on the tray: uniform in +-value along x and y",
    "object_yaw_deg": "object yaw on the tray: uniform in +-value",
    "base_speed_std": "initial horizontal velocity of robot and object: Gaussian std per axis",
    "push_max_N": "trunk push magnitude: uniform in [0, value], random horizontal direction",
    "push_duration_s": "push duration",
    "push_window": "push start: uniform in this fraction of the planned duration",
    "qvel_noise_std": "white Gaussian noise on every generalized velocity the controller reads, every control "
                      "step (the physics stays exact)",
    "push_dir_deg": "direction of the `push_N` factor's pushes, counterclockwise from world +x (only with that "
                    "factor)",
}
ANALYSIS_MEANING = {
    "order": "highest interaction order of the report's ANOVA model (2: main effects + two-way interactions)",
    "alpha": "significance level of the report's tests",
}
TUNE_MEANING = {
    "name": "free text",
    "campaign": "campaign spec (scene, course, timing, factor levels, perturbations, ADMM iterations)",
    "method": "search method: `grid`, `random`, `cem` (cross-entropy method) or `halving` (successive halving over "
              "candidates x simulated time)",
    "candidates": "candidates per round (cem: at least 2)",
    "rounds": "rounds (grid: computed from the grid)",
    "seed": "search seed",
    "reps": "repetitions per cell (replaces the campaign's)",
    "max_seconds": "cap on simulated time per run (0: the campaign's)",
    "qp_iters": "ADMM iterations per control step (0: the campaign's)",
    "batch": "runs per rollout call (0: all of a round's runs on an accelerator, 1 on a CPU, where jaxlib 0.10's "
             "batched LAPACK kernels can deadlock the thread pool)",
}
HALVING_MEANING = {
    "eta": "keep the best 1/eta of the candidates after each rung",
    "rungs": "rungs per bracket; rung r simulates full / eta^(rungs-1-r) of the horizon, continuing the survivors",
}
CONFIRM_MEANING = {
    "campaign": "campaign the default gains and the best candidates are replayed on after the search",
    "top": "candidates confirmed besides the defaults",
    "reps": "repetitions per cell of the confirmation (0: the campaign's)",
    "alpha": "significance level of the paired tests (Wilcoxon signed-rank, exact McNemar for success)",
}
OBJECTIVE_MEANING = {
    "w_R": "weight of mean R / atan(mu)^2",
    "w_S": "weight of mean S / s_ref",
    "w_T": "weight of -mean T [mm]",
    "s_ref": "scale of S",
    "min_success": "constraint: success rate at least this",
    "t_max_mm": "constraint: mean T at most this (0: no bound)",
}
CEM_MEANING = {
    "elite_frac": "elite share of each round's candidates",
    "init_std": "initial std of ln(multiplier)",
    "min_std": "floor of the std",
    "smoothing": "weight of the new elite's mean and std",
}
GRID_MEANING = {"points": "log-spaced multipliers per tuned leaf (grid size at most 1e6)"}


def _number(x) -> str:
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e15:
        return repr(x)
    return f"{x:g}" if isinstance(x, float) else str(x)


def _type(typ) -> str:
    return {str: "string", int: "integer", float: "number", list: "[a, b]"}[typ]


def _range(typ, lo, hi, lo_open, unit) -> str:
    if typ is str:
        return ""
    if typ is list:
        return unit
    return f"{_number(lo)} < value <= {_number(hi)}" if lo_open else f"{_number(lo)} .. {_number(hi)}"


def _unit(typ, unit) -> str:
    """The table's unit if it is one ("[m]", "[s], 0 = no cap" -> "m"), else empty (its text is then a meaning)."""
    if typ is list or not unit.startswith("["):
        return ""
    return unit[1:unit.index("]")]


def key_table(name: str, schema: dict, meaning: dict) -> list[str]:
    """Markdown rows of one validator table (``key: (type, default, lo, hi, lo_open, unit)``).

    Raises:
        KeyError: a key of ``schema`` has no entry in ``meaning``.
    """
    missing = sorted(set(schema) - set(meaning))
    if missing:
        raise KeyError(f"[{name}] {missing[0]}: no description in wbc_jax.studies.spec_docs")
    rows = ["| key | type | default | unit | range | meaning |", "|---|---|---|---|---|---|"]
    for key, (typ, default, lo, hi, lo_open, unit) in schema.items():
        d = f'"{default}"' if typ is str else (str(default) if typ is list else _number(default))
        rows.append(f"| `{name}.{key}` | {_type(typ)} | {d} | {_unit(typ, unit)} | "
                    f"{_range(typ, lo, hi, lo_open, unit)} | {meaning[key]} |")
    return rows


def factor_table() -> list[str]:
    """Markdown rows of the ``[factors]`` table (each a list of at least 2 distinct levels), in design order."""
    defs = {**spec.FACTORS, f"{factors.GAIN_PREFIX}<leaf>": factors.GAIN,
            f"{factors.PLUGIN_PREFIX}<field>": factors.plugin_factor(0.0)}
    missing = sorted(set(defs) - set(FACTOR_MEANING))
    if missing:
        raise KeyError(f"[factors] {missing[0]}: no description in wbc_jax.studies.spec_docs")
    rows = ["| key | levels | unit | range of each level | when not a factor | meaning |", "|---|---|---|---|---|---|"]
    for key, fd in defs.items():
        kind = {"number": "numbers", "bool": "booleans (true/false or 1/0)", "choice": "strings"}[fd.kind]
        rng = (_range(float, fd.lo, fd.hi, fd.lo_open, fd.unit) if fd.kind == "number" else
               ", ".join(f"`{c}`" for c in fd.choices) if fd.kind == "choice" else "")
        fixed = f"`{fd.fixed}`" if "." in fd.fixed and " " not in fd.fixed else fd.fixed
        rows.append(f"| `factors.{key}` | list of >= 2 distinct {kind} | {_unit(float, fd.unit)} | {rng} | {fixed} "
                    f"| {FACTOR_MEANING[key]} |")
    return rows


def _header() -> list[str]:
    """The title, the generated-file note and what every spec shares."""
    return [
        "# Spec reference",
        "",
        "<!-- Generated by `python -m wbc_jax.studies.spec_docs` from the validators' key tables "
        "(wbc_jax/campaign/spec.py, wbc_jax/studies/tune_spec.py); do not edit by hand. -->",
        "",
        "Specs are TOML files read with the standard library's `tomllib`. Every key is optional except "
        "`[factors]`; a key left out takes its default. An unknown table or key, a wrong type or an out-of-range "
        "value stops the command before anything runs: one line `wbc-jax CMD: error: FILE: KEY: ...` naming the "
        "expected range, exit code 2, nothing written.",
        "",
    ]


def _campaign_section() -> list[str]:
    """Campaign specs: ``[campaign]``, ``[factors]``, ``[perturbations]``, ``[analysis]``."""
    return [
        "## Campaign specs (`wbc-jax campaign --spec`, `sweeps/*.toml`)",
        "",
        "Shipped: `sweeps/paper_campaign.toml` (the paper's 3 x 3 x 3 levels x 10 reps = 270 runs on the "
        "obstacle course) and `sweeps/quick.toml` (the same levels x 2 reps = 54 runs, 0.15 m on flat ground; "
        "the default on a CPU-only machine).",
        "",
        "### `[campaign]`: what is simulated",
        "",
        *key_table("campaign", spec.CAMPAIGN, CAMPAIGN_MEANING),
        "",
        "### `[factors]`: levels of the factorial design",
        "",
        f"1 to {factors.MAX_FACTORS} of these factors, each a list of at least 2 distinct levels. The design is the "
        "product of their levels in the order of this table (whatever the order in the file), then the "
        "repetitions; a factor not listed takes the value of the key in \"when not a factor\". A run's results "
        "row has one column per factor (`m`, `mu`, `d` always). The shipped specs beyond the paper: "
        "`sweeps/ablation.toml` (variant x mu x d) and `sweeps/robustness.toml` (push_N x speed x m).",
        "",
        *factor_table(),
        "",
        "### `[perturbations]`: per run, drawn from the run's own seed",
        "",
        "All zero makes the repetitions identical (the campaign and the report warn). Run i (cells in the design "
        "order of the product of the levels, then reps) has seed `SeedSequence([seed, i]).generate_state(1)[0]`; "
        "its perturbations are drawn from `numpy.random.default_rng(run_seed)` in the order dx, dy, yaw, vx, vy, "
        "push magnitude, push angle, push start.",
        "",
        *key_table("perturbations", spec.PERTURBATIONS, PERTURB_MEANING),
        "",
        "### The centroidal controller (`controller = \"centroidal\"`)",
        "",
        "Every run trots straight along the trunk's forward axis (world -y on the shipped scenes) at its commanded "
        "speed (`campaign.speed` or the `speed` factor; stride = speed x `step_time`) with the cube on the tray, "
        "whose mass the controller assumes as its payload. Its factors: `m`, `mu`, `d`, `ground_mu`, `speed`, "
        "`push_N`, `qvel_noise_std`, `mass_error`; `distance`, `variant`, `terrain` and `com_plan` are the "
        "transport's and must stay at their defaults (and the centroidal keys at theirs for the transport). "
        "`qp_iters` is the centroidal QP's ADMM iterations (the shipped trot specs: 40). results.csv holds per "
        "run `speed_mps`, `cp_err_x_rms_mm`, `cp_err_y_rms_mm`, `cp_err_x_max_mm`, `roll_amp_deg`, "
        "`pitch_amp_deg`, `yaw_amp_deg`, `max_tau_ratio`, `foot_slip_mm`, `distance_m`, `walked` and the shared "
        "flags (wbc_jax/rollout/controllers/trot_metrics.py); the report's ANOVA covers speed, the CP errors and "
        "roll and pitch. Shipped: `sweeps/trot_paper.toml` (mass error x speed, the paper's Fig. 12, 10 reps), "
        "`sweeps/trot_robustness.toml` (mass error x ground friction x lateral push) and `sweeps/trot_quick.toml` "
        "(2 runs for a CPU).",
        "",
        "### `[analysis]`: the campaign report's statistics (not part of the spec hash)",
        "",
        "The report fits, per metric, an ANOVA with every interaction up to `order`; it also tabulates the success "
        "rate per factor level and per pair of factors, and compares each `variant` (or `observer` level) with the "
        "reference controller (Welch t and Mann-Whitney U on max slip and R, Fisher's exact test on success).",
        "",
        *key_table("analysis", spec.ANALYSIS, ANALYSIS_MEANING),
        "",
        "### `[plugin]`: a controller from outside the package",
        "",
        "`class = \"module:Class\"` names a subclass of the spec's controller (`TransportController` or "
        "`CentroidalController`) in a module importable from the current folder (or `PYTHONPATH`); every other key "
        "sets one of the class's own fields (bool, int, float or str, the class's default otherwise); a float or bool "
        "field may instead be a factor, `\"plugin.<field>\"` in `[factors]`. The campaign, "
        "its results columns, report and regress bands are the named controller's; the module file's sha256 is "
        "part of the spec hash. The rules a plug-in follows: `wbc_jax/rollout/controllers/plugin.py`; an example: "
        "`examples/torque_lag.py` (`sweeps/torque_lag.toml`). `wbc-jax tune` searches the built-in controller only.",
        "",
    ]


def _tuning_section() -> list[str]:
    """Tuning specs: every table of :mod:`wbc_jax.studies.tune_spec`."""
    return [
        "## Tuning specs (`wbc-jax tune --spec`; `sweeps/gain_tuning_course.toml` with an accelerator, "
        "`sweeps/gain_tuning_cpu.toml` on a CPU, `sweeps/gain_tuning.toml`)",
        "",
        "### `[tune]`",
        "",
        *key_table("tune", tune._TUNE, TUNE_MEANING),
        "| `tune.cells` | `\"all\"` or list of [m, mu, d] | \"all\" |  | levels of the campaign, no cell twice "
        "| the factor cells every candidate runs |",
        "",
        "### `[start]` and `[leaves]`",
        "",
        "`[start]`: the start point as scales of the default gains, 0 < scale <= 1e4: `kp` (every `kp_*` leaf), "
        "`kd` (every `kd_*` leaf) or a leaf name (overrides its group). Leaves not tuned keep their start value.",
        "",
        "`[leaves]` (at least one): `leaf = [lo, hi]`, the tuned leaf's multiplier range of its default value, "
        "0 < lo < hi <= 1e4 (a vector leaf is scaled as a whole). Leaves: "
        + ", ".join(f"`{leaf}`" for leaf in tune.LEAVES) + ".",
        "",
        "### `[objective]`: J = w_R mean(R / atan(mu)^2) + w_S mean(S / s_ref) - w_T mean(T [mm])",
        "",
        *key_table("objective", tune._OBJECTIVE, OBJECTIVE_MEANING),
        "",
        "### `[cem]` and `[grid]`",
        "",
        *key_table("cem", tune._CEM, CEM_MEANING),
        "",
        *key_table("grid", tune._GRID, GRID_MEANING),
        "",
        "### `[halving]` and `[confirm]`",
        "",
        *key_table("halving", tune._HALVING, HALVING_MEANING),
        "",
        *key_table("confirm", tune._CONFIRM, CONFIRM_MEANING),
        "",
    ]


def _gains_section() -> list[str]:
    """Gains files (``--gains``, ``best_gains.toml``)."""
    return [
        "## Gains files (`wbc-jax campaign --gains FILE`, `best_gains.toml` of `wbc-jax tune`)",
        "",
        "`[gains]`: any subset of the leaves above, the rest default; a vector leaf takes a list of its length or "
        "one number. Every value finite, 0 <= value <= 1e9 (`tau_margin`: 0 < value <= 1). `[info]`: free-form, "
        "not read. See `wbc_jax/campaign/gains.py`.",
        "",
    ]


def render() -> str:
    """The text of ``docs/specs.md``."""
    return "\n".join([*_header(), *_campaign_section(), *_tuning_section(), *_gains_section()])


def main(argv: list[str] | None = None) -> int:
    """Write ``docs/specs.md`` (or with ``--check`` only compare it); returns the exit code."""
    ap = argparse.ArgumentParser(prog="python -m wbc_jax.studies.spec_docs", description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the file differs from the generated text")
    ap.add_argument("--out", type=Path, default=DOCS, help=f"output path (default {DOCS})")
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        same = args.out.exists() and args.out.read_text() == text
        print(f"{args.out}: {'up to date' if same else 'out of date (run python -m wbc_jax.studies.spec_docs)'}")
        return 0 if same else 1
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
