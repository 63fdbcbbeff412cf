"""``wbc-jax warmup``: its argument checks and the Warp kernel modules it compiles ahead of use."""

import pytest

from wbc_jax import cli


def test_warmup_rejects_a_negative_worker_count(capsys):
    assert cli.main(["warmup", "--workers", "-1"]) == 2
    assert "--workers -1" in capsys.readouterr().err


def test_warp_kernel_modules_are_mujoco_warps():
    pytest.importorskip("warp")
    from wbc_jax.physics import warp_kernels

    names = [m.name for m in warp_kernels.kernel_modules()]
    assert any(n.endswith("mujoco_warp._src.solver") for n in names)
    assert any(n.endswith("mujoco_warp._src.collision_primitive") for n in names)
    assert not any(n.startswith("warp.") for n in names)


def test_preload_only_where_warp_runs_on_a_gpu_and_its_error_reaches_the_caller(monkeypatch):
    from wbc_jax.physics import warp_kernels

    assert warp_kernels.start_preload("jax") is None
    assert warp_kernels.start_preload("warp") is None  # JAX on the CPU: Warp's kernels compile on first use
    monkeypatch.setattr(warp_kernels, "preload", lambda workers, device, names: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        warp_kernels.Preload(2).result()


def test_warmup_compiles_the_campaigns_chunk_program_on_warp(capsys):
    """On Warp the warmup builds and compiles as the campaign does (``build_ahead``, ``states_and_program``: the chunk
    program from the batch's shapes, then the initial states) and runs the first chunk: the CI baseline spec, CPU."""
    pytest.importorskip("warp")
    from wbc_jax.campaign.spec import SWEEPS

    spec = str(SWEEPS.parent / "reports" / "baseline" / "spec.toml")
    assert cli.main(["warmup", "--spec", spec, "--backend", "warp"]) == 0
    out = capsys.readouterr().out
    assert "warmup: setup_s" in out and "compile_chunk_s" in out and "first_chunk_s" in out, out
