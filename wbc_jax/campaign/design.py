"""The design table of a campaign spec: one row per run, with its seed, perturbations and controller settings.

Run i (cells in the design order of the factors' product, :func:`wbc_jax.campaign.factors.design_order`, then reps)
has seed ``SeedSequence([seed, i]).generate_state(1)[0]``; its perturbations are drawn from
``numpy.random.default_rng(run_seed)`` in the order dx, dy, yaw, vx, vy, push magnitude, push angle, push start.
Plain Python and numpy (no JAX).
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass

import numpy as np

from wbc_jax.campaign import factors as factors_mod
from wbc_jax.control.variants import VARIANTS


@dataclass(frozen=True)
class Design:
    """One row per run (cells in the product order of the spec's factors, in design order, then reps), with the
    run's perturbations and controller settings.

    Attributes (each (B,) unless shown): m, mu, d (object mass [kg], tray friction, side [m]: the level of the
    factor or the campaign's value), rep, seed; obj_dx, obj_dy [m] and obj_yaw [rad] (placement on the
    tray, tray-aligned world x/y), v0 (B, 2) [m/s] initial horizontal velocity, push_force (B, 3) [N],
    push_frac (push start as a fraction of the planned duration, known once the plan is: see
    :func:`wbc_jax.campaign.build.build`), push_duration [s]; qvel_noise_std [m/s, rad/s] (controller-view
    velocity noise, drawn during the rollout from the run's seed); ground_mu (foot/ground friction, 0: the
    scene's), speed [m/s] (cruise speed of the run's plan); variant (B, 3) the controller's ablation switches
    (tray_cone, observer, posture; :mod:`wbc_jax.control.variants`); mass_error: the centroidal controller's
    model mass error (fraction); gain_scale: leaf -> (B,) multiplier of that
    ``TransportGains`` leaf (the ``gain.*`` factors); plugin_params: field -> (B,) the run's value of that field
    of the ``[plugin]`` class (the ``plugin.*`` factors); levels: factor name -> (B,) the run's level of each
    varied factor (the results table's factor columns).
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
    ground_mu: np.ndarray
    speed: np.ndarray
    variant: np.ndarray
    mass_error: np.ndarray
    gain_scale: dict
    plugin_params: dict
    levels: dict

    @property
    def n(self) -> int:
        return int(self.m.shape[0])

    def asdict(self):
        return asdict(self)


def run_seed(base: int, i: int) -> int:
    return int(np.random.SeedSequence([int(base), int(i)]).generate_state(1)[0])


def run_levels(spec) -> tuple[dict, np.ndarray]:
    """``(levels, rep)`` of ``spec``'s runs in design order, without their seeds and perturbations: factor name ->
    (B,) each run's level of that factor, and (B,) each run's repetition index."""
    f = spec.factors
    cells = list(itertools.product(*f.values()))  # spec.factors is in design order
    rows = [(cell, r) for cell in cells for r in range(spec.reps)]
    return {k: np.array([cell[j] for cell, _ in rows]) for j, k in enumerate(f)}, np.array([r for _, r in rows])


def object_levels(spec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(B,) each of the runs' m, mu and d (:class:`Design`'s, the factor's level or the campaign's value), without
    the rest of the design."""
    levels, rep = run_levels(spec)
    return tuple(levels[k] if k in levels else np.full(len(rep), spec.campaign[k]) for k in ("m", "mu", "d"))


def design(spec) -> Design:
    """The design table of ``spec`` (a validated :class:`wbc_jax.campaign.spec.Spec`) with every run's seed and
    perturbations (host-side, deterministic)."""
    p, c = spec.perturbations, spec.campaign
    levels, rep = run_levels(spec)
    B = len(rep)

    def value(key, fixed):
        """(B,) the run's level of factor ``key``, or ``fixed`` for every run when it is not varied."""
        return levels[key] if key in levels else np.full(B, fixed)

    seeds = np.array([run_seed(c["seed"], i) for i in range(B)], dtype=np.uint64)
    draws = np.zeros((B, 8))
    for i, s in enumerate(seeds):
        rng = np.random.default_rng(int(s))
        draws[i] = [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1), rng.normal(), rng.normal(),
                    rng.uniform(0, 1), rng.uniform(0, 2 * np.pi), rng.uniform(0, 1)]
    a, b = p["push_window"]
    on = p["push_duration_s"] > 0
    if "push_N" in levels:  # a fixed magnitude and direction; the start still drawn in the window
        mag, angle = levels["push_N"] * on, np.full(B, np.deg2rad(p["push_dir_deg"]))
    else:  # random magnitude in [0, push_max_N] and direction
        mag, angle = (draws[:, 5] * p["push_max_N"] if on else np.zeros(B)), draws[:, 6]
    push = np.stack([mag * np.cos(angle), mag * np.sin(angle), np.zeros(B)], axis=1)
    pushed = levels["push_N"] > 0 if "push_N" in levels else np.full(B, p["push_max_N"] > 0)
    switches = np.array([VARIANTS[v] for v in value("variant", c["variant"])], dtype=float)  # (B, 3)
    switches[:, 1] *= value("observer", 1)
    return Design(
        m=value("m", c["m"]), mu=value("mu", c["mu"]), d=value("d", c["d"]), rep=rep,
        seed=seeds, obj_dx=draws[:, 0] * p["object_xy_mm"] * 1e-3, obj_dy=draws[:, 1] * p["object_xy_mm"] * 1e-3,
        obj_yaw=np.deg2rad(draws[:, 2] * p["object_yaw_deg"]), v0=draws[:, 3:5] * p["base_speed_std"],
        push_force=push, push_frac=a + (b - a) * draws[:, 7],
        push_duration=np.where(pushed, p["push_duration_s"], 0.0),
        qvel_noise_std=value("qvel_noise_std", p["qvel_noise_std"]), ground_mu=value("ground_mu", c["ground_mu"]),
        speed=value("speed", c["speed"]), variant=switches, mass_error=value("mass_error", c["mass_error"]),
        gain_scale={k[len(factors_mod.GAIN_PREFIX):]: v for k, v in levels.items()
                    if k.startswith(factors_mod.GAIN_PREFIX)},
        plugin_params={k[len(factors_mod.PLUGIN_PREFIX):]: v for k, v in levels.items()
                       if k.startswith(factors_mod.PLUGIN_PREFIX)},
        levels=levels)
