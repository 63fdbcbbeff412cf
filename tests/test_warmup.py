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
