"""The ADMM QP solver flags contradictory equalities as primal infeasible, in float32 and float64, with and without
polishing. A file of its own because the float32 certificate is reached within the iterations only with LLVM's fused
multiply-adds (marker ``llvm_default``, conftest.py): the process that runs it compiles at LLVM's default level, the
others (tests/test_qp.py's many solver programs among them) at -O0."""

import jax
import numpy as np
import pytest
from test_qp import _assert_finite, _box_problem

from wbc_jax.qp import FLAG_PRIMAL_INFEASIBLE, QPSettings, solve_qp


@pytest.mark.llvm_default
@pytest.mark.parametrize("polish", [False, True])
@pytest.mark.parametrize("x64", [False, True])
def test_infeasible_contradictory_equalities(x64, polish):
    A = [[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    data = _box_problem([1.0, 2.0, -np.inf], [1.0, 2.0, 5.0], A)
    with jax.enable_x64(x64):
        res = solve_qp(*data, settings=QPSettings(polish=polish))
        _assert_finite(res)
        assert int(res.flag) == FLAG_PRIMAL_INFEASIBLE
