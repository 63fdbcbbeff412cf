"""Tuning specs of ``wbc-jax tune`` (``sweeps/gain_tuning*.toml``): loading with stdlib ``tomllib``, validation.

Spec::

    [tune]
    name = "gain-tuning"        # free text
    campaign = "quick.toml"     # campaign spec (path relative to this file): scene, course, timing, factors,
                                # perturbations, ADMM iterations
    method = "cem"              # "grid", "random", "cem" or "halving" (successive halving)
    candidates = 16             # C, candidates per round (cem: >= 2; halving: per bracket), 1..1000000
    rounds = 5                  # 1..10000 (grid: computed from the grid; halving: brackets)
    seed = 0                    # search seed, 0 <= seed < 2**32
    reps = 1                    # repetitions per cell (replaces the campaign's reps), 1..1000
    cells = "all"               # "all" or a list of [m, mu, d] cells of the campaign's levels
    max_seconds = 0.0           # cap on simulated time per run [s] (0: the campaign's), 0..600
    qp_iters = 0                # ADMM iterations per control step, static (0: the campaign's), 0..1000
    batch = 0                   # runs per rollout call (0: all the round's runs on an accelerator, 1 on a CPU),
                                # 0..1000000; every call has this one shape (padded), so one compilation serves
                                # every round, rung and the confirmation

    [start]                     # start = default gains x these scales (0 < scale <= 1e4)
    kp = 0.2                    # every kp_* leaf; "kd" every kd_* leaf; a leaf name overrides its group

    [leaves]                    # tuned leaves: [lo, hi] multiplier of the default value, 0 < lo < hi <= 1e4
    kp_com = [0.1, 4.0]         # (the start scale must lie in the range)

    [objective]                 # w_R, w_S (0..100), w_T [1/mm] (0..100), s_ref [s^2/m] (> 0),
                                # min_success (0..1), t_max_mm [mm] (0..1000, 0 = no bound)
    [cem]                       # elite_frac (0 < . <= 1), init_std, min_std [ln units] (0..5), smoothing (0 < . <= 1)
    [grid]                      # points per leaf, 2..100 (grid size <= 1e6)
    [halving]                   # eta: keep 1/eta per rung (2..10), rungs (1..10): horizons full / eta^(rungs-1-r)
    [confirm]                   # after the search: the top candidates and the default gains on another campaign
    campaign = ""               # campaign spec (relative to this file; "" = no confirmation)
    top = 3                     # candidates confirmed (1..100), best first by the search's ranking
    reps = 0                    # repetitions per cell (0: the campaign's), 0..1000
    alpha = 0.01                # significance level of the paired tests in report.md, 0 < alpha < 1
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from wbc_jax.campaign.spec import SWEEPS, Spec, checked_number, checked_table, load_spec, parse_spec, spec_error
from wbc_jax.control.transport import TransportGains
from wbc_jax.errors import SpecError

LEAVES = TransportGains._fields
GROUPS = {"kp": tuple(f for f in LEAVES if f.startswith("kp_")), "kd": tuple(f for f in LEAVES if f.startswith("kd_"))}
METHODS = ("grid", "random", "cem", "halving")
MULT_MAX = 1e4  # largest multiplier of a default gain (start scale or range end)
GRID_MAX = 1_000_000  # largest grid (points ** tuned leaves)
# Runs per rollout call on a CPU when tune.batch = 0: one, so that every batched LAPACK kernel (Cholesky, triangular
# solve) runs inline on its own thread; larger batches split over XLA's intra-op thread pool, where two such kernels
# can wait for each other forever (docs/cluster.md, the CPU-device deadlock).
CPU_BATCH = 1
GPU_SPEC = SWEEPS / "gain_tuning_course.toml"
CPU_SPEC = SWEEPS / "gain_tuning_cpu.toml"

# key: (type, default, lo, hi, lo_open, unit/description), as in wbc_jax.campaign.spec
_TUNE = {
    "name": (str, "gain-tuning", None, None, False, "text"),
    "campaign": (str, "quick.toml", None, None, False, "campaign spec path, relative to this file"),
    "method": (str, "cem", None, None, False, '"grid", "random", "cem" or "halving"'),
    "candidates": (int, 16, 1, 1_000_000, False, "candidates per round"),
    "rounds": (int, 5, 1, 10_000, False, "rounds"),
    "seed": (int, 0, 0, 2**32 - 1, False, "search seed"),
    "reps": (int, 1, 1, 1000, False, "repetitions per cell"),
    "max_seconds": (float, 0.0, 0.0, 600.0, False, "[s], 0 = the campaign's"),
    "qp_iters": (int, 0, 0, 1000, False, "ADMM iterations, 0 = the campaign's"),
    "batch": (int, 0, 0, 1_000_000, False, "runs per rollout call, 0 = automatic"),
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
_HALVING = {"eta": (int, 3, 2, 10, False, "reduction factor"), "rungs": (int, 3, 1, 10, False, "rungs per bracket")}
_CONFIRM = {
    "campaign": (str, "", None, None, False, 'campaign spec path, relative to this file ("" = none)'),
    "top": (int, 3, 1, 100, False, "candidates confirmed"),
    "reps": (int, 0, 0, 1000, False, "repetitions per cell, 0 = the campaign's"),
    "alpha": (float, 0.01, 0.0, 1.0, True, "significance level"),
}


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
    halving: dict = dataclasses.field(default_factory=lambda: checked_table("", "halving", {}, _HALVING))
    confirm: dict = dataclasses.field(default_factory=lambda: checked_table("", "confirm", {}, _CONFIRM))
    confirm_campaign: Spec | None = None
    text_sha256: str = ""

    def canonical(self) -> dict:
        return dict(tune=self.tune, cells=self.cells, start=self.start,
                    leaves={k: list(v) for k, v in self.leaves.items()},
                    objective=self.objective, cem=self.cem, grid=self.grid, halving=self.halving,
                    confirm=self.confirm, campaign=self.campaign.canonical(),
                    confirm_campaign=self.confirm_campaign.canonical() if self.confirm_campaign else None)

    @property
    def hash(self) -> str:
        """sha256 of the validated content (defaults filled in, the campaign spec included as in its own hash)."""
        cc = self.confirm_campaign.hashed() if self.confirm_campaign else None
        return hashlib.sha256(json.dumps(dict(self.canonical(), campaign=self.campaign.hashed(), confirm_campaign=cc),
                                         sort_keys=True).encode()).hexdigest()

    def with_overrides(self, candidates: int | None = None, rounds: int | None = None,
                       batch: int | None = None) -> TuneSpec:
        """This spec with ``tune.candidates`` / ``tune.rounds`` / ``tune.batch`` replaced (command-line flags)."""
        t = dict(self.tune)
        for key, v in (("candidates", candidates), ("rounds", rounds), ("batch", batch)):
            if v is not None:
                typ, _, lo, hi, lo_open, unit = _TUNE[key]
                t[key] = checked_number(f"--{key}", "value", v, typ, lo, hi, lo_open, unit)
        out = dataclasses.replace(self, tune=t)
        _check_method(out)
        return out


def _check_method(s: TuneSpec) -> None:
    if s.tune["method"] == "cem" and s.tune["candidates"] < 2:
        raise spec_error(s.path, "tune.candidates", f"= {s.tune['candidates']}: the cross-entropy method needs >= 2")
    if s.tune["method"] == "grid" and s.grid["points"] ** len(s.leaves) > GRID_MAX:
        raise spec_error(s.path, "grid.points", f"= {s.grid['points']}: {s.grid['points']}^{len(s.leaves)} grid "
                                                f"points, more than {GRID_MAX}")


def _campaign(path, rel: str, reps: int = 0, max_seconds: float = 0.0, qp_iters: int = 0) -> Spec:
    """The campaign spec ``rel`` (relative to the tuning spec ``path``) with reps / max_seconds / qp_iters
    replaced where > 0. Its own errors name its file."""
    cpath = Path(rel)
    if not cpath.is_absolute():
        cpath = Path(path).parent / cpath
    if not cpath.is_file():
        raise SpecError(f"{path}: campaign spec {rel!r}: no file {cpath} (a relative path is read from the tuning "
                        f"spec's folder; the shipped campaign specs are in {SWEEPS})")
    camp = load_spec(cpath)
    if camp.campaign["controller"] != "transport":  # the search space is the transport controller's gains
        raise SpecError(f"{path}: campaign spec {rel!r}: campaign.controller {camp.campaign['controller']!r}; "
                        "tune searches the transport controller's gains (controller = \"transport\")")
    if camp.plugin:  # tune's programs and confirmation campaign are the built-in controller's
        raise SpecError(f"{path}: campaign spec {rel!r}: plugin.class {camp.plugin['class']!r}: tune searches the "
                        "built-in transport controller's gains; leave out [plugin]")
    c = dict(camp.campaign)
    for key, v in (("reps", reps), ("max_seconds", max_seconds), ("qp_iters", qp_iters)):
        if v > 0:
            c[key] = v
    return parse_spec(dict(campaign=c, factors=camp.factors, perturbations=camp.perturbations), str(cpath),
                      camp.text_sha256)


def default_tune_spec_path(accelerator: bool) -> Path:
    """The course spec (``sweeps/gain_tuning_course.toml``) when an accelerator is present, else the CPU-sized one."""
    return GPU_SPEC if accelerator else CPU_SPEC


def _cells(path, raw, camp) -> list | None:
    """``tune.cells`` validated against the campaign spec ``camp``: each [m, mu, d] a level of that factor, or
    the campaign's fixed value where it is not a factor."""
    if raw == "all":
        return None
    if not isinstance(raw, list) or not raw:
        raise spec_error(path, "tune.cells", f'expected "all" or a list of [m, mu, d] cells, got {raw!r}')
    out = []
    for i, c in enumerate(raw):
        key = f"tune.cells[{i}]"
        if not isinstance(c, list) or len(c) != 3:
            raise spec_error(path, key, f"expected [m, mu, d], got {c!r}")
        cell = [checked_number(path, key, v, float, 0.0, 1e3, False, "") for v in c]
        for name, v in zip(("m", "mu", "d"), cell):
            levels = camp.factors.get(name, [camp.campaign[name]])
            if not any(math.isclose(v, lv, rel_tol=1e-9, abs_tol=1e-12) for lv in levels):
                what = "a level" if name in camp.factors else "the fixed value"
                raise spec_error(path, key, f"{name} = {v} is not {what} of the campaign ({levels})")
        if cell in out:
            raise spec_error(path, key, f"{cell} listed twice")
        out.append(cell)
    return out


def _start(path, raw) -> dict:
    if not isinstance(raw, dict):
        raise spec_error(path, "start", "expected a table [start]")
    scale = {k: 1.0 for k in LEAVES}
    for key in sorted(raw, key=lambda k: k not in GROUPS):  # groups first, then leaf overrides
        if key not in GROUPS and key not in LEAVES:
            raise spec_error(path, f"start.{key}", f"unknown key; expected kp, kd or a leaf ({', '.join(LEAVES)})")
        v = checked_number(path, f"start.{key}", raw[key], float, 0.0, MULT_MAX, True, "(multiplier of the default)")
        for leaf in GROUPS.get(key, (key,)):
            scale[leaf] = v
    return scale


def _leaves(path, raw) -> dict:
    if not isinstance(raw, dict) or not raw:
        raise spec_error(path, "leaves", "expected a table [leaves] with at least one tuned leaf = [lo, hi]")
    out = {}
    for key, v in raw.items():
        full = f"leaves.{key}"
        if key not in LEAVES:
            raise spec_error(path, full, f"unknown leaf; expected one of {', '.join(LEAVES)}")
        if not isinstance(v, list) or len(v) != 2:
            raise spec_error(path, full, f"expected [lo, hi] (multipliers of the default), got {v!r}")
        lo, hi = (checked_number(path, full, x, float, 0.0, MULT_MAX, True, "(multiplier)") for x in v)
        if not lo < hi:
            raise spec_error(path, full, f"= {v}: expected lo < hi")
        out[key] = (lo, hi)
    return out


def parse_tune_spec(data: dict, path: str = "<tune spec>", text_sha256: str = "") -> TuneSpec:
    """Validate a tuning-spec dict (as read by tomllib). Raises SpecError naming ``path`` and the key."""
    tables = ("tune", "start", "leaves", "objective", "cem", "grid", "halving", "confirm")
    unknown = sorted(set(data) - set(tables))
    if unknown:
        raise spec_error(path, unknown[0], f"unknown table; expected {', '.join(tables)}")
    raw_t = data.get("tune", {})
    if not isinstance(raw_t, dict):
        raise spec_error(path, "tune", "expected a table [tune]")
    raw_t = dict(raw_t)
    raw_cells = raw_t.pop("cells", "all")
    tune = checked_table(path, "tune", raw_t, _TUNE)
    if tune["method"] not in METHODS:
        raise spec_error(path, "tune.method", f"= {tune['method']!r}: expected one of {', '.join(METHODS)}")
    camp = _campaign(path, tune["campaign"], reps=tune["reps"], max_seconds=tune["max_seconds"],
                     qp_iters=tune["qp_iters"])
    confirm = checked_table(path, "confirm", data.get("confirm", {}), _CONFIRM)
    confirm_camp = _campaign(path, confirm["campaign"], reps=confirm["reps"]) if confirm["campaign"] else None
    leaves = _leaves(path, data.get("leaves"))
    start = _start(path, data.get("start", {}))
    for leaf, (lo, hi) in leaves.items():
        if not lo <= start[leaf] <= hi:
            raise spec_error(path, f"leaves.{leaf}", f"= [{lo}, {hi}] does not contain the start scale {start[leaf]}")
    s = TuneSpec(path=str(path), tune=tune, cells=_cells(path, raw_cells, camp), start=start, leaves=leaves,
                 objective=checked_table(path, "objective", data.get("objective", {}), _OBJECTIVE),
                 cem=checked_table(path, "cem", data.get("cem", {}), _CEM),
                 grid=checked_table(path, "grid", data.get("grid", {}), _GRID),
                 halving=checked_table(path, "halving", data.get("halving", {}), _HALVING), confirm=confirm,
                 campaign=camp, confirm_campaign=confirm_camp, text_sha256=text_sha256)
    if s.cem["min_std"] > s.cem["init_std"]:
        raise spec_error(path, "cem.min_std", f"= {s.cem['min_std']}: expected <= cem.init_std ({s.cem['init_std']})")
    _check_method(s)
    return s


def load_tune_spec(path: str | Path) -> TuneSpec:
    """Read and validate a tuning spec. Raises SpecError (one line: file, key, expected) on any problem."""
    try:
        raw = Path(path).read_bytes()
        data = tomllib.loads(raw.decode("utf-8-sig"))
    except OSError as e:
        raise SpecError(f"{path}: cannot read spec file ({e.strerror or e})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SpecError(f"{path}: not valid TOML ({str(e).splitlines()[0]})") from None
    return parse_tune_spec(data, str(path), hashlib.sha256(raw).hexdigest())


