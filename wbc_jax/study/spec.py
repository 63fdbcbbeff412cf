"""Campaign specs (``sweeps/*.toml``): loading with stdlib ``tomllib``, validation, the design table.

A spec has three tables (every key optional except ``factors``; an example with the shipped specs' values below;
every key's default, unit and range: ``docs/specs.md``, generated from the key tables ``CAMPAIGN``, ``FACTORS`` and
``PERTURBATIONS`` by :mod:`wbc_jax.study.spec_docs`)::

    [campaign]                 # what is simulated
    name = "paper"             # free text
    reps = 10                  # repetitions per cell, 1..1000
    seed = 2024                # base seed, 0 <= seed < 2**32
    scene = "transport"        # "transport" (obstacle course) or "flat"
    distance = 3.4             # object travel [m], 0.05..10
    speed = 0.13               # cruise speed [m/s], 0.01..0.5
    extra_seconds = 0.5        # simulated time after the planned path ends [s], 0..10
    max_seconds = 0.0          # cap on the simulated time [s] (0: no cap; a capped run stops mid-path), 0..600
    qp_iters = 20              # ADMM iterations per control step, 1..1000
    control_substeps = 1       # physics steps per control step (zero-order hold), 1..10; 1 = control at the
                               # physics rate (the control period is this x the scene's timestep; the metrics'
                               # physics-rate monitors still run every physics step, see wbc_jax.sim.rollout)
    chunk_seconds = 2.0        # simulated seconds per jit call / checkpoint, 0.02..60

    [factors]                  # levels of the 3 x 3 x 3 design (at least 2 levels each)
    m = [0.2, 0.3, 0.4]        # object mass [kg], 0 < m <= 20
    mu = [0.4, 0.7, 1.0]       # tray friction, 0 < mu <= 5
    d = [0.06, 0.08, 0.10]     # object side [m], 0.008 < d <= 0.2 (the robot's tray narrows it further)

    [perturbations]            # per run, drawn from the run's own seed; all zero = deterministic repetitions
    object_xy_mm = 3.0         # object placement on the tray: uniform in +-value along x and y [mm], 0..20
    object_yaw_deg = 3.0       # object yaw on the tray: uniform in +-value [deg], 0..30
    base_speed_std = 0.02      # initial horizontal velocity of robot and object, Gaussian std per axis [m/s], 0..0.5
    push_max_N = 20.0          # trunk push: magnitude uniform in [0, value] [N], random horizontal direction, 0..200
    push_duration_s = 0.2      # push duration [s], 0..2
    push_window = [0.2, 0.7]   # push start: uniform in this fraction of the planned duration, 0 <= a <= b < 1
    qvel_noise_std = 0.01      # noise on the state the controller sees: white Gaussian std added every control step
                               # to each generalized velocity it reads [m/s, rad/s], 0..1 (the physics stays exact;
                               # drawn from the run's seed, see wbc_jax.sim.rollout.Push)

Run i (cells in the order m, mu, d of the product of the levels, then reps) has seed
``SeedSequence([seed, i]).generate_state(1)[0]``; its perturbations are drawn from
``numpy.random.default_rng(run_seed)`` in the order dx, dy, yaw, vx, vy, push magnitude, push angle, push start.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from wbc_jax.errors import InputError, SpecError
from wbc_jax.io_utils import read_capped

SWEEPS = Path(__file__).resolve().parents[2] / "sweeps"

# The validator's key tables (docs/specs.md is generated from them: wbc_jax.study.spec_docs).
# key: (type, default, lo, hi, lo_open, unit/description)
CAMPAIGN = {
    "name": (str, "campaign", None, None, False, "text"),
    "reps": (int, 10, 1, 1000, False, "repetitions per cell"),
    "seed": (int, 0, 0, 2**32 - 1, False, "base seed"),
    "scene": (str, "transport", None, None, False, '"transport" or "flat"'),
    "distance": (float, 3.4, 0.05, 10.0, False, "[m]"),
    "speed": (float, 0.13, 0.01, 0.5, False, "[m/s]"),
    "extra_seconds": (float, 0.5, 0.0, 10.0, False, "[s]"),
    "max_seconds": (float, 0.0, 0.0, 600.0, False, "[s], 0 = no cap"),
    "qp_iters": (int, 20, 1, 1000, False, "ADMM iterations"),
    "control_substeps": (int, 1, 1, 10, False,
                         "physics steps per control step (zero-order hold); 1 = control at the physics rate"),
    "chunk_seconds": (float, 2.0, 0.02, 60.0, False, "[s]"),
    "solver_iterations": (int, 0, 0, 1000, False, "MuJoCo constraint-solver iterations per physics step; 0 = the scene's"),
    "backend": (str, "auto", None, None, False,
                '"auto" (JAX for now), "jax" or "warp": the MJX physics implementation'),
}
# key: (lo, hi, unit); each level in lo < value <= hi
FACTORS = {"m": (0.0, 20.0, "[kg]"), "mu": (0.0, 5.0, "[-]"), "d": (0.008, 0.2, "[m]")}
PERTURBATIONS = {
    "object_xy_mm": (float, 0.0, 0.0, 20.0, False, "[mm]"),
    "object_yaw_deg": (float, 0.0, 0.0, 30.0, False, "[deg]"),
    "base_speed_std": (float, 0.0, 0.0, 0.5, False, "[m/s]"),
    "push_max_N": (float, 0.0, 0.0, 200.0, False, "[N]"),
    "push_duration_s": (float, 0.2, 0.0, 2.0, False, "[s]"),
    "push_window": (list, [0.2, 0.7], 0.0, 1.0, False, "fractions of the planned duration, 0 <= a <= b < 1"),
    "qvel_noise_std": (float, 0.0, 0.0, 1.0, False, "[m/s, rad/s]"),
}
SCENES = ("transport", "flat")
BACKENDS = ("auto", "jax", "warp")  # wbc_jax.sim.physics.BACKENDS (not imported here: spec loading stays JAX-free)
# keys added after specs were first hashed: left out of Spec.hash at these values (which reproduce the behaviour
# from before the key existed), so the hashes of existing baselines and checkpoints stay valid
_HASH_NEUTRAL = {"campaign": {"control_substeps": 1, "backend": "auto", "solver_iterations": 0}}


@dataclass(frozen=True)
class Spec:
    """A validated campaign spec (units as in the module docstring)."""

    path: str
    campaign: dict
    factors: dict
    perturbations: dict
    text_sha256: str = field(default="")

    @property
    def reps(self) -> int:
        return self.campaign["reps"]

    def canonical(self) -> dict:
        return dict(campaign=self.campaign, factors=self.factors, perturbations=self.perturbations)

    def hashed(self) -> dict:
        """:meth:`canonical` less the keys of ``_HASH_NEUTRAL`` that are at their neutral value."""
        out = self.canonical()
        for table, keys in _HASH_NEUTRAL.items():
            out[table] = {k: v for k, v in out[table].items() if not (k in keys and v == keys[k])}
        return out

    @property
    def hash(self) -> str:
        """sha256 of the validated content (defaults filled in, key order fixed; :meth:`hashed`)."""
        return hashlib.sha256(json.dumps(self.hashed(), sort_keys=True).encode()).hexdigest()

    @property
    def zero_noise(self) -> bool:
        p = self.perturbations
        return not (p["object_xy_mm"] > 0 or p["object_yaw_deg"] > 0 or p["base_speed_std"] > 0
                    or (p["push_max_N"] > 0 and p["push_duration_s"] > 0) or p["qvel_noise_std"] > 0)


def _err(path, key, msg):
    return SpecError(f"{path}: {key}: {msg}")


def _number(path, key, v, typ, lo, hi, lo_open, unit):
    if typ is int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise _err(path, key, f"expected an integer {lo}..{hi} ({unit}), got {v!r}")
    elif isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _err(path, key, f"expected a number {lo}..{hi} {unit}, got {v!r}")
    v = typ(v)
    if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
        rng = f"{lo} < value <= {hi}" if lo_open else f"{lo} <= value <= {hi}"
        raise _err(path, key, f"= {v}: out of range, expected {rng} {unit}")
    return v


def _table(path, name, raw, schema):
    if not isinstance(raw, dict):
        raise _err(path, name, f"expected a table [{name}], got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(schema))
    if unknown:
        raise _err(path, f"{name}.{unknown[0]}", f"unknown key; expected one of {', '.join(schema)}")
    out = {}
    for key, (typ, default, lo, hi, lo_open, unit) in schema.items():
        full = f"{name}.{key}"
        v = raw.get(key, default)
        if typ is str:
            if not isinstance(v, str):
                raise _err(path, full, f"expected a string ({unit}), got {v!r}")
            out[key] = v
        elif typ is list:
            if (not isinstance(v, list) or len(v) != 2
                    or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)):
                raise _err(path, full, f"expected a list of 2 numbers ({unit}), got {v!r}")
            a, b = float(v[0]), float(v[1])
            if not (0.0 <= a <= b < 1.0):
                raise _err(path, full, f"= {v}: out of range, expected {unit}")
            out[key] = [a, b]
        else:
            out[key] = _number(path, full, v, typ, lo, hi, lo_open, unit)
    return out


def parse_spec(data: dict, path: str = "<spec>", text_sha256: str = "") -> Spec:
    """Validate a spec dict (as read by tomllib). Raises SpecError naming ``path``, the key and the range."""
    unknown = sorted(set(data) - {"campaign", "factors", "perturbations"})
    if unknown:
        raise _err(path, unknown[0], "unknown table; expected campaign, factors, perturbations")
    camp = _table(path, "campaign", data.get("campaign", {}), CAMPAIGN)
    if camp["backend"] not in BACKENDS:
        raise _err(path, "campaign.backend", f"= {camp['backend']!r}: expected one of {', '.join(BACKENDS)}")
    if camp["scene"] not in SCENES:
        raise _err(path, "campaign.scene", f"= {camp['scene']!r}: expected one of {', '.join(SCENES)}")
    if "factors" not in data:
        raise _err(path, "factors", "missing table [factors] (m, mu, d level lists)")
    raw_f = data["factors"]
    if not isinstance(raw_f, dict):
        raise _err(path, "factors", "expected a table")
    unknown = sorted(set(raw_f) - set(FACTORS))
    if unknown:
        raise _err(path, f"factors.{unknown[0]}", f"unknown factor; expected {', '.join(FACTORS)}")
    factors = {}
    for key, (lo, hi, unit) in FACTORS.items():
        full = f"factors.{key}"
        if key not in raw_f:
            raise _err(path, full, f"missing; expected a list of levels in {lo} < value <= {hi} {unit}")
        v = raw_f[key]
        if not isinstance(v, list) or len(v) < 2:
            raise _err(path, full, f"expected a list of at least 2 levels, got {v!r}")
        levels = [_number(path, full, x, float, lo, hi, True, unit) for x in v]
        if len(set(levels)) != len(levels):
            raise _err(path, full, f"= {v}: levels must be distinct")
        factors[key] = levels
    pert = _table(path, "perturbations", data.get("perturbations", {}), PERTURBATIONS)
    return Spec(path=str(path), campaign=camp, factors=factors, perturbations=pert, text_sha256=text_sha256)


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
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SpecError(f"{path}: not valid TOML ({str(e).splitlines()[0]})") from None
    return parse_spec(data, str(path), hashlib.sha256(raw).hexdigest())


def default_spec_path(accelerator: bool) -> Path:
    """The paper spec when an accelerator is present, else the CPU-sized quick spec."""
    return SWEEPS / ("paper_campaign.toml" if accelerator else "quick.toml")


@dataclass(frozen=True)
class Design:
    """One row per run (cells in product order of m, mu, d, then reps), with the run's perturbations.

    Attributes (each (B,)): m, mu, d, rep, seed; obj_dx, obj_dy [m] and obj_yaw [rad] (placement on the
    tray, tray-aligned world x/y), v0 (B, 2) [m/s] initial horizontal velocity, push_force (B, 3) [N],
    push_t0 [s] (fraction of the planned duration until the plan is known: see :func:`design`),
    push_duration [s]; qvel_noise_std [m/s, rad/s] (controller-view velocity noise, drawn during the rollout from
    the run's seed).
    """

    m: np.ndarray
    mu: np.ndarray
    d: np.ndarray
    rep: np.ndarray
    seed: np.ndarray
    obj_dx: np.ndarray
    obj_dy: np.ndarray
    obj_yaw: np.ndarray
    v0: np.ndarray
    push_force: np.ndarray
    push_frac: np.ndarray
    push_duration: np.ndarray
    qvel_noise_std: np.ndarray

    @property
    def n(self) -> int:
        return int(self.m.shape[0])

    def asdict(self):
        return asdict(self)


def run_seed(base: int, i: int) -> int:
    return int(np.random.SeedSequence([int(base), int(i)]).generate_state(1)[0])


def design(spec: Spec) -> Design:
    """The design table of a spec with every run's seed and perturbations (host-side, deterministic)."""
    f, p = spec.factors, spec.perturbations
    cells = list(itertools.product(f["m"], f["mu"], f["d"]))
    rows = [(c, r) for c in cells for r in range(spec.reps)]
    B = len(rows)
    seeds = np.array([run_seed(spec.campaign["seed"], i) for i in range(B)], dtype=np.uint64)
    draws = np.zeros((B, 8))
    for i, s in enumerate(seeds):
        rng = np.random.default_rng(int(s))
        draws[i] = [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1), rng.normal(), rng.normal(),
                    rng.uniform(0, 1), rng.uniform(0, 2 * np.pi), rng.uniform(0, 1)]
    a, b = p["push_window"]
    mag = draws[:, 5] * p["push_max_N"] if p["push_duration_s"] > 0 else np.zeros(B)
    push = np.stack([mag * np.cos(draws[:, 6]), mag * np.sin(draws[:, 6]), np.zeros(B)], axis=1)
    return Design(
        m=np.array([c[0] for c, _ in rows]), mu=np.array([c[1] for c, _ in rows]),
        d=np.array([c[2] for c, _ in rows]), rep=np.array([r for _, r in rows]), seed=seeds,
        obj_dx=draws[:, 0] * p["object_xy_mm"] * 1e-3, obj_dy=draws[:, 1] * p["object_xy_mm"] * 1e-3,
        obj_yaw=np.deg2rad(draws[:, 2] * p["object_yaw_deg"]), v0=draws[:, 3:5] * p["base_speed_std"],
        push_force=push, push_frac=a + (b - a) * draws[:, 7],
        push_duration=np.full(B, p["push_duration_s"] if p["push_max_N"] > 0 else 0.0),
        qvel_noise_std=np.full(B, p["qvel_noise_std"]))
