"""The iterations kernel's launch order under ``vmap`` (``QPSettings.launch_order="predicted"``).

The fused iterations kernel runs one program per problem, and a batch's programs start in launch order as slots
free up. Under the campaign's velocity noise a few solves run many times the typical number of ADMM iterations
(docs/performance.md, the launch order). The batch ends when its last long solve does, so one that starts late
holds up the whole control step. Started longest-predicted first, the long solves run beside the short ones.

:func:`predicted_length` is the prediction, from vectors only (no matrix is read): the predecessor's iterations plus
``check_every`` per decade of the warm start's bound violation on the new problem. :func:`launch` calls a kernel
either way; :func:`ordered_call` is the kernel under ``jax.custom_batching``: unbatched it is the plain
``pallas_call``; batched, one ``pallas_call`` over the batch whose program ``i`` reads problem ``perm[i]``
(``perm``: the problems by decreasing key) from the whole input arrays (:class:`Problem`: every read indexes
``ref[perm[i], ...]``, nothing gathered) and writes its own output block ``i``; the outputs, a few vectors per
problem, are then put back in the batch's order. Each problem's arithmetic is unchanged (in Pallas' CPU
interpreter equal to float rounding: its XLA compiles the reads from the whole arrays with other dot kernels).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from wbc_jax.qp.settings import QPSettings

REGISTERS_PER_SM = 65536  # 32-bit registers of one streaming multiprocessor (sm_80 and sm_90)
REGISTERS_PER_THREAD = 255  # the most a thread can hold; one_wave counts a program as using them all


def one_wave(num_warps: int) -> int:
    """The programs of ``num_warps`` warps at ``REGISTERS_PER_THREAD`` registers that the default device runs at
    once: its multiprocessors x the programs one holds. A batch no larger starts every program at once, so no
    launch order can shorten it; 0 where the device does not report its multiprocessors (e.g. a CPU)."""
    sms = getattr(jax.devices()[0], "core_count", None) or 0
    return int(sms) * max(1, REGISTERS_PER_SM // (REGISTERS_PER_THREAD * 32 * num_warps))


def predicted_length(l, u, wz, wk, s: QPSettings):
    """() the launch key of one warm-started problem, larger for a longer solve: ``wk`` (the predecessor's
    iterations, () int) plus ``s.check_every`` x log10(1 + v), with v the warm start's largest bound violation on the
    new problem, max |wz - clip(wz, l, u)|, relative to the tolerance ``eps_abs + eps_rel * max |wz|``: O(m), no
    matrix read (a key from the warm start's residuals, which reads P and A, cost the campaign's step more than the
    order saved; docs/performance.md).

    Args:
        l, u: (m,) the new problem's bounds (infinite where a row has none); wz: (m,) the warm start's A x.
    """
    viol = jnp.max(jnp.abs(wz - jnp.clip(wz, l, u))) / (s.eps_abs + s.eps_rel * jnp.max(jnp.abs(wz)))
    return wk.astype(wz.dtype) + s.check_every * jnp.log10(1.0 + viol)


class Problem:
    """Problem ``i`` of a batch-wide input ref ``(batch, *shape)``, read as a kernel reads its own block's ref:
    ``shape``, ``dtype``, ``p[idx]`` and ``p.at[idx]`` (for ``plgpu.load``) index ``ref[(i, *idx)]``. One indexer per
    read: Triton's lowering takes no view of a view (``ref.at[i].at[idx]``)."""

    def __init__(self, ref, i):
        self.ref, self.i = ref, i
        self.shape, self.dtype = tuple(ref.shape[1:]), ref.dtype

    def index(self, idx) -> tuple:
        return (self.i, *(idx if isinstance(idx, tuple) else (idx,)))

    def __getitem__(self, idx):
        return self.ref[self.index(idx)]

    @property
    def at(self):
        return _At(self)


class _At:
    """``Problem.at``: ``p.at[idx]`` is the batch ref's ``ref.at[(i, *idx)]``."""

    def __init__(self, p: Problem):
        self.p = p

    def __getitem__(self, idx):
        return self.p.ref.at[self.p.index(idx)]


def launch(kernel, out_shape: list, key, ins: tuple, *, interpret: bool, compiler_params, name: str,
           wave: int = 0) -> tuple:
    """``pallas_call(kernel, out_shape)(*ins)`` as a tuple, one program per problem under ``vmap``: in the batch's
    order where ``key`` is None, else by :func:`ordered_call` (``wave``: its :func:`one_wave`)."""
    if key is None:
        return tuple(pl.pallas_call(kernel, out_shape=out_shape, interpret=interpret,
                                    compiler_params=compiler_params, name=name)(*ins))
    return ordered_call(kernel, out_shape, interpret=interpret, compiler_params=compiler_params, name=name,
                        wave=wave)(key, *ins)


def ordered_call(kernel, out_shape: list, *, interpret: bool, compiler_params, name: str, wave: int = 0):
    """``f(key, *ins) -> outs`` (a tuple): ``pallas_call(kernel, out_shape)(*ins)`` for one problem; under one
    ``vmap``, one call over the batch whose programs start in order of decreasing ``key`` (module docstring), or in
    the batch's order where the batch is at most ``wave`` problems (:func:`one_wave`: they all start at once, and
    the order's sort and gathers would only add launches). ``kernel`` takes the inputs' then the outputs' refs of
    one problem."""

    def one(key, *ins):
        return launch(kernel, out_shape, None, ins, interpret=interpret, compiler_params=compiler_params, name=name)

    f = jax.custom_batching.custom_vmap(one)

    @f.def_vmap
    def batched(axis_size, in_batched, key, *ins):
        if axis_size <= wave:
            outs = jax.vmap(one, in_axes=(None, *(0 if b else None for b in in_batched[1:])),
                            axis_size=axis_size)(key, *ins)
            return tuple(outs), (True,) * len(outs)
        key, *ins = (x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
                     for x, b in zip((key, *ins), in_batched))
        perm = jnp.argsort(-key).astype(jnp.int32)

        def whole(shape):
            return pl.BlockSpec(shape, lambda i, n=len(shape): (0,) * n)

        def own(shape):
            return pl.BlockSpec((None, *shape), lambda i, n=len(shape): (i,) + (0,) * n)

        def program(perm_ref, *refs):
            i = perm_ref[pl.program_id(0)]
            kernel(*(Problem(r, i) for r in refs[:len(ins)]), *refs[len(ins):])

        res = pl.pallas_call(program, grid=(axis_size,), interpret=interpret, compiler_params=compiler_params,
                             out_shape=[jax.ShapeDtypeStruct((axis_size,) + o.shape, o.dtype) for o in out_shape],
                             in_specs=[whole(perm.shape)] + [whole(x.shape) for x in ins],
                             out_specs=[own(o.shape) for o in out_shape], name=name)(perm, *ins)
        back = jnp.zeros_like(perm).at[perm].set(jnp.arange(axis_size, dtype=perm.dtype))  # block i: perm[i]
        return tuple(r[back] for r in res), (True,) * len(res)

    return f
