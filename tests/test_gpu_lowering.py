"""Programs lowered for a GPU on a CPU-only machine: the fused QP kernels, and the paper campaign's chunk program.

Pallas lowers a kernel to Triton's IR when the program is lowered, before any GPU is involved: a kernel body that
Triton's lowering rejects (e.g. a ``lax.cond`` branch that yields a constant) fails here, where the interpreter the
other tests use runs it. Lowered with ``lowering_platforms=("cuda",)``; nothing is compiled or run.
"""

from __future__ import annotations

import functools
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wbc_jax.control.transport import control_qp_settings
from wbc_jax.qp import fused
from wbc_jax.qp.api import resolve_settings

N, M, NE, NB, B = 56, 78, 24, 32, 4  # the transport QP's variables, rows, exact rows, box rows; a batch of 4
PAPER_SPEC = dict(warm_first_test=4, alpha=1.3, rho=2.0, reuse_factors=True, launch_order="predicted")


def _lowered_text(s, warm: bool) -> str:
    """The StableHLO text of a vmapped fused solve of B problems with settings ``s`` (resolved as on a GPU),
    warm-started with the previous solve's factors and iterations where ``warm``, lowered for CUDA."""
    s = resolve_settings(s._replace(box_rows=NB), 8, np.float32, "gpu")
    assert s.kernel == "fused"
    rng = np.random.default_rng(0)
    z = lambda *shape: jnp.asarray(rng.standard_normal((B, *shape)), jnp.float32)  # noqa: E731
    P, q, A, l, u = z(N, N), z(N), z(M, N), -jnp.ones((B, M)), jnp.ones((B, M))
    w = None
    if warm:
        factors = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (B, *a.shape)),
                                         fused.empty_factors(N, M, s))
        w = (z(N), z(M), z(M), jnp.full((B,), 2.0, jnp.float32), jnp.full((B,), 9, jnp.int32), factors)
    solve = jax.vmap(functools.partial(fused.solve_fused, s=s, iters=8, interpret=False))
    return jax.jit(solve).trace(P, q, A, l, u, w).lower(lowering_platforms=("cuda",)).as_text()


@pytest.mark.parametrize("warm, settings", [(False, {}), (True, PAPER_SPEC)], ids=["bench", "paper_spec"])
def test_fused_kernels_lower_for_a_gpu(warm, settings):
    """The control loop's settings cold (the bench's solve) and the paper spec's warm (first test after the
    predecessor's count, over-relaxation 1.3, rho 2, the factors kept, the predicted launch order): the three
    kernels lower to Triton."""
    text = _lowered_text(control_qp_settings(8, kernel="fused", **settings), warm)
    for name in ("admm_prepare", "admm_factor", "admm_iterations"):
        assert name in text, name


def test_paper_campaign_program_lowers_for_a_gpu(monkeypatch):
    """The paper spec's campaign chunk program as a GPU would build it (Warp physics through MJX's FFI calls, the
    fused QP kernels with the spec's settings: JAX's default backend reported as "gpu" while it is built and traced,
    the build's caches fresh), 1 repetition (27 runs), lowered for CUDA: the three Triton kernels and MuJoCo Warp's
    calls are in the program."""
    pytest.importorskip("warp")
    from wbc_jax.campaign import build
    from wbc_jax.campaign.spec import SWEEPS, parse_spec
    from wbc_jax.rollout import loop
    from wbc_jax.rollout.batch import chunk_args

    data = tomllib.loads((SWEEPS / "paper_campaign.toml").read_text())
    data["campaign"]["reps"] = 1
    for name, fresh in (("_SIMS", {}), ("_FNS", {})):
        monkeypatch.setattr(build, name, fresh)
    monkeypatch.setattr(loop, "_CHUNK_FNS", {})
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    try:
        built, _ = build.build_ahead(build.with_backend(parse_spec(data), "warp"))
        b = built.batch
        fn = build.chunk_fn(built.sim, b.in_axes, built.logs_per_chunk, None, b.state_axes)
        text = fn.trace(*chunk_args(b)).lower(lowering_platforms=("cuda",)).as_text()
    finally:
        jax.clear_caches()  # no trace made as for a GPU is reused by a later test on the CPU
    for name in ("admm_prepare", "admm_factor", "admm_iterations"):
        assert name in text, name
    assert text.count("stablehlo.custom_call") >= 3 + 1  # the kernels and MuJoCo Warp's calls
