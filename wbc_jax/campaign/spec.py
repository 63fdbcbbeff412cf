"""Campaign specs (``sweeps/*.toml``): loading with stdlib ``tomllib`` and validation.

A spec has up to five tables (every key optional except ``factors``; an example with the paper specs' values below;
every key's default, unit and range: ``docs/specs.md``, generated from the key tables ``CAMPAIGN``, ``FACTORS``,
``PERTURBATIONS`` and ``ANALYSIS`` by :mod:`wbc_jax.studies.spec_docs`)::

    [campaign]                 # what is simulated
    name = "paper"             # free text
    reps = 10                  # repetitions per cell, 1..1000
    seed = 2024                # base seed, 0 <= seed < 2**32
    scene = "transport"        # "transport" (obstacle course) or "flat"
    distance = 3.4             # object travel [m], 0.05..10
    speed = 0.13               # cruise speed [m/s], 0.01..0.5
    obj_accel = 0.0            # peak acceleration of the object's start and stop [m/s^2], 0..20 (the speed ramps
                               # last 2 speed / obj_accel; 0: the planner's 1 s ramps)
    extra_seconds = 0.5        # simulated time after the planned path ends [s], 0..10
    max_seconds = 0.0          # cap on the simulated time [s] (0: no cap; a capped run stops mid-path), 0..600
    qp_iters = 4               # ADMM iterations per control step before the convergence checks (up to 200), 1..1000
    qp_first_test = -1         # >= 0: a control step's first convergence check after the last step's iterations
                               # minus this (QPSettings.warm_first_test; fewer checks under noise); -1: after qp_iters
    qp_alpha = 0.0             # ADMM over-relaxation of the controller's QP (QPSettings.alpha), 0..1.95; 0: the
                               # controller's own (1.6)
    qp_rho = 0.0               # ADMM step size rho of the transport controller's QP (QPSettings.rho), 0..1000;
                               # 0: the controller's own (3)
    control_substeps = 1       # physics steps per control step (zero-order hold), 1..10; 1 = control at the
                               # physics rate (the control period is this x the scene's timestep; the metrics'
                               # physics-rate monitors still run every physics step, see wbc_jax.rollout.step)
    chunk_seconds = 2.0        # most simulated seconds per jit call / checkpoint (fitted to the horizon), 0.02..60
    m = 0.3                    # object mass [kg], tray friction, object side [m], foot/ground friction (0: the
    mu = 0.7                   # scene's) and controller variant of every run, for those of them that are not
    d = 0.08                   # factors
    ground_mu = 0.0
    variant = "full"
    terrain = "known"          # "known": footholds on the blocks' tops from the scene file; "blind": at the
                               # floor's height, the touchdown rules handle the blocks (wbc_jax.planner.transport)
    com_plan = "zmp"           # "zmp": the CoM replanned per footstep, ZMP on the stance pair's line (the paper's;
                               # wbc_jax.planner.transport.zmp_com_path); "spline": it follows the object (+ offset)
    cone = "scene"             # MuJoCo's friction cone of every contact: "scene" (the scene file's: pyramidal),
    impratio = 0.0             # "pyramidal" or "elliptic"; impratio: frictional-to-normal impedance ratio (0: the
                               # scene's, 10); both for studies of the contact law (wbc_jax.studies.s_cause)
    sensing = "auto"           # Warp: "exact" (a sensing call gives the controller the current state) or "delayed"
                               # (it reads what Warp's step left: the state one physics step old; one call fewer);
                               # "auto": delayed on Warp (same statistics, measured), exact on JAX
    controller = "transport"   # "transport" (the object-transport WBC; metrics R, T, S) or "centroidal" (the
                               # capture-point trot of the centroidal WBC; wbc_jax.rollout.controllers.trot_metrics):
                               # it stands 0.5 s, then walks walk_seconds at the commanded speed (campaign.speed or
                               # the speed factor) in half-cycles of step_time with four_foot of four-foot support
    mass_error = 0.0           # centroidal: the controller's model mass error (-0.2: model 20 % too light)
    walk_seconds = 10.0        # centroidal: walking time [s] (round(walk_seconds / step_time) half-cycles)
    step_time = 0.25           # centroidal: trot half-cycle [s]
    four_foot = 0.08           # centroidal: four-foot support per half-cycle [s]

    [factors]                  # 1 to 5 factors of wbc_jax.campaign.factors, at least 2 levels each: here the
    m = [0.2, 0.3, 0.4]        # paper's 3 x 3 x 3: object mass [kg], 0 < m <= 20
    mu = [0.4, 0.7, 1.0]       # tray friction, 0 < mu <= 5
    d = [0.06, 0.08, 0.10]     # object side [m], 0.008 < d <= 0.2 (the robot's tray narrows it further)
                               # others: ground_mu, speed, obj_accel, push_N, qvel_noise_std, observer, variant,
                               # gain.<leaf>; centroidal: m, mu, d, ground_mu, speed, push_N, qvel_noise_std, mass_error

    [perturbations]            # per run, drawn from the run's own seed; all zero = deterministic repetitions
    object_xy_mm = 3.0         # object placement on the tray: uniform in +-value along x and y [mm], 0..20
    object_yaw_deg = 3.0       # object yaw on the tray: uniform in +-value [deg], 0..30
    base_speed_std = 0.02      # initial horizontal velocity of robot and object, Gaussian std per axis [m/s], 0..0.5
    push_max_N = 20.0          # trunk push: magnitude uniform in [0, value] [N], random horizontal direction, 0..200
    push_duration_s = 0.2      # push duration [s], 0..2
    push_window = [0.2, 0.7]   # push start: uniform in this fraction of the planned duration, 0 <= a <= b < 1
    qvel_noise_std = 0.01      # noise on the state the controller sees: white Gaussian std added every control step
                               # to each generalized velocity it reads [m/s, rad/s], 0..1 (the physics stays exact;
                               # drawn from the run's seed, see wbc_jax.rollout.state.Push)
    push_dir_deg = 0.0         # direction of the push_N factor's pushes from world +x [deg] (only with push_N)

    [analysis]                 # the report's statistics (not hashed)
    order = 2                  # highest ANOVA interaction order
    alpha = 0.05

    [plugin]                   # optional: a subclass of the controller from outside the package, its own fields
    class = "examples.torque_lag:TorqueLag"   # (wbc_jax.campaign.spec_controller)

The design table of a spec (one row per run, its seed and perturbations): :mod:`wbc_jax.campaign.design`.
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from wbc_jax.campaign import controllers as controllers_mod
from wbc_jax.campaign import factors as factors_mod
from wbc_jax.campaign.design import Design, design  # noqa: F401  (a spec's design table, re-exported)
from wbc_jax.campaign.spec_controller import check_controller, parse_plugin
from wbc_jax.control.variants import VARIANTS
from wbc_jax.errors import InputError, SpecError
from wbc_jax.io_utils import read_capped

SWEEPS = Path(__file__).resolve().parents[2] / "sweeps"

# The validator's key tables (docs/specs.md is generated from them: wbc_jax.studies.spec_docs).
# key: (type, default, lo, hi, lo_open, unit/description)
CAMPAIGN = {
    "name": (str, "campaign", None, None, False, "text"),
    "reps": (int, 10, 1, 1000, False, "repetitions per cell"),
    "seed": (int, 0, 0, 2**32 - 1, False, "base seed"),
    "scene": (str, "transport", None, None, False, '"transport" or "flat"'),
    "distance": (float, 3.4, 0.05, 10.0, False, "[m]"),
    "speed": (float, 0.13, 0.01, 0.5, False, "[m/s]"),
    "obj_accel": (float, 0.0, 0.0, 20.0, False, "[m/s^2], 0 = the planner's 1 s ramps"),
    "extra_seconds": (float, 0.5, 0.0, 10.0, False, "[s]"),
    "max_seconds": (float, 0.0, 0.0, 600.0, False, "[s], 0 = no cap"),
    "qp_iters": (int, 4, 1, 1000, False, "ADMM iterations before the convergence checks"),
    "qp_first_test": (int, -1, -1, 1000, False,
                      "the first convergence check after the last control step's iterations minus this; -1: after "
                      "qp_iters"),
    "qp_alpha": (float, 0.0, 0.0, 1.95, False, "ADMM over-relaxation of the controller's QP; 0 = the controller's"),
    "qp_rho": (float, 0.0, 0.0, 1000.0, False, "ADMM step size rho of the transport controller's QP; 0 = its own"),
    "qp_max_iters": (int, 0, 0, 1000, False,
                     "the most ADMM iterations of the controller's QP in a control step; 0 = the controller's (200)"),
    "qp_launch_order": (str, "batch", None, None, False,
                        '"batch" or "predicted": the order the QP\'s iteration programs start in (GPU kernels)'),
    "qp_reuse_factors": (int, 0, 0, 1, False,
                         "1: the transport controller's QP factors every other control step (GPU kernels)"),
    "control_substeps": (int, 1, 1, 10, False,
                         "physics steps per control step (zero-order hold); 1 = control at the physics rate"),
    "chunk_seconds": (float, 2.0, 0.02, 60.0, False, "[s]"),
    "solver_iterations": (int, 0, 0, 1000, False,
                          "MuJoCo constraint-solver iterations per physics step; 0 = the scene's"),
    "cone": (str, "scene", None, None, False,
             '"scene" (the scene file\'s), "pyramidal" or "elliptic": MuJoCo\'s friction cone of every contact'),
    "impratio": (float, 0.0, 0.0, 1000.0, False, "MuJoCo's frictional-to-normal impedance ratio; 0 = the scene's"),
    "backend": (str, "auto", None, None, False,
                '"auto" (Warp on a CUDA GPU with warp-lang, else JAX), "jax" or "warp": the MJX physics '
                'implementation'),
    # a run's value of a factor the spec does not vary (wbc_jax.campaign.factors.REGISTRY: FactorDef.fixed)
    "m": (float, 0.3, 0.0, 20.0, True, "[kg]"),
    "mu": (float, 0.7, 0.0, 5.0, True, "[-]"),
    "d": (float, 0.08, 0.008, 0.2, True, "[m]"),
    "ground_mu": (float, 0.0, 0.0, 5.0, False, "[-], 0 = the scene's"),
    "variant": (str, "full", None, None, False, '"full", "no_tray_cone", "no_observer" or "no_posture"'),
    "terrain": (str, "known", None, None, False,
                '"known" (footholds on the blocks, from the scene file) or "blind" (footholds at the floor\'s '
                'height; the touchdown rules handle the blocks)'),
    "com_plan": (str, "zmp", None, None, False,
                 '"spline" (the CoM follows the object) or "zmp" (replanned per footstep: ZMP on the stance pair\'s '
                 'line)'),
    "sensing": (str, "auto", None, None, False,
                '"auto" (delayed on Warp, exact on JAX), "exact" or "delayed" (Warp only: the controller reads the '
                'state one physics step old and Warp\'s sensing call is saved; wbc_jax.rollout.config.SENSING)'),
    "controller": (str, "transport", None, None, False,
                   '"transport" (object transport; R, T, S) or "centroidal" (the capture-point trot; speed, CP error, '
                   'attitude)'),
    "mass_error": (float, 0.0, -0.5, 1.0, True, "centroidal: the controller's model mass error [-] (fraction)"),
    "walk_seconds": (float, 10.0, 0.5, 600.0, False, "centroidal: walking time [s]"),
    "step_time": (float, 0.25, 0.02, 2.0, False, "centroidal: trot half-cycle [s]"),
    "four_foot": (float, 0.08, 0.0, 2.0, True, "centroidal: four-foot support per half-cycle [s], < step_time"),
}
# the factors a spec may vary: wbc_jax.campaign.factors (name -> FactorDef; plus gain.<leaf> multipliers)
FACTORS = factors_mod.REGISTRY
PERTURBATIONS = {
    "object_xy_mm": (float, 0.0, 0.0, 20.0, False, "[mm]"),
    "object_yaw_deg": (float, 0.0, 0.0, 30.0, False, "[deg]"),
    "base_speed_std": (float, 0.0, 0.0, 0.5, False, "[m/s]"),
    "push_max_N": (float, 0.0, 0.0, 200.0, False, "[N]"),
    "push_duration_s": (float, 0.2, 0.0, 2.0, False, "[s]"),
    "push_window": (list, [0.2, 0.7], 0.0, 1.0, False, "fractions of the planned duration, 0 <= a <= b < 1"),
    "qvel_noise_std": (float, 0.0, 0.0, 1.0, False, "[m/s, rad/s]"),
    "push_dir_deg": (float, 0.0, 0.0, 360.0, False, "[deg]"),
}
# the report's statistics (not hashed: they do not change a run)
ANALYSIS = {
    "order": (int, 2, 1, factors_mod.MAX_FACTORS, False, "highest interaction order of the ANOVA model"),
    "alpha": (float, 0.05, 0.0, 0.5, True, "significance level"),
}
SCENES = ("transport", "flat")
SENSING = ("auto", "exact", "delayed")  # wbc_jax.rollout.config.SENSING (not imported: spec loading stays JAX-free)
TERRAINS = ("known", "blind")  # wbc_jax.planner.transport.TERRAINS (not imported: spec loading stays JAX-free)
COM_PLANS = ("spline", "zmp")  # wbc_jax.planner.transport.COM_PLANS (not imported, as above)
CONES = ("scene", "pyramidal", "elliptic")  # MuJoCo's opt.cone, or the scene file's
CONTROLLER_NAMES = tuple(controllers_mod.CONTROLLERS)  # wbc_jax.rollout.controllers.CONTROLLERS (JAX-free copy)
BACKENDS = ("auto", "jax", "warp")  # wbc_jax.physics.backend.BACKENDS (not imported here: spec loading stays JAX-free)
LAUNCH_ORDERS = ("batch", "predicted")  # wbc_jax.qp.settings.LAUNCH_ORDERS (not imported, as above)
# keys added after specs were first hashed: left out of Spec.hash at these values (the behaviour from before the key
# existed), so existing baselines and checkpoints stay valid; a default unlike its neutral value (com_plan "zmp")
# changes the hash of every spec that omits the key, as the behaviour changed
_HASH_NEUTRAL = {"campaign": {"control_substeps": 1, "backend": "auto", "solver_iterations": 0, "m": 0.3, "mu": 0.7,
                               "d": 0.08, "ground_mu": 0.0, "variant": "full", "terrain": "known",
                               "com_plan": "spline", "sensing": "auto",
                               "obj_accel": 0.0, "cone": "scene", "impratio": 0.0, "controller": "transport",
                               "mass_error": 0.0, "walk_seconds": 10.0, "step_time": 0.25, "four_foot": 0.08,
                               "qp_first_test": -1, "qp_alpha": 0.0, "qp_reuse_factors": 0,
                               "qp_rho": 0.0, "qp_max_iters": 0, "qp_launch_order": "batch"},
                 "perturbations": {"push_dir_deg": 0.0}}


@dataclass(frozen=True)
class Spec:
    """A validated campaign spec (units as in the module docstring)."""

    path: str
    campaign: dict
    factors: dict
    perturbations: dict
    text_sha256: str = field(default="")
    analysis: dict = field(default_factory=lambda: {k: v[1] for k, v in ANALYSIS.items()})
    plugin: dict = field(default_factory=dict)  # [plugin] (wbc_jax.campaign.spec_controller); {}: none
    plugin_sha256: str = ""  # its module file's sha256 (in the hash)

    @property
    def reps(self) -> int:
        return self.campaign["reps"]

    def canonical(self) -> dict:
        return dict(campaign=self.campaign, factors=self.factors, perturbations=self.perturbations,
                    analysis=self.analysis, **({"plugin": self.plugin} if self.plugin else {}))

    def hashed(self) -> dict:
        """:meth:`canonical` less ``analysis`` and the keys of ``_HASH_NEUTRAL`` that are at their neutral value,
        with a plug-in's module sha256."""
        out = self.canonical()
        del out["analysis"]
        for table, keys in _HASH_NEUTRAL.items():
            out[table] = {k: v for k, v in out[table].items() if not (k in keys and v == keys[k])}
        return dict(out, plugin_sha256=self.plugin_sha256) if self.plugin else out

    @property
    def hash(self) -> str:
        """sha256 of the validated content (defaults filled in, key order fixed; :meth:`hashed`)."""
        return hashlib.sha256(json.dumps(self.hashed(), sort_keys=True).encode()).hexdigest()

    @property
    def zero_noise(self) -> bool:
        """No per-run randomness: the repetitions of a cell are identical."""
        p, f = self.perturbations, self.factors
        a, b = p["push_window"]
        pushed = p["push_max_N"] > 0 or (max(f.get("push_N", [0.0])) > 0 and a < b)  # random size or start
        return not (p["object_xy_mm"] > 0 or p["object_yaw_deg"] > 0 or p["base_speed_std"] > 0
                    or (pushed and p["push_duration_s"] > 0) or p["qvel_noise_std"] > 0
                    or max(f.get("qvel_noise_std", [0.0])) > 0)


def spec_error(path, key, msg) -> SpecError:
    """The one-line error ``PATH: KEY: MSG`` of a spec (or of a file read with the same rules: gains, tune specs)."""
    return SpecError(f"{path}: {key}: {msg}")


def checked_number(path, key, v, typ, lo, hi, lo_open, unit):
    """``v`` as ``typ`` (int or float) within [lo, hi] (lo excluded with ``lo_open``); a :func:`spec_error` naming
    ``key`` and ``unit`` otherwise."""
    if typ is int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise spec_error(path, key, f"expected an integer {lo}..{hi} ({unit}), got {v!r}")
    elif isinstance(v, bool) or not isinstance(v, (int, float)):
        raise spec_error(path, key, f"expected a number {lo}..{hi} {unit}, got {v!r}")
    v = typ(v)
    if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
        rng = f"{lo} < value <= {hi}" if lo_open else f"{lo} <= value <= {hi}"
        raise spec_error(path, key, f"= {v}: out of range, expected {rng} {unit}")
    return v


def checked_table(path, name, raw, schema) -> dict:
    """The TOML table ``raw`` named ``name`` checked against ``schema`` (key -> (type, default, lo, hi, lo_open,
    unit)): every key of the schema, defaults filled in; a :func:`spec_error` for an unknown key or a bad value."""
    if not isinstance(raw, dict):
        raise spec_error(path, name, f"expected a table [{name}], got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(schema))
    if unknown:
        raise spec_error(path, f"{name}.{unknown[0]}", f"unknown key; expected one of {', '.join(schema)}")
    out = {}
    for key, (typ, default, lo, hi, lo_open, unit) in schema.items():
        full = f"{name}.{key}"
        v = raw.get(key, default)
        if typ is str:
            if not isinstance(v, str):
                raise spec_error(path, full, f"expected a string ({unit}), got {v!r}")
            out[key] = v
        elif typ is list:
            if (not isinstance(v, list) or len(v) != 2
                    or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)):
                raise spec_error(path, full, f"expected a list of 2 numbers ({unit}), got {v!r}")
            a, b = float(v[0]), float(v[1])
            if not (0.0 <= a <= b < 1.0):
                raise spec_error(path, full, f"= {v}: out of range, expected {unit}")
            out[key] = [a, b]
        else:
            out[key] = checked_number(path, full, v, typ, lo, hi, lo_open, unit)
    return out


def _level(path, key, x, fd: factors_mod.FactorDef):
    """One level of a factor, validated and normalised (numbers: float; bool: 1/0; choice: the string)."""
    if fd.kind == "bool":
        if x in (True, False) or (isinstance(x, int) and x in (0, 1)):
            return int(x)
        raise spec_error(path, key, f"level {x!r}: expected true, false, 1 or 0")
    if fd.kind == "choice":
        if isinstance(x, str) and x in fd.choices:
            return x
        raise spec_error(path, key, f"level {x!r}: expected one of {', '.join(fd.choices)}")
    return checked_number(path, key, x, float, fd.lo, fd.hi, fd.lo_open, fd.unit)


def _parse_factors(path, raw_f, plugin_fields: dict) -> dict:
    """The [factors] table: 1..MAX_FACTORS known factors (``plugin_fields``: the plug-in's, name -> default), each a
    list of >= 2 distinct valid levels; returned in design order (:func:`wbc_jax.campaign.factors.design_order`)."""
    if not isinstance(raw_f, dict):
        raise spec_error(path, "factors", "expected a table")
    for key in sorted(raw_f):
        if isinstance(raw_f[key], dict) and raw_f[key]:  # TOML read gain.kp_obj = [...] as a table
            sub = next(iter(raw_f[key]))
            raise spec_error(path, f"factors.{key}.{sub}", f'a dotted factor name: quote it ("{key}.{sub}" = [...])')
        if factors_mod.factor_def(key, plugin_fields) is None:
            raise spec_error(path, f"factors.{key}", f"unknown factor; expected one of {factors_mod.known_names()}")
    if not 1 <= len(raw_f) <= factors_mod.MAX_FACTORS:
        raise spec_error(path, "factors", f"{len(raw_f)} factors: expected 1 to {factors_mod.MAX_FACTORS}")
    out = {}
    for key in factors_mod.design_order(raw_f, plugin_fields):
        full, v = f"factors.{key}", raw_f[key]
        if not isinstance(v, list) or len(v) < 2:
            raise spec_error(path, full, f"expected a list of at least 2 levels, got {v!r}")
        levels = [_level(path, full, x, factors_mod.factor_def(key, plugin_fields)) for x in v]
        if len(set(levels)) != len(levels):
            raise spec_error(path, full, f"= {v}: levels must be distinct")
        leaf = key[len(factors_mod.GAIN_PREFIX):] if key.startswith(factors_mod.GAIN_PREFIX) else None
        if leaf in factors_mod.REGULARIZATION and min(levels) <= 0:
            raise spec_error(path, full, f"level {min(levels):g}: a regularization weight's multiplier must be > 0 "
                                         "(the QP would be singular)")
        out[key] = levels
    return out


def _check_fixed(path, camp: dict, pert: dict, factors: dict, plugin_fields: dict) -> None:
    """A varied factor's fixed-value key (FactorDef.fixed) must stay at its default; ``push_dir_deg`` needs the
    push_N factor; ``qp_max_iters`` is 0 or at least ``qp_iters`` (the fixed iterations come first)."""
    tables = {"campaign": (camp, CAMPAIGN), "perturbations": (pert, PERTURBATIONS)}
    for key in factors:
        table, _, name = factors_mod.factor_def(key, plugin_fields).fixed.partition(".")
        if table in tables and tables[table][0][name] != tables[table][1][name][1]:
            raise spec_error(path, f"{table}.{name}", f"= {tables[table][0][name]!r}: the factor {key} is varied; "
                                                     "leave this key out (or at its default)")
    if pert["push_dir_deg"] != PERTURBATIONS["push_dir_deg"][1] and "push_N" not in factors:
        raise spec_error(path, "perturbations.push_dir_deg", "used only with the push_N factor (random pushes have "
                                                           "a random direction)")
    if 0 < camp["qp_max_iters"] < camp["qp_iters"]:
        raise spec_error(path, "campaign.qp_max_iters", f"= {camp['qp_max_iters']} is below campaign.qp_iters = "
                                                        f"{camp['qp_iters']}: use 0 (the controller's 200) or more")


def parse_spec(data: dict, path: str = "<spec>", text_sha256: str = "") -> Spec:
    """Validate a spec dict (as read by tomllib). Raises SpecError naming ``path``, the key and the range."""
    unknown = sorted(set(data) - {"campaign", "factors", "perturbations", "analysis", "plugin"})
    if unknown:
        raise spec_error(path, unknown[0], "unknown table; expected campaign, factors, perturbations, analysis, plugin")
    camp = checked_table(path, "campaign", data.get("campaign", {}), CAMPAIGN)
    for key, allowed in (("backend", BACKENDS), ("scene", SCENES), ("variant", tuple(VARIANTS)),
                         ("terrain", TERRAINS), ("com_plan", COM_PLANS), ("sensing", SENSING), ("cone", CONES),
                         ("controller", CONTROLLER_NAMES), ("qp_launch_order", LAUNCH_ORDERS)):
        if camp[key] not in allowed:
            raise spec_error(path, f"campaign.{key}", f"= {camp[key]!r}: expected one of {', '.join(allowed)}")
    if "factors" not in data:
        raise spec_error(path, "factors", "missing table [factors] (level lists, e.g. m, mu, d)")
    plugin = parse_plugin(path, data.get("plugin"), camp["controller"], data["factors"])
    factors = _parse_factors(path, data["factors"], plugin.fields)
    pert = checked_table(path, "perturbations", data.get("perturbations", {}), PERTURBATIONS)
    _check_fixed(path, camp, pert, factors, plugin.fields)
    check_controller(path, camp, factors, CAMPAIGN)
    analysis = checked_table(path, "analysis", data.get("analysis", {}), ANALYSIS)
    return Spec(path=str(path), campaign=camp, factors=factors, perturbations=pert, text_sha256=text_sha256,
                analysis=analysis, plugin=plugin.values, plugin_sha256=plugin.sha256)


def load_spec(path: str | Path) -> Spec:
    """Read and validate a TOML spec (at most 1 MiB). Raises SpecError (one line: file, key, expected) on any
    problem."""
    try:
        raw = read_capped(path, what="spec")
    except OSError as e:
        raise SpecError(f"{path}: cannot read spec file ({e.strerror or e})") from None
    except InputError as e:
        raise SpecError(str(e)) from None
    try:
        data = tomllib.loads(raw.decode("utf-8-sig"))  # a byte-order mark (some Windows editors) is dropped
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SpecError(f"{path}: not valid TOML ({str(e).splitlines()[0]})") from None
    return parse_spec(data, str(path), hashlib.sha256(raw).hexdigest())


def default_spec_path(accelerator: bool) -> Path:
    """The paper spec when an accelerator is present, else the CPU-sized quick spec."""
    return SWEEPS / ("paper_campaign.toml" if accelerator else "quick.toml")
