"""Search methods of ``wbc-jax tune``: pure functions and classes over candidate arrays (no simulation).

A candidate is a point x in the box [lo, hi]^k of ln-multipliers of the default gains, one coordinate per tuned
leaf (:class:`Space`). A search proposes C candidates per round (``ask``) and learns from their rank keys
(``tell``; :func:`rank_key`: larger is better).

* :class:`GridSearch`: ``grid.points`` log-spaced multipliers per leaf, their full product.
* :class:`RandomSearch`: log-uniform in the box.
* :class:`CEMSearch`: cross-entropy method, a diagonal Gaussian over x with smoothed updates; the best so far is
  carried into slot 0 of every later round.
* :class:`HalvingSearch`: successive halving over candidates x simulated time. Every round is one bracket of
  C log-uniform candidates (slot 0: the start in round 1, the best so far after); rung r simulates the survivors
  up to ``horizons[r]`` chunks (continuing their states) and keeps the best ``alive[r + 1]`` of them
  (:func:`halving_schedule`). Only candidates that reached the last rung (the full horizon) can be the best.

Round 0 slot 0 is always the start, so the start is scored on the same footing as every candidate.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from wbc_jax.control.transport import TransportGains, default_gains


class Space:
    """Tuned leaves' ln-multiplier box and the map from points to batched gains.

    Attributes:
        names: (k,) tuned leaves; lo, hi: (k,) ln of their multiplier ranges; x0: (k,) ln of the start
        multipliers; base: default gains (unbatched); start: every leaf's start multiplier.
    """

    def __init__(self, leaves: dict, start: dict):
        """Args: leaves: tuned leaf -> (lo, hi) multiplier range; start: every leaf -> start multiplier."""
        self.names = tuple(leaves)
        self.lo = np.log([leaves[n][0] for n in self.names])
        self.hi = np.log([leaves[n][1] for n in self.names])
        self.x0 = np.log([start[n] for n in self.names])
        self.base = default_gains()
        self.start = dict(start)

    @property
    def k(self) -> int:
        return len(self.names)

    def multipliers(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """X (C, k) -> every leaf's multiplier, (C,) each."""
        x = np.atleast_2d(x)
        mult = {leaf: np.full(x.shape[0], s) for leaf, s in self.start.items()}
        for j, n in enumerate(self.names):
            mult[n] = np.exp(x[:, j])
        return mult

    def gains(self, x: np.ndarray, mult: dict | None = None) -> TransportGains:
        """X (C, k) -> TransportGains with leading axis C (host numpy, the default gains' dtypes).
        ``mult``: every leaf's multiplier (C,) instead (e.g. all ones: the defaults)."""
        mult = self.multipliers(x) if mult is None else mult
        out = {}
        for name, v in zip(self.base._fields, self.base):
            v = np.asarray(v)
            out[name] = (v[None] * np.asarray(mult[name]).reshape((-1,) + (1,) * v.ndim)).astype(v.dtype)
        return TransportGains(**out)

    def default_multipliers(self, C: int = 1) -> dict[str, np.ndarray]:
        """Multiplier 1 for every leaf: the default gains, C copies."""
        return {leaf: np.ones(C) for leaf in self.start}


def rank_key(feasible: bool, violation: float, objective: float) -> tuple:
    """Sort key, larger is better: feasible first, then smaller violation, then larger objective."""
    return (bool(feasible), -float(violation), float(objective) if np.isfinite(objective) else -math.inf)


def order_by_key(keys: list) -> list[int]:
    """Indices of ``keys`` from best to worst (stable for ties)."""
    return sorted(range(len(keys)), key=lambda i: keys[i], reverse=True)


def pareto_mask(points: np.ndarray) -> np.ndarray:
    """Non-dominated rows of ``points`` (N, q), every column to be maximised (rows with NaN: never)."""
    p = np.asarray(points, float)
    good = np.all(np.isfinite(p), axis=1)
    mask = good.copy()
    for i in np.where(good)[0]:
        dom = good & np.all(p >= p[i], axis=1) & np.any(p > p[i], axis=1)
        mask[i] = not dom.any()
    return mask


def halving_schedule(C: int, eta: int, rungs: int, n_chunks: int) -> tuple[list[int], list[int]]:
    """Successive-halving plan of one bracket.

    Args:
        C: candidates in the bracket; eta: reduction factor (>= 2); rungs: number of rungs (>= 1);
        n_chunks: chunks of the full horizon.

    Returns:
        (alive, horizons): alive[r] candidates simulated in rung r (alive[0] = C, then ceil(C / eta^r), at least 1,
        non-increasing); horizons[r] chunks simulated by the end of rung r (n_chunks / eta^(rungs - 1 - r) rounded
        up, at least 1, strictly increasing where possible, horizons[-1] = n_chunks). Rungs whose horizon would
        repeat the previous one are merged.
    """
    alive, horizons = [], []
    for r in range(rungs):
        h = min(n_chunks, max(1, math.ceil(n_chunks / eta ** (rungs - 1 - r) - 1e-9)))
        a = max(1, math.ceil(C / eta ** r - 1e-9))
        if horizons and h == horizons[-1]:
            alive[-1] = a  # same horizon: the later rung's smaller set, no extra simulation
            continue
        alive.append(a)
        horizons.append(h)
    alive[0] = C
    return alive, horizons


def halving_cost(C: int, eta: int, rungs: int, n_chunks: int) -> int:
    """Candidate-chunks simulated by one bracket (survivors continue their states: no chunk is simulated twice)."""
    alive, horizons = halving_schedule(C, eta, rungs, n_chunks)
    return sum(a * (h - h0) for a, h, h0 in zip(alive, horizons, [0] + horizons[:-1]))


class Search:
    """Base class: ``ask(r)`` -> (x (C, k), kinds (C,)), ``tell(x, keys)`` after scoring."""

    rounds: int

    def __init__(self, space: Space, C: int, rounds: int, rng: np.random.Generator):
        self.space, self.C, self.rounds, self.rng = space, C, rounds, rng
        self.best_x, self.best_key = None, None

    def _remember(self, x, keys) -> None:
        i = order_by_key(keys)[0]
        if self.best_key is None or keys[i] >= self.best_key:
            self.best_x, self.best_key = np.array(x[i]), keys[i]

    def tell(self, x, keys) -> None:
        self._remember(x, keys)

    def uniform(self, n: int) -> np.ndarray:
        s = self.space
        return s.lo + (s.hi - s.lo) * self.rng.random((n, s.k))


class RandomSearch(Search):
    def ask(self, r):
        x = self.uniform(self.C)
        kinds = ["sample"] * self.C
        if r == 0:
            x[0], kinds[0] = self.space.x0, "start"
        return x, kinds


class HalvingSearch(RandomSearch):
    """Successive halving (module docstring): ``ask`` as :class:`RandomSearch` with the best so far in slot 0
    after round 1; the bracket's rungs are planned by :func:`halving_schedule` and run by the caller."""

    def __init__(self, space, C, rounds, rng, eta: int, rungs: int):
        super().__init__(space, C, rounds, rng)
        self.eta, self.rungs = eta, rungs

    def ask(self, r):
        x, kinds = super().ask(r)
        if r > 0 and self.best_x is not None:
            x[0], kinds[0] = self.best_x, "elite"
        return x, kinds

    @staticmethod
    def survivors(keys: list, n_keep: int) -> np.ndarray:
        """Indices (into ``keys``) of the ``n_keep`` best, best first."""
        return np.asarray(order_by_key(keys)[:n_keep], int)


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
        order = order_by_key(keys)
        elite = x[order[:self.n_elite]]
        a = self.alpha
        self.mean = a * elite.mean(0) + (1 - a) * self.mean
        self.std = np.maximum(self.min_std, a * elite.std(0) + (1 - a) * self.std)
        self._remember(x, keys)
        self.history.append(dict(mean=self.mean.tolist(), std=self.std.tolist()))


def make_search(spec, space: Space) -> Search:
    """The search of a validated :class:`wbc_jax.studies.tune_spec.TuneSpec`."""
    t = spec.tune
    rng = np.random.default_rng(t["seed"])
    if t["method"] == "grid":
        return GridSearch(space, t["candidates"], t["rounds"], rng, spec.grid["points"])
    if t["method"] == "random":
        return RandomSearch(space, t["candidates"], t["rounds"], rng)
    if t["method"] == "halving":
        return HalvingSearch(space, t["candidates"], t["rounds"], rng, spec.halving["eta"], spec.halving["rungs"])
    return CEMSearch(space, t["candidates"], t["rounds"], rng, **spec.cem)
