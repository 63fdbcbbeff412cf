"""``wbc-jax tune``: batched search over the transport controller's gains.

A **candidate** is a :class:`~wbc_jax.control.transport.TransportGains` whose tuned leaves are the default
gains times a multiplier; the search works on x = ln(multiplier), one coordinate per tuned leaf (a vector leaf
such as ``kp_com`` (3,) is scaled as a whole). Leaves that are not tuned keep their *start* value (default x
the spec's start scale). Every round evaluates C candidates on n runs each (the chosen factor cells x reps of
a campaign spec) in **one** batched rollout of B = C n runs, candidate-major (run i belongs to candidate
i // n). The gains are pytree leaves with a leading run axis, so every round calls the same compiled chunk
function (same shapes every round; the manifest records that no new compilation happened after round 1).

Search methods (``tune.method``):

* ``grid``: ``grid.points`` log-spaced multipliers per tuned leaf, their full product, C per round (the last
  round padded with copies of the start, not scored); ``tune.rounds`` is not used.
* ``random``: log-uniform in every leaf's range.
* ``cem`` (cross-entropy method): a diagonal Gaussian over x, started at the start point with std
  ``cem.init_std`` [ln units]; after each round its mean and std move (``cem.smoothing``) to those of the
  round's elite (the best ``cem.elite_frac`` C by the ranking below); slot 0 of every round after the first
  re-evaluates the best candidate so far (the carried elite), so a round's best never ranks below the
  previous round's (the rollout is deterministic).

Round 0 slot 0 is always the start, so the start is scored on the same footing as every candidate.

**Objective** (``[objective]``), per candidate over its successful runs (cells x reps):

    J = w_R mean(R / atan(mu)^2) + w_S mean(S / s_ref) - w_T mean(T) [mm]

R / atan(mu)^2 is R as a fraction of its maximum (a cube at rest on a level tray: every contact force on
its normal, see ``wbc_jax.sim.metrics``), in [0, 1] for every friction level, so cells of low and high mu
weigh alike. S has no natural maximum; S / s_ref (s_ref [s^2/m], default 3, about the default gains'
S on the quick course) puts it on the same O(1) scale. Defaults: w_R = w_S = 1, w_T = 0.
**Constraints**: success rate >= ``min_success`` (default 1: every run succeeds) and mean T <= ``t_max_mm``
(0: no bound). violation = (min_success - success rate)+ + ((T - t_max) / t_max)+ (the T term is 1 when no run
succeeded). **Ranking**: feasible candidates (violation 0) first, by J descending; then infeasible ones by
violation ascending (ties by J). The Pareto front of (R / atan(mu)^2 max, S max, T min) is taken over the
feasible candidates.

Outputs (DIR, written atomically): ``leaderboard.csv`` (one row per candidate evaluated: round, slot, kind,
multipliers ``<leaf>_x`` and values ``<leaf>`` (first component) of the tuned leaves, R, R_norm, S, S_norm,
T_mm, success_rate, objective, violation, feasible, rank, pareto), ``best_gains.toml`` (all leaves, for
``wbc-jax campaign --gains``; :mod:`wbc_jax.study.gains`), ``best_runs.csv`` (per run metrics of the start and the
best candidate), ``objective_per_round.png``, ``pareto.png`` and ``manifest.json`` (versions, device, spec
hash, seeds, wall time, candidates/s, compilations).

Spec (``sweeps/gain_tuning.toml``)::

    [tune]
    name = "gain-tuning"        # free text
    campaign = "quick.toml"     # campaign spec (path relative to this file): scene, course, timing, factors,
                                # perturbations, ADMM iterations
    method = "cem"              # "grid", "random" or "cem"
    candidates = 16             # C, candidates per round (cem: >= 2), 1..1000000
    rounds = 5                  # 1..10000 (grid: computed from the grid)
    seed = 0                    # search seed, 0 <= seed < 2**32
    reps = 1                    # repetitions per cell (replaces the campaign's reps), 1..1000
    cells = "all"               # "all" or a list of [m, mu, d] cells of the campaign's levels
    max_seconds = 0.0           # cap on simulated time per run [s] (0: the campaign's), 0..600
    qp_iters = 0                # ADMM iterations per control step, static (0: the campaign's), 0..1000

    [start]                     # start = default gains x these scales (0 < scale <= 1e4)
    kp = 0.2                    # every kp_* leaf; "kd" every kd_* leaf; a leaf name overrides its group

    [leaves]                    # tuned leaves: [lo, hi] multiplier of the default value, 0 < lo < hi <= 1e4
    kp_com = [0.1, 4.0]         # (the start scale must lie in the range)

    [objective]                 # w_R, w_S (0..100), w_T [1/mm] (0..100), s_ref [s^2/m] (> 0),
                                # min_success (0..1), t_max_mm [mm] (0..1000, 0 = no bound)
    [cem]                       # elite_frac (0 < . <= 1), init_std, min_std [ln units] (0..5), smoothing (0 < . <= 1)
    [grid]                      # points per leaf, 2..100 (grid size <= 1e6)
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import os
import platform
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wbc_jax.control.transport import TransportGains, default_gains
from wbc_jax.errors import SpecError
from wbc_jax.study.spec import SWEEPS, Spec, _err, _number, _table, load_spec, parse_spec

LEAVES = TransportGains._fields
GROUPS = {"kp": tuple(f for f in LEAVES if f.startswith("kp_")), "kd": tuple(f for f in LEAVES if f.startswith("kd_"))}
METHODS = ("grid", "random", "cem")
MULT_MAX = 1e4  # largest multiplier of a default gain (start scale or range end)
GRID_MAX = 1_000_000  # largest grid (points ** tuned leaves)
DEFAULT_SPEC = SWEEPS / "gain_tuning.toml"

# key: (type, default, lo, hi, lo_open, unit/description), as in wbc_jax.study.spec
_TUNE = {
    "name": (str, "gain-tuning", None, None, False, "text"),
    "campaign": (str, "quick.toml", None, None, False, "campaign spec path, relative to this file"),
    "method": (str, "cem", None, None, False, '"grid", "random" or "cem"'),
    "candidates": (int, 16, 1, 1_000_000, False, "candidates per round"),
    "rounds": (int, 5, 1, 10_000, False, "rounds"),
    "seed": (int, 0, 0, 2**32 - 1, False, "search seed"),
    "reps": (int, 1, 1, 1000, False, "repetitions per cell"),
    "max_seconds": (float, 0.0, 0.0, 600.0, False, "[s], 0 = the campaign's"),
    "qp_iters": (int, 0, 0, 1000, False, "ADMM iterations, 0 = the campaign's"),
}
_OBJECTIVE = {
    "w_R": (float, 1.0, 0.0, 100.0, False, "weight of mean R / atan(mu)^2"),
    "w_S": (float, 1.0, 0.0, 100.0, False, "weight of mean S / s_ref"),
    "w_T": (float, 0.0, 0.0, 100.0, False, "[1/mm] weight of -mean T"),
    "s_ref": (float, 3.0, 0.0, 1e6, True, "[s^2/m]"),
    "min_success": (float, 1.0, 0.0, 1.0, False, "fraction of runs"),
    "t_max_mm": (float, 2.0, 0.0, 1000.0, False, "[mm], 0 = no bound"),
}
_CEM = {
    "elite_frac": (float, 0.25, 0.0, 1.0, True, "fraction of the candidates"),
    "init_std": (float, 0.5, 0.0, 5.0, True, "[ln units]"),
    "min_std": (float, 0.05, 0.0, 5.0, False, "[ln units]"),
    "smoothing": (float, 0.7, 0.0, 1.0, True, "weight of the new elite statistics"),
}
_GRID = {"points": (int, 3, 2, 100, False, "points per tuned leaf")}


# ---------------------------------------------------------------- spec


@dataclass(frozen=True)
class TuneSpec:
    """A validated tuning spec (module docstring). ``campaign`` is the referenced campaign spec with this
    spec's reps / max_seconds / qp_iters applied; ``cells`` None means all; ``start`` holds every leaf's
    start multiplier; ``leaves`` the tuned leaves' multiplier ranges (lo, hi) in file order."""

    path: str
    tune: dict
    cells: list | None
    start: dict
    leaves: dict
    objective: dict
    cem: dict
    grid: dict
    campaign: Spec
    text_sha256: str = ""

    def canonical(self) -> dict:
        return dict(tune=self.tune, cells=self.cells, start=self.start,
                    leaves={k: list(v) for k, v in self.leaves.items()},
                    objective=self.objective, cem=self.cem, grid=self.grid, campaign=self.campaign.canonical())

    @property
    def hash(self) -> str:
        """sha256 of the validated content (defaults filled in, the campaign spec included as in its own hash)."""
        return hashlib.sha256(json.dumps(dict(self.canonical(), campaign=self.campaign.hashed()),
                                         sort_keys=True).encode()).hexdigest()

    def with_overrides(self, candidates: int | None = None, rounds: int | None = None) -> TuneSpec:
        t = dict(self.tune)
        for key, v in (("candidates", candidates), ("rounds", rounds)):
            if v is not None:
                typ, _, lo, hi, lo_open, unit = _TUNE[key]
                t[key] = _number(f"--{key}", "value", v, typ, lo, hi, lo_open, unit)
        out = dataclasses.replace(self, tune=t)
        _check_method(out)
        return out


def _check_method(s: TuneSpec) -> None:
    if s.tune["method"] == "cem" and s.tune["candidates"] < 2:
        raise _err(s.path, "tune.candidates", f"= {s.tune['candidates']}: the cross-entropy method needs >= 2")
    if s.tune["method"] == "grid" and s.grid["points"] ** len(s.leaves) > GRID_MAX:
        raise _err(s.path, "grid.points", f"= {s.grid['points']}: {s.grid['points']}^{len(s.leaves)} grid points, "
                                          f"more than {GRID_MAX}")


def _cells(path, raw, factors) -> list | None:
    if raw == "all":
        return None
    if not isinstance(raw, list) or not raw:
        raise _err(path, "tune.cells", f'expected "all" or a list of [m, mu, d] cells, got {raw!r}')
    out = []
    for i, c in enumerate(raw):
        key = f"tune.cells[{i}]"
        if not isinstance(c, list) or len(c) != 3:
            raise _err(path, key, f"expected [m, mu, d], got {c!r}")
        cell = [_number(path, key, v, float, 0.0, 1e3, False, "") for v in c]
        for name, v in zip(("m", "mu", "d"), cell):
            if not any(math.isclose(v, lv, rel_tol=1e-9, abs_tol=1e-12) for lv in factors[name]):
                raise _err(path, key, f"{name} = {v} is not a level of the campaign ({factors[name]})")
        if cell in out:
            raise _err(path, key, f"{cell} listed twice")
        out.append(cell)
    return out


def _start(path, raw) -> dict:
    if not isinstance(raw, dict):
        raise _err(path, "start", "expected a table [start]")
    scale = {k: 1.0 for k in LEAVES}
    for key in sorted(raw, key=lambda k: k not in GROUPS):  # groups first, then leaf overrides
        if key not in GROUPS and key not in LEAVES:
            raise _err(path, f"start.{key}", f"unknown key; expected kp, kd or a leaf ({', '.join(LEAVES)})")
        v = _number(path, f"start.{key}", raw[key], float, 0.0, MULT_MAX, True, "(multiplier of the default)")
        for leaf in GROUPS.get(key, (key,)):
            scale[leaf] = v
    return scale


def _leaves(path, raw) -> dict:
    if not isinstance(raw, dict) or not raw:
        raise _err(path, "leaves", "expected a table [leaves] with at least one tuned leaf = [lo, hi]")
    out = {}
    for key, v in raw.items():
        full = f"leaves.{key}"
        if key not in LEAVES:
            raise _err(path, full, f"unknown leaf; expected one of {', '.join(LEAVES)}")
        if not isinstance(v, list) or len(v) != 2:
            raise _err(path, full, f"expected [lo, hi] (multipliers of the default), got {v!r}")
        lo, hi = (_number(path, full, x, float, 0.0, MULT_MAX, True, "(multiplier)") for x in v)
        if not lo < hi:
            raise _err(path, full, f"= {v}: expected lo < hi")
        out[key] = (lo, hi)
    return out


def parse_tune_spec(data: dict, path: str = "<tune spec>", text_sha256: str = "") -> TuneSpec:
    """Validate a tuning-spec dict (as read by tomllib). Raises SpecError naming ``path`` and the key."""
    tables = ("tune", "start", "leaves", "objective", "cem", "grid")
    unknown = sorted(set(data) - set(tables))
    if unknown:
        raise _err(path, unknown[0], f"unknown table; expected {', '.join(tables)}")
    raw_t = data.get("tune", {})
    if not isinstance(raw_t, dict):
        raise _err(path, "tune", "expected a table [tune]")
    raw_t = dict(raw_t)
    raw_cells = raw_t.pop("cells", "all")
    tune = _table(path, "tune", raw_t, _TUNE)
    if tune["method"] not in METHODS:
        raise _err(path, "tune.method", f"= {tune['method']!r}: expected one of {', '.join(METHODS)}")
    cpath = Path(tune["campaign"])
    if not cpath.is_absolute():
        cpath = Path(path).parent / cpath
    camp = load_spec(cpath)  # its own errors name its file
    c = dict(camp.campaign, reps=tune["reps"])
    if tune["max_seconds"] > 0:
        c["max_seconds"] = tune["max_seconds"]
    if tune["qp_iters"] > 0:
        c["qp_iters"] = tune["qp_iters"]
    camp = parse_spec(dict(campaign=c, factors=camp.factors, perturbations=camp.perturbations), str(cpath),
                      camp.text_sha256)
    leaves = _leaves(path, data.get("leaves"))
    start = _start(path, data.get("start", {}))
    for leaf, (lo, hi) in leaves.items():
        if not lo <= start[leaf] <= hi:
            raise _err(path, f"leaves.{leaf}", f"= [{lo}, {hi}] does not contain the start scale {start[leaf]}")
    s = TuneSpec(path=str(path), tune=tune, cells=_cells(path, raw_cells, camp.factors), start=start, leaves=leaves,
                 objective=_table(path, "objective", data.get("objective", {}), _OBJECTIVE),
                 cem=_table(path, "cem", data.get("cem", {}), _CEM),
                 grid=_table(path, "grid", data.get("grid", {}), _GRID),
                 campaign=camp, text_sha256=text_sha256)
    if s.cem["min_std"] > s.cem["init_std"]:
        raise _err(path, "cem.min_std", f"= {s.cem['min_std']}: expected <= cem.init_std ({s.cem['init_std']})")
    _check_method(s)
    return s


def load_tune_spec(path: str | Path) -> TuneSpec:
    """Read and validate a tuning spec. Raises SpecError (one line: file, key, expected) on any problem."""
    try:
        raw = Path(path).read_bytes()
        data = tomllib.loads(raw.decode("utf-8"))
    except OSError as e:
        raise SpecError(f"{path}: cannot read spec file ({e.strerror or e})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SpecError(f"{path}: not valid TOML ({str(e).splitlines()[0]})") from None
    return parse_tune_spec(data, str(path), hashlib.sha256(raw).hexdigest())


# ---------------------------------------------------------------- search space


class Space:
    """Tuned leaves' ln-multiplier box and the map from points to batched gains.

    Attributes:
        names: (k,) tuned leaves; lo, hi: (k,) ln of their multiplier ranges; x0: (k,) ln of the start
        multipliers; base: default gains (unbatched); start: every leaf's start multiplier.
    """

    def __init__(self, spec: TuneSpec):
        self.names = tuple(spec.leaves)
        self.lo = np.log([spec.leaves[n][0] for n in self.names])
        self.hi = np.log([spec.leaves[n][1] for n in self.names])
        self.x0 = np.log([spec.start[n] for n in self.names])
        self.base = default_gains()
        self.start = dict(spec.start)

    @property
    def k(self) -> int:
        return len(self.names)

    def multipliers(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """x (C, k) -> every leaf's multiplier, (C,) each."""
        x = np.atleast_2d(x)
        mult = {leaf: np.full(x.shape[0], s) for leaf, s in self.start.items()}
        for j, n in enumerate(self.names):
            mult[n] = np.exp(x[:, j])
        return mult

    def gains(self, x: np.ndarray) -> TransportGains:
        """x (C, k) -> TransportGains with leading axis C (host numpy, the default gains' dtypes)."""
        mult = self.multipliers(x)
        out = {}
        for name, v in zip(self.base._fields, self.base):
            v = np.asarray(v)
            out[name] = (v[None] * mult[name].reshape((-1,) + (1,) * v.ndim)).astype(v.dtype)
        return TransportGains(**out)


def rank_key(feasible: bool, violation: float, objective: float) -> tuple:
    """Sort key, larger is better: feasible first, then smaller violation, then larger objective."""
    return (bool(feasible), -float(violation), float(objective) if np.isfinite(objective) else -math.inf)


class Search:
    """Base class: ``ask(r)`` -> (x (C, k), kinds (C,)), ``tell(x, keys)`` after scoring."""

    rounds: int

    def __init__(self, space: Space, C: int, rounds: int, rng: np.random.Generator):
        self.space, self.C, self.rounds, self.rng = space, C, rounds, rng

    def tell(self, x, keys) -> None:
        pass


class RandomSearch(Search):
    def ask(self, r):
        s = self.space
        x = s.lo + (s.hi - s.lo) * self.rng.random((self.C, s.k))
        kinds = ["sample"] * self.C
        if r == 0:
            x[0], kinds[0] = s.x0, "start"
        return x, kinds


class GridSearch(Search):
    def __init__(self, space, C, rounds, rng, points: int):
        axes = [np.linspace(a, b, points) for a, b in zip(space.lo, space.hi)]
        self.points = np.concatenate([space.x0[None], np.array(list(itertools.product(*axes)))])
        super().__init__(space, C, -(-len(self.points) // C), rng)

    def ask(self, r):
        x = self.points[r * self.C:(r + 1) * self.C]
        kinds = ["start" if r == 0 and i == 0 else "grid" for i in range(len(x))]
        pad = self.C - len(x)
        return np.concatenate([x, np.repeat(self.space.x0[None], pad, 0)]), kinds + ["padding"] * pad


class CEMSearch(Search):
    """Cross-entropy method with a diagonal Gaussian over x, smoothed updates and the best carried."""

    def __init__(self, space, C, rounds, rng, elite_frac, init_std, min_std, smoothing):
        super().__init__(space, C, rounds, rng)
        self.mean = space.x0.copy()
        self.std = np.full(space.k, init_std)
        self.n_elite = min(C, max(2, int(round(elite_frac * C))))
        self.min_std, self.alpha = min_std, smoothing
        self.best_x, self.best_key = None, None
        self.history = []  # (round, mean, std) after each update

    def ask(self, r):
        s = self.space
        x = np.clip(self.mean + self.std * self.rng.standard_normal((self.C, s.k)), s.lo, s.hi)
        kinds = ["sample"] * self.C
        if r == 0:
            x[0], kinds[0] = s.x0, "start"
        else:
            x[0], kinds[0] = self.best_x, "elite"
        return x, kinds

    def tell(self, x, keys):
        order = sorted(range(len(keys)), key=lambda i: keys[i], reverse=True)
        elite = x[order[:self.n_elite]]
        a = self.alpha
        self.mean = a * elite.mean(0) + (1 - a) * self.mean
        self.std = np.maximum(self.min_std, a * elite.std(0) + (1 - a) * self.std)
        if self.best_key is None or keys[order[0]] >= self.best_key:
            self.best_x, self.best_key = x[order[0]].copy(), keys[order[0]]
        self.history.append(dict(mean=self.mean.tolist(), std=self.std.tolist()))


def make_search(spec: TuneSpec, space: Space) -> Search:
    t = spec.tune
    rng = np.random.default_rng(t["seed"])
    if t["method"] == "grid":
        return GridSearch(space, t["candidates"], t["rounds"], rng, spec.grid["points"])
    if t["method"] == "random":
        return RandomSearch(space, t["candidates"], t["rounds"], rng)
    return CEMSearch(space, t["candidates"], t["rounds"], rng, **spec.cem)


# ---------------------------------------------------------------- batched evaluation


def _take(tree, idx, in_axes=0):
    """Rows ``idx`` of every batched leaf (``in_axes`` 0) of ``tree``; unbatched leaves (None) unchanged."""
    import jax

    leaves, treedef = jax.tree_util.tree_flatten(tree)
    axes = [in_axes] * len(leaves) if isinstance(in_axes, int) else treedef.flatten_up_to(in_axes)
    return jax.tree_util.tree_unflatten(treedef, [x if a is None else x[idx] for x, a in zip(leaves, axes)])


class Evaluator:
    """One batched rollout of C candidates x n runs (the chosen cells x reps), compiled once, called every round.

    Attributes:
        C, n: candidates and runs per candidate; B = C n runs, candidate-major.
        m, mu, d, rep: (n,) the factor values and repetition of each run of a candidate.
        seconds: simulated time per run [s]; n_chunks: jit calls per round; fn: the compiled chunk function.
    """

    def __init__(self, spec: TuneSpec, C: int):
        import jax
        import jax.numpy as jnp

        from wbc_jax.study import campaign

        sim, dz, b, _, logs_per_chunk, n_chunks = campaign.build(spec.campaign)
        if spec.cells is None:
            sel = np.arange(dz.n)
        else:
            cells = np.asarray(spec.cells)
            have = np.stack([dz.m, dz.mu, dz.d], axis=1)
            sel = np.where(np.isclose(have[:, None, :], cells[None]).all(-1).any(-1))[0]
        self.C, self.n, self.sim, self.n_chunks = C, len(sel), sim, n_chunks
        self.m, self.mu, self.d, self.rep = dz.m[sel], dz.mu[sel], dz.d[sel], dz.rep[sel]
        self.seeds = dz.seed[sel]
        self.seconds = n_chunks * logs_per_chunk * campaign.LOG_EVERY * sim.dt_control
        idx = jnp.asarray(np.tile(sel, C))  # (B,) run i of the batch = run sel[i % n] of the campaign's design
        self.batch = b._replace(model=_take(b.model, idx, b.in_axes), state=_take(b.state, idx),
                                plan=_take(b.plan, idx), om=_take(b.om, idx), gains=_take(b.gains, idx),
                                push=_take(b.push, idx), mu_ground=_take(b.mu_ground, idx))
        self.mesh = None
        if jax.device_count() > 1:  # spread the runs over all devices (wbc_jax.sim.sharding)
            from wbc_jax.sim.sharding import run_mesh, shard_batch

            self.mesh = run_mesh()
            self.batch, _ = shard_batch(self.batch, self.mesh)
        self.fn = campaign._chunk_fn(sim, b.in_axes, logs_per_chunk)

    @property
    def B(self) -> int:
        return self.C * self.n

    def per_run(self, gains: TransportGains) -> TransportGains:
        """Candidate gains (leading axis C) -> per-run gains (leading axis B), placed like the batch."""
        import jax
        import jax.numpy as jnp

        g = jax.tree_util.tree_map(lambda x: jnp.repeat(jnp.asarray(x), self.n, axis=0), gains)
        if self.mesh is not None:
            from wbc_jax.sim.sharding import shard_runs

            g = shard_runs(g, self.mesh)
        return g

    def compiled_variants(self) -> int | None:
        """Number of compiled variants of the chunk function so far (None if this JAX does not say)."""
        size = getattr(self.fn, "_cache_size", None)
        return int(size()) if callable(size) else None

    def __call__(self, gains: TransportGains, bar=None) -> dict[str, np.ndarray]:
        """Roll out every candidate's runs from the initial state. gains: leading axis C.

        Returns ``wbc_jax.sim.metrics.finalize``'s per-run dict, every array reshaped to (C, n).
        """
        import jax

        from wbc_jax.sim.rollout import final_results

        b, B = self.batch, self.B
        g = self.per_run(gains)
        state, logs = b.state, None
        for _ in range(self.n_chunks):
            state, logs = self.fn(b.model, state, b.plan, b.om, g, b.push, b.mu_ground)
            if bar is not None:
                jax.block_until_ready(state)
                bar.update(1)
        res = final_results(self.sim, state, logs.p_obj_ref[:, -1], np.tile(self.mu, self.C), n=B)
        return {k: np.asarray(v).reshape(self.C, self.n) for k, v in res.items()}


def score(res: dict, mu: np.ndarray, obj: dict) -> dict[str, np.ndarray]:
    """Per-candidate aggregates (module docstring) from per-run results ``res`` (each (C, n)) and the runs'
    friction ``mu`` (n,). Returns (C,) arrays: success_rate, R, R_norm, S, S_norm, T_mm (means over the
    successful runs, NaN when none), objective, violation, feasible."""
    ok = res["success"].astype(bool)
    n_ok = ok.sum(1)

    def mean_ok(v):
        v = np.where(ok, np.asarray(v, float), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n_ok > 0, v.sum(1) / np.maximum(n_ok, 1), np.nan)

    R, S, T_mm = mean_ok(res["R"]), mean_ok(res["S"]), mean_ok(res["T"] * 1e3)
    R_norm = mean_ok(res["R"] / np.arctan(mu)[None] ** 2)
    S_norm = S / obj["s_ref"]
    objective = obj["w_R"] * R_norm + obj["w_S"] * S_norm - obj["w_T"] * T_mm
    rate = ok.mean(1)
    viol = np.maximum(0.0, obj["min_success"] - rate)
    if obj["t_max_mm"] > 0:
        viol = viol + np.where(n_ok > 0, np.maximum(0.0, T_mm - obj["t_max_mm"]) / obj["t_max_mm"], 1.0)
    viol = np.where(n_ok > 0, viol, np.maximum(viol, 1.0))  # no successful run is never feasible
    return dict(success_rate=rate, R=R, R_norm=R_norm, S=S, S_norm=S_norm, T_mm=T_mm, objective=objective,
                violation=viol, feasible=viol <= 0.0)


def pareto_mask(points: np.ndarray) -> np.ndarray:
    """Non-dominated rows of ``points`` (N, q), every column to be maximised (rows with NaN: never)."""
    p = np.asarray(points, float)
    good = np.all(np.isfinite(p), axis=1)
    mask = good.copy()
    for i in np.where(good)[0]:
        dom = good & np.all(p >= p[i], axis=1) & np.any(p > p[i], axis=1)
        mask[i] = not dom.any()
    return mask


# ---------------------------------------------------------------- outputs


def _figures(df, best_idx: int) -> dict[str, bytes]:
    from matplotlib.figure import Figure

    from wbc_jax.analysis.figures import _png

    out = {}
    fig = Figure(figsize=(6.4, 4.0), layout="constrained")
    ax = fig.subplots()
    feas = df.feasible.to_numpy(bool)
    jit = (np.random.default_rng(0).random(len(df)) - 0.5) * 0.25
    ax.scatter(df["round"][~feas] + jit[~feas], df.objective[~feas], s=10, c="0.7", marker="x", label="infeasible")
    ax.scatter(df["round"][feas] + jit[feas], df.objective[feas], s=12, c="tab:blue", label="feasible")
    rounds = np.sort(df["round"].unique())
    top = [df[df["round"] == r].sort_values("rank").iloc[0] for r in rounds]  # each round's best by rank
    so_far = [df[df["round"] <= r].sort_values("rank").iloc[0] for r in rounds]
    ax.plot(rounds, [t.objective for t in top], "-", c="tab:red", lw=1.5, label="round best (filled: feasible)")
    ax.scatter(rounds, [t.objective for t in top], s=30, c=["tab:red" if t.feasible else "white" for t in top],
               edgecolors="tab:red", zorder=3)
    ax.plot(rounds, [t.objective for t in so_far], "--", c="k", lw=1, label="best so far (by rank)")
    ax.set_xticks(rounds)
    st = df.iloc[0]
    ax.axhline(st.objective, c="tab:orange", lw=1, ls=":",
               label=f"start ({'feasible' if st.feasible else 'infeasible'})")
    ax.set_xlabel("round")
    ax.set_ylabel("objective J")
    ax.set_title("objective per round")
    ax.legend(fontsize=7)
    out["objective_per_round.png"] = _png(fig)

    fig = Figure(figsize=(6.4, 4.6), layout="constrained")
    ax = fig.subplots()
    ax.scatter(df.R_norm[~feas], df.S[~feas], s=8, c="0.8", marker="x", label="infeasible")
    if feas.any():
        sc = ax.scatter(df.R_norm[feas], df.S[feas], s=14, c=df.T_mm[feas], cmap="viridis", label="feasible")
        fig.colorbar(sc, ax=ax, label="mean T [mm]")
        front = df[df.pareto.to_numpy(bool)].sort_values("R_norm")
        ax.plot(front.R_norm, front.S, "o", mfc="none", mec="tab:red", ms=8, label="Pareto front (R, S, T)")
        b = df.iloc[best_idx]
        ax.plot([b.R_norm], [b.S], "*", c="tab:red", ms=14, label="best J")
    ax.plot([st.R_norm], [st.S], "s", mfc="none", mec="tab:orange", ms=9, label="start")
    ax.set_xlabel("mean R / atan(mu)^2")
    ax.set_ylabel("mean S [s^2/m]")
    ax.set_title("candidates: robustness vs smoothness (colour: tracking T)")
    ax.legend(fontsize=7)
    out["pareto.png"] = _png(fig)
    return out


def _rows(r: int, x: np.ndarray, kinds: list, space: Space, sc: dict) -> list[dict]:
    """Leaderboard rows of round r (0-based) for the scored candidates (padding left out)."""
    mult = space.multipliers(x)
    base = space.base._asdict()
    rows = []
    for i, kind in enumerate(kinds):
        if kind == "padding":
            continue
        row = dict(round=r + 1, slot=i, kind=kind)
        for n in space.names:
            row[f"{n}_x"] = float(mult[n][i])
            row[n] = float(np.ravel(base[n])[0] * mult[n][i])
        row.update({k: (bool(v[i]) if k == "feasible" else float(v[i])) for k, v in sc.items()})
        rows.append(row)
    return rows


def _key(row: dict) -> tuple:
    return rank_key(row["feasible"], row["violation"], row["objective"])


def _leaderboard(rows: list[dict]):
    """DataFrame of all rows with ``rank`` (1 = best) and ``pareto`` (front of (R_norm, S, -T) over the feasible)."""
    import pandas as pd

    df = pd.DataFrame(rows)
    order = sorted(range(len(rows)), key=lambda i: _key(rows[i]), reverse=True)
    df["rank"] = 0
    df.loc[order, "rank"] = np.arange(1, len(rows) + 1)
    feas = df.feasible.to_numpy(bool)
    pm = np.zeros(len(df), bool)
    if feas.any():
        pm[feas] = pareto_mask(np.stack([df.R_norm[feas], df.S[feas], -df.T_mm[feas]], axis=1))
    df["pareto"] = pm
    return df


def _runs_table(ev: Evaluator, per_run: dict):
    """Per-run metrics of the start and the best candidate (``best_runs.csv``)."""
    import pandas as pd

    return pd.concat([pd.DataFrame(dict(
        candidate=who, m=ev.m, mu=ev.mu, d=ev.d, rep=ev.rep, seed=ev.seeds, success=v["success"], R=v["R"],
        R_norm=v["R"] / np.arctan(ev.mu) ** 2, S=v["S"], T_mm=v["T"] * 1e3, max_slip_mm=v["max_slip_mm"],
        fell=v["fell"], dropped=v["dropped"], final_err_mm=v["final_err_mm"])) for who, v in per_run.items()])


def _round_line(r: int, R: int, wall: float, sc: dict, keys: list, best: dict) -> str:
    C = len(keys)
    i = max(range(C), key=lambda j: keys[j])
    viol = "" if sc["feasible"][i] else f", violation {sc['violation'][i]:.3g}"
    return (f"round {r + 1}/{R}: {wall:.1f} s ({C / wall:.2f} candidates/s), feasible {int(sc['feasible'].sum())}/{C}; "
            f"round best J {sc['objective'][i]:.4f} (success {sc['success_rate'][i]:.0%}, "
            f"T {sc['T_mm'][i]:.2f} mm{viol}); "
            f"best so far J {best['objective']:.4f} ({'feasible' if best['feasible'] else 'infeasible'})")


SUMMARY = ("round", "slot", "kind", "objective", "R", "R_norm", "S", "S_norm", "T_mm", "success_rate", "violation",
           "feasible")


def run_tune(spec_path: str | None, out: str, candidates: int | None = None, rounds: int | None = None,
             progress: bool = True, force: bool = False) -> dict:
    """Run a gain search and write DIR (module docstring). Returns the manifest.

    Args:
        spec_path: tuning spec (None: ``sweeps/gain_tuning.toml``); out: output directory (replaced atomically).
        candidates, rounds: override the spec's ``tune.candidates`` / ``tune.rounds``.
        progress: show a progress bar per round (stderr).
    """
    import jax

    from wbc_jax.study import campaign
    from wbc_jax.study.gains import gains_toml
    from wbc_jax.io_utils import atomic_dir, check_out_dir, write_json_atomic

    t_start = time.perf_counter()
    spec = load_tune_spec(spec_path if spec_path is not None else DEFAULT_SPEC).with_overrides(candidates, rounds)
    check_out_dir(out, "wbc-jax tune", force=force, inputs=[spec.path])  # force: replace an earlier tune's DIR
    space = Space(spec)
    search = make_search(spec, space)
    C, R, t = search.C, search.rounds, spec.tune
    ev = Evaluator(spec, C)
    steps = int(round(ev.seconds / ev.sim.dt_control)) * ev.sim.n_substeps  # physics (env-)steps per run and round
    print(f"tune {t['name']!r} ({spec.path}): {t['method']}, {R} rounds x {C} candidates, {space.k} tuned leaves; "
          f"each candidate on {ev.n} runs ({ev.n // t['reps']} cells x {t['reps']} reps of {spec.campaign.path}), "
          f"batch {ev.B} runs x {ev.seconds:.2f} s simulated, {spec.campaign.campaign['qp_iters']} ADMM iterations, "
          f"device {jax.devices()[0].device_kind}", flush=True)

    rows, walls, variants, per_run, best = [], [], [ev.compiled_variants()], {}, None
    for r in range(R):
        x, kinds = search.ask(r)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=ev.n_chunks, desc=f"round {r + 1}/{R}", unit="chunk", file=sys.stderr, leave=False)
        t0 = time.perf_counter()
        res = ev(space.gains(x), bar)  # per run, (C, n) each
        walls.append(time.perf_counter() - t0)
        if bar is not None:
            bar.close()
        variants.append(ev.compiled_variants())
        sc = score(res, ev.mu, spec.objective)
        keys = [rank_key(sc["feasible"][i], sc["violation"][i], sc["objective"][i]) for i in range(C)]
        search.tell(x, keys)
        new = _rows(r, x, kinds, space, sc)
        for row in new:
            i = row["slot"]
            if r == 0 and i == 0:
                per_run["start"] = {k: v[i] for k, v in res.items()}
            if best is None or keys[i] > _key(best[0]):
                best = (row, x[i].copy())
                per_run["best"] = {k: v[i] for k, v in res.items()}
        rows += new
        print(_round_line(r, R, walls[-1], sc, keys, best[0]), flush=True)

    df = _leaderboard(rows)
    start, top = rows[0], best[0]
    best_gains = jax.tree_util.tree_map(lambda v: v[0], space.gains(best[1][None]))
    round_s = float(np.median(walls[1:] if len(walls) > 1 else walls))  # rounds after the first do not compile
    new_compiles = (variants[-1] - variants[1]) if None not in (variants[1], variants[-1]) else None
    if new_compiles:
        print(f"warning: the chunk function compiled {new_compiles} more time(s) after round 1", flush=True)
    manifest = dict(
        command="wbc-jax tune", spec_path=spec.path, spec_hash=spec.hash, spec_file_sha256=spec.text_sha256,
        spec=spec.canonical(), campaign_spec_path=spec.campaign.path, method=t["method"], candidates_per_round=C,
        rounds=R, candidates_evaluated=len(rows), tuned_leaves=list(space.names), runs_per_candidate=ev.n,
        batch_runs=ev.B, cells=[[float(a), float(b), float(c)] for a, b, c in zip(ev.m, ev.mu, ev.d)][::t["reps"]],
        seeds=[int(s) for s in ev.seeds], search_seed=t["seed"], simulated_s=ev.seconds,
        control_dt_s=ev.sim.dt_control, versions=campaign._versions(), git_commit=campaign._git_commit(),
        device=dict(backend=jax.default_backend(), kind=jax.devices()[0].device_kind, count=jax.device_count(),
                    host=platform.node(), cpu_count=os.cpu_count()),
        round_wall_s=walls, first_round_s=walls[0], steady_round_s=round_s, candidates_per_s=C / round_s,
        env_steps_per_s=ev.B * steps / round_s, compiled_variants_per_round=variants,
        new_compilations_after_round_1=new_compiles,
        start={k: start[k] for k in SUMMARY}, best={k: top[k] for k in SUMMARY},
        best_multipliers={n: top[f"{n}_x"] for n in space.names},
        improvement={k: top[k] - start[k] for k in ("objective", "R", "R_norm", "S", "T_mm", "success_rate")},
        n_feasible=int(df.feasible.sum()), n_pareto=int(df.pareto.sum()), objective=spec.objective)
    if isinstance(search, CEMSearch):
        manifest["cem_history"] = search.history
    info = dict(source="wbc-jax tune", spec=spec.path, spec_hash=spec.hash, qp_iters=spec.campaign.campaign["qp_iters"],
                **{k: top[k] for k in ("round", "objective", "feasible", "R", "S", "T_mm", "success_rate")},
                **{f"{n}_x": top[f"{n}_x"] for n in space.names})
    with atomic_dir(Path(out).absolute()) as tmp:
        df.to_csv(tmp / "leaderboard.csv", index=False)
        _runs_table(ev, per_run).to_csv(tmp / "best_runs.csv", index=False)
        (tmp / "best_gains.toml").write_text(gains_toml(
            best_gains, f"wbc-jax tune: best gains of {spec.path} (rank 1 of {len(rows)} candidates)\n"
                        "use: wbc-jax campaign --gains best_gains.toml", info))
        for name, png in _figures(df, int(df["rank"].to_numpy().argmin())).items():
            (tmp / name).write_bytes(png)
        manifest["wall_s_total"] = time.perf_counter() - t_start
        write_json_atomic(tmp / "manifest.json", manifest)
    print(f"{len(rows)} candidates in {manifest['wall_s_total']:.1f} s; {C / round_s:.2f} candidates/s "
          f"({ev.B * steps / round_s:,.0f} env-steps/s) per round after the first; feasible {manifest['n_feasible']}, "
          f"Pareto front {manifest['n_pareto']}", flush=True)
    print(f"start: J {start['objective']:.4f}, success {start['success_rate']:.0%}, R {start['R']:.4f}, "
          f"T {start['T_mm']:.2f} mm; best (round {top['round']}): J {top['objective']:.4f}, success "
          f"{top['success_rate']:.0%}, R {top['R']:.4f}, T {top['T_mm']:.2f} mm; written to {out}", flush=True)
    return manifest
