"""Random QPs with a known optimum, and accuracy metrics, for tests and benchmarks.

Every problem is built backwards from a chosen KKT point ``(x*, y*)``: the bounds make a
chosen subset of inequality rows active (``y*`` of the right sign there, zero elsewhere),
and ``q = -P x* - A' y*``. Because ``P`` is positive definite, ``x*`` is the unique
minimizer, so accuracy can be measured without trusting any solver.

Two families, both of whole-body-controller size (n = 68, 24 equality rows,
70 inequality rows by default):

* ``"generic"``: Gaussian ``A``, well-conditioned ``P``, unit-scale ``x*``.
* ``"wbc"``: the structure and the scales of a real WBC QP: variables are joint
  accelerations (~10 rad/s^2), contact-force edge multipliers (0-200 N, half of them
  at their bound 0) and slacks; equality rows are floating-base dynamics (mass-matrix
  entries 0.01-25 mixed with Jacobian-transpose entries) and contact-acceleration rows
  (Jacobian entries ~0.3); inequalities are multipliers >= 0, torque limits +-60 N m
  and swing-tracking bands; the cost is ``||H x - r||_Q^2 + ||x||_R^2`` with task
  weights 50..1e4 and regularization 1..1e3. Entries of ``P``, ``q`` and ``A`` span six
  or more orders of magnitude, which is what Ruiz equilibration is for.

All arrays are NumPy float64; ``+-inf`` marks a missing bound.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class QPProblem(NamedTuple):
    """A QP ``min 1/2 x'Px + q'x  s.t. l <= Ax <= u`` with its known solution.

    Fields may carry leading batch axes ``(B, ...)``.

    Attributes:
        P: (n, n) symmetric positive definite cost Hessian.
        q: (n,) cost gradient at zero.
        A: (m, n) constraint matrix; the first ``m_eq`` rows are equalities.
        l: (m,) lower bounds (``-inf`` where absent).
        u: (m,) upper bounds (``+inf`` where absent; ``l == u`` on equalities).
        x: (n,) the optimal primal solution.
        y: (m,) optimal duals (OSQP sign: > 0 at an active upper bound, < 0 at lower).
        f: () optimal objective value.
    """

    P: np.ndarray
    q: np.ndarray
    A: np.ndarray
    l: np.ndarray
    u: np.ndarray
    x: np.ndarray
    y: np.ndarray
    f: np.ndarray


def objective(P, q, x):
    """``1/2 x'Px + q'x`` in float64, batched over leading axes. Returns (...,)."""
    P, q, x = (np.asarray(a, np.float64) for a in (P, q, x))
    return 0.5 * np.einsum("...i,...ij,...j->...", x, P, x) + np.einsum("...i,...i->...", q, x)


def rel_objective_error(P, q, x, f_star):
    """``|f(x) - f*| / max(1, |f*|)`` (float64), batched. Returns (...,)."""
    f_star = np.asarray(f_star, np.float64)
    return np.abs(objective(P, q, x) - f_star) / np.maximum(1.0, np.abs(f_star))


def max_violation(A, l, u, x, relative: bool = True):
    """Largest constraint violation ``max_i dist(a_i x, [l_i, u_i])`` (float64).

    Args:
        A, l, u, x: problem rows and candidate solution, batched over leading axes.
        relative: divide by ``max(1, ||A x||_inf)``, as OSQP's primal tolerance does
            (``eps_abs + eps_rel ||Ax||``); WBC rows reach several hundred N m, where
            an absolute 1e-5 is below float32 rounding of ``A x``. False: absolute,
            in the units of each row (N, N m, rad/s^2, ...).

    Returns:
        (...,) violation; rows with ``l > u`` count their gap.
    """
    A, l, u, x = (np.asarray(a, np.float64) for a in (A, l, u, x))
    ax = np.einsum("...ij,...j->...i", A, x)
    v = np.max(np.maximum(np.maximum(l - ax, ax - u), 0.0), axis=-1)
    if relative:
        v = v / np.maximum(1.0, np.max(np.abs(ax), axis=-1))
    return v


def _finish(P, A, x, m_eq, act_lo, act_up, gap_lo, gap_up, one_sided_lo, one_sided_up, y):
    """Bounds from activity pattern, then ``q`` from stationarity."""
    ax = A @ x
    m = A.shape[0]
    l = np.empty(m)
    u = np.empty(m)
    l[:m_eq] = u[:m_eq] = ax[:m_eq]
    i = slice(m_eq, m)
    l[i] = np.where(act_lo, ax[i], ax[i] - gap_lo)
    u[i] = np.where(act_up, ax[i], ax[i] + gap_up)
    l[i] = np.where(one_sided_lo & ~act_lo, -np.inf, l[i])
    u[i] = np.where(one_sided_up & ~act_up, np.inf, u[i])
    q = -P @ x - A.T @ y
    f = 0.5 * x @ P @ x + q @ x
    return QPProblem(P, q, A, l, u, x, y, np.float64(f))


def _active_pattern(rng, m_in, frac_active):
    act = rng.random(m_in) < frac_active
    up = rng.random(m_in) < 0.5
    return act & ~up, act & up


def random_generic_qp(rng: np.random.Generator, n=68, m_eq=24, m_in=70, frac_active=0.35):
    """One well-scaled strictly convex QP with known optimum (see module docstring)."""
    B = rng.standard_normal((n, n)) / np.sqrt(n)
    P = B.T @ B + np.diag(rng.uniform(0.05, 1.0, n))
    A = rng.standard_normal((m_eq + m_in, n)) / np.sqrt(n)
    x = rng.standard_normal(n)
    act_lo, act_up = _active_pattern(rng, m_in, frac_active)
    y = np.zeros(m_eq + m_in)
    y[:m_eq] = rng.standard_normal(m_eq)
    mag = rng.uniform(0.1, 2.0, m_in)
    y[m_eq:] = np.where(act_up, mag, np.where(act_lo, -mag, 0.0))
    gap_lo = rng.uniform(0.05, 2.0, m_in)
    gap_up = rng.uniform(0.05, 2.0, m_in)
    one_lo = rng.random(m_in) < 0.25
    one_up = (rng.random(m_in) < 0.25) & ~one_lo
    return _finish(P, A, x, m_eq, act_lo, act_up, gap_lo, gap_up, one_lo, one_up, y)


class _WbcRows(NamedTuple):
    """Row and column layout of :func:`random_wbc_qp`'s problem."""

    nv: int  # joint accelerations qdd
    nrho: int  # contact-force edge multipliers rho
    nslack: int  # slacks of the first contact-acceleration rows
    n_eq_contact: int  # contact-acceleration equalities
    n_torque: int  # torque-limit rows
    n_swing: int  # swing-band rows

    @property
    def n(self) -> int:
        return self.nv + self.nrho + self.nslack

    @property
    def m_eq(self) -> int:
        return 6 + self.n_eq_contact

    @property
    def m_in(self) -> int:
        return self.nrho + self.n_torque + self.n_swing


def _wbc_constraints(rng: np.random.Generator, k: _WbcRows) -> np.ndarray:
    """(m, n) constraint matrix: base dynamics, contact accelerations (slack-softened), multipliers, torques,
    swing bands."""
    nv, nrho, nslack, n_torque = k.nv, k.nrho, k.nslack, k.n_torque
    iq, ir, is_ = slice(0, nv), slice(nv, nv + nrho), slice(nv + nrho, k.n)
    # Mass matrix: SPD with entries 0.01..25 (heavy base, light distal links).
    link = np.exp(rng.uniform(np.log(0.01), np.log(25.0), nv))
    Lm = rng.standard_normal((nv, nv)) * 0.3
    M = np.sqrt(np.outer(link, link)) * (Lm @ Lm.T / nv + np.eye(nv))
    # Contact Jacobian-transpose times friction-pyramid edges: entries ~0.3-1.
    JtW = rng.standard_normal((nv, nrho)) * 0.3
    Jc = rng.standard_normal((k.n_eq_contact, nv)) * 0.3
    Jc[:, :6] += rng.standard_normal((k.n_eq_contact, 6))  # base columns matter most
    m_eq = k.m_eq
    A = np.zeros((m_eq + k.m_in, k.n))
    A[:6, iq] = M[:6]
    A[:6, ir] = -JtW[:6]
    A[6:m_eq, iq] = Jc
    A[6:6 + nslack, is_] = np.eye(nslack)
    r0 = m_eq
    A[r0:r0 + nrho, ir] = np.eye(nrho)
    r1 = r0 + nrho
    jrows = rng.choice(np.arange(6, nv), n_torque, replace=n_torque > nv - 6)
    A[r1:r1 + n_torque, iq] = M[jrows]
    A[r1:r1 + n_torque, ir] = -JtW[jrows]
    r2 = r1 + n_torque
    A[r2:, iq] = rng.standard_normal((k.n_swing, nv)) * 0.3
    return A


def _wbc_cost(rng: np.random.Generator, k: _WbcRows) -> np.ndarray:
    """(n, n) Hessian of ``||H x - r||_Q^2 + ||x||_R^2``: P = 2 (H'QH + R), task weights 50..1e4."""
    nv, nrho, nslack = k.nv, k.nrho, k.nslack
    iq = slice(0, nv)
    n_task = 6 + (nv - 6) + 6
    H = np.zeros((n_task, k.n))
    H[:6, iq] = rng.standard_normal((6, nv)) * 0.5  # CoM / base task
    H[6:nv, 6:nv] = np.eye(nv - 6)  # posture
    H[nv:, iq] = rng.standard_normal((6, nv)) * 0.3  # end effector
    Q = np.exp(rng.uniform(np.log(50.0), np.log(1e4), n_task))
    R = np.concatenate([
        np.exp(rng.uniform(np.log(1.0), np.log(10.0), nv)),
        np.exp(rng.uniform(np.log(1.0), np.log(10.0), nrho)),
        np.exp(rng.uniform(np.log(1e2), np.log(1e3), nslack)),
    ])
    P = 2.0 * (H.T @ (Q[:, None] * H) + np.diag(R))
    return 0.5 * (P + P.T)


class _Activity(NamedTuple):
    """Which inequality rows of :func:`random_wbc_qp` are active at the optimum, and how."""

    act_lo: np.ndarray  # (m_in,) bool: at the lower bound
    act_up: np.ndarray  # (m_in,) bool: at the upper bound
    t_act: np.ndarray  # (n_torque,) bool: torque row active
    s_act: np.ndarray  # (n_swing,) bool: swing row active


def _wbc_activity(rng: np.random.Generator, k: _WbcRows, on: np.ndarray) -> _Activity:
    """Active set: multipliers at 0 where not ``on``, about 30 % of torque and swing rows at a random side."""
    nrho, n_torque = k.nrho, k.n_torque
    act_lo = np.zeros(k.m_in, bool)
    act_up = np.zeros(k.m_in, bool)
    act_lo[:nrho] = ~on
    t_act = rng.random(n_torque) < 0.3
    t_up = rng.random(n_torque) < 0.5
    act_lo[nrho:nrho + n_torque] = t_act & ~t_up
    act_up[nrho:nrho + n_torque] = t_act & t_up
    s_act = rng.random(k.n_swing) < 0.3
    s_up = rng.random(k.n_swing) < 0.5
    act_lo[nrho + n_torque:] = s_act & ~s_up
    act_up[nrho + n_torque:] = s_act & s_up
    return _Activity(act_lo, act_up, t_act, s_act)


def _wbc_gaps(rng: np.random.Generator, k: _WbcRows, x_rho: np.ndarray, act: _Activity):
    """(gap_lo, gap_up) (m_in,) of the inequality rows: multipliers >= 0, torque bands 120 N m wide around a bias,
    swing bands 0.5..5 wide; zero on the active side."""
    nrho, n_torque = k.nrho, k.n_torque
    gap_lo = np.empty(k.m_in)
    gap_up = np.empty(k.m_in)
    gap_lo[:nrho] = x_rho  # lower bound 0 exactly
    gap_up[:nrho] = np.inf
    frac = rng.uniform(0.1, 0.9, n_torque)
    gl = np.where(act.act_lo[nrho:nrho + n_torque], 0.0, np.where(act.t_act, 120.0, 120.0 * frac))
    gap_lo[nrho:nrho + n_torque] = gl
    gap_up[nrho:nrho + n_torque] = 120.0 - gl
    width = rng.uniform(0.5, 5.0, k.n_swing)
    fs = rng.uniform(0.1, 0.9, k.n_swing)
    gs = np.where(act.act_lo[nrho + n_torque:], 0.0, np.where(act.s_act, width, width * fs))
    gap_lo[nrho + n_torque:] = gs
    gap_up[nrho + n_torque:] = width - gs
    return gap_lo, gap_up


def random_wbc_qp(rng: np.random.Generator, nv=18, nrho=40, nslack=10, n_eq_contact=18,
                  n_torque=12, n_swing=18):
    """One QP with the structure and scales of a whole-body-control step.

    Variables ``x = [qdd (nv), rho (nrho), s (nslack)]``. Rows: 6 floating-base dynamics
    + ``n_eq_contact`` contact-acceleration equalities (the first ``nslack`` of them
    softened by a slack), then ``nrho`` multiplier rows ``rho >= 0``, ``n_torque``
    torque-limit rows ``|M_j qdd + h_j - (J'W)_j rho| <= 60`` and ``n_swing`` swing
    bands. Defaults give n = 68, m_eq = 24, m_in = 70.
    """
    k = _WbcRows(nv, nrho, nslack, n_eq_contact, n_torque, n_swing)
    n, m_eq, m_in = k.n, k.m_eq, k.m_in
    iq, ir, is_ = slice(0, nv), slice(nv, nv + nrho), slice(nv + nrho, n)
    A = _wbc_constraints(rng, k)
    P = _wbc_cost(rng, k)
    # Known optimum: accelerations ~10, half the multipliers at 0, the rest 0..200 N.
    x = np.zeros(n)
    x[iq] = rng.standard_normal(nv) * 10.0
    on = rng.random(nrho) < 0.5
    x[ir] = np.where(on, rng.uniform(1.0, 200.0, nrho), 0.0)
    x[is_] = rng.standard_normal(nslack) * 0.05
    y = np.zeros(m_eq + m_in)
    y[:m_eq] = rng.standard_normal(m_eq) * np.exp(rng.uniform(0.0, np.log(1e3), m_eq))
    act = _wbc_activity(rng, k, on)
    mag = np.exp(rng.uniform(np.log(1.0), np.log(1e3), m_in))
    y[m_eq:] = np.where(act.act_up, mag, np.where(act.act_lo, -mag, 0.0))
    gap_lo, gap_up = _wbc_gaps(rng, k, x[ir], act)
    one_lo = np.zeros(m_in, bool)
    one_up = np.zeros(m_in, bool)
    one_up[:nrho] = True
    prob = _finish(P, A, x, m_eq, act.act_lo, act.act_up, gap_lo, gap_up, one_lo, one_up, y)
    # The multiplier rows' lower bound is exactly 0 (not ax - x, which rounds).
    l = prob.l.copy()
    l[m_eq:m_eq + nrho] = 0.0
    return prob._replace(l=l)


def make_batch(seed: int, count: int, family: str = "mixed") -> QPProblem:
    """``count`` problems stacked on a leading axis.

    Args:
        seed: NumPy seed.
        count: number of problems B.
        family: ``"generic"``, ``"wbc"`` or ``"mixed"`` (alternating, generic first).

    Returns:
        QPProblem with fields of shape (B, ...).
    """
    rng = np.random.default_rng(seed)
    probs = []
    for k in range(count):
        fam = family if family != "mixed" else ("generic", "wbc")[k % 2]
        probs.append(random_generic_qp(rng) if fam == "generic" else random_wbc_qp(rng))
    return QPProblem(*(np.stack(f) for f in zip(*probs)))


def transport_sized(batch: int, seed: int = 3, distinct: int = 64) -> QPData:
    """``batch`` generic problems of the transport QP's size (56 variables, 24 equality and 54 inequality rows):
    ``distinct`` of them (seed ``seed``) repeated in turn, float32, fields of shape (batch, ...) (the GPU kernel
    studies' load)."""
    rng = np.random.default_rng(seed)
    probs = [random_generic_qp(rng, n=56, m_eq=24, m_in=54) for _ in range(distinct)]
    idx = np.arange(batch) % distinct
    return QPData(*(np.stack([getattr(p, k) for p in probs])[idx].astype(np.float32) for k in QPData._fields))


class QPData(NamedTuple):
    """The data of a QP ``min 1/2 x'Px + q'x  s.t. l <= Ax <= u`` (no known solution), float64."""

    P: np.ndarray
    q: np.ndarray
    A: np.ndarray
    l: np.ndarray
    u: np.ndarray


def perturb(batch: QPProblem, seed: int, rel: float = 0.01, p_mode: str = "congruence") -> QPData:
    """Perturb the data ``(P, q, A, l, u)`` of a batch by a relative ``rel``.

    ``q``, ``A`` and finite bounds are perturbed entrywise ``* (1 + rel N(0,1))``;
    equalities stay equalities and zero entries stay zero (structure is fixed, as in
    consecutive control steps). ``P`` (``p_mode="congruence"``, default) becomes
    ``S P S`` with ``S = diag(1 + rel / sqrt(2) N(0,1))``: every entry changes by ~``rel``
    rms, zeros stay zero and ``P`` stays positive definite, as when the generator's
    weights change. ``p_mode="entrywise"``: ``P * (1 + rel E)`` with symmetric Gaussian
    ``E``, shifted by a multiple of the identity where that made it indefinite. That
    shift is not a small perturbation on ill-conditioned ``P``: on the WBC family
    (eigenvalues 2..1e5) 1 % entrywise noise makes ~13 % of the ``P`` indefinite, the
    shift adds up to ~140 I to a cost whose regularization is 2..20, and the optimum
    moves by ~50 % with 20-35 of the 70 inequality rows changing activity. The known
    optimum no longer applies.

    Returns:
        QPData (P, q, A, l, u) of the batch's shapes.
    """
    rng = np.random.default_rng(seed)

    def mul(a):
        return a * (1.0 + rel * rng.standard_normal(a.shape))

    if p_mode == "congruence":
        S = 1.0 + rel / np.sqrt(2.0) * rng.standard_normal(batch.P.shape[:-1])
        P = S[..., :, None] * batch.P * S[..., None, :]
    elif p_mode == "entrywise":
        E = rng.standard_normal(batch.P.shape)
        E = 0.5 * (E + np.swapaxes(E, -1, -2))
        P = batch.P * (1.0 + rel * E)
        shift = np.maximum(0.0, -np.linalg.eigvalsh(P).min(axis=-1)) * 1.01
        P = P + shift[..., None, None] * np.eye(P.shape[-1])
    else:
        raise ValueError(f"p_mode must be 'congruence' or 'entrywise', not {p_mode!r}")
    A = mul(batch.A)
    q = mul(batch.q)
    eq = batch.l == batch.u
    fac = 1.0 + rel * rng.standard_normal(batch.l.shape)
    l = np.where(np.isfinite(batch.l), batch.l * fac, batch.l)
    fac2 = np.where(eq, fac, 1.0 + rel * rng.standard_normal(batch.u.shape))
    u = np.where(np.isfinite(batch.u), batch.u * fac2, batch.u)
    l = np.minimum(l, u)
    return QPData(P, q, A, l, u)
