"""The kernels one MuJoCo Warp physics step of a campaign's scene launches, with their launch dimensions.

    python examples/warp_step_launches.py SPEC [NJMAX[,NJMAX...]] [WORLDS]

Runs MuJoCo Warp's ``step`` directly (no MJX, no XLA) on Warp's default device for ``WORLDS`` copies (default 4)
of the spec's first run at its initial configuration, once per constraint-row capacity ``NJMAX`` (default: the
campaign's, ``wbc_jax.physics.backend.make_data``), and prints every launch of the second call: how many times,
tiled (``t`` and the block size) or not (``l``), its dimensions and the kernel. The solver's iteration kernels
appear once per iteration (on the CPU the loop runs ``opt.iterations`` times; on a GPU a CUDA graph's conditional
node stops when every world has converged). Per capacity it prints the launches' threads in all and in the
launches that have a constraint-row dimension: what a tighter ``njmax`` would save.
"""

from __future__ import annotations

import sys
from collections import Counter

import mujoco
import numpy as np
import warp as wp

from wbc_jax.campaign import build
from wbc_jax.campaign.spec import load_spec
from wbc_jax.physics.backend import make_data

LAUNCHES: list[tuple[str, tuple, str]] = []  # (kernel, dims, "l" or "t<block>")


def recording(launch, kind):
    """``launch`` (``wp.launch`` or ``wp.launch_tiled``) that also appends its kernel and dimensions to LAUNCHES."""
    def wrapped(kernel, *args, dim=None, **kwargs):
        if dim is None:
            dim, args = args[0], args[1:]
        dims = (int(dim),) if np.ndim(dim) == 0 else tuple(int(x) for x in dim)
        LAUNCHES.append((getattr(kernel, "key", str(kernel)), dims, kind + str(kwargs.get("block_dim", ""))))
        return launch(kernel, *args, dim=dim, **kwargs)
    return wrapped


def main() -> None:
    spec = load_spec(sys.argv[1])
    worlds = int(sys.argv[3]) if len(sys.argv) > 3 else 4
    built, _ = build.build_ahead(build.with_backend(spec, "warp"))
    mjm = built.sim.robot.mj_model
    warp = make_data(built.sim.robot, worlds)._impl  # the campaign's capacities for a batch of this size
    default = int(warp.njmax)
    capacities = [int(x) for x in sys.argv[2].split(",")] if len(sys.argv) > 2 else [default]
    mjd = mujoco.MjData(mjm)
    mjd.qpos[:] = np.asarray(build.initial_configuration(built.sim.robot, built.design)[0])[0]
    mujoco.mj_forward(mjm, mjd)
    print(f"nv {mjm.nv}, njnt {mjm.njnt}, the campaign's njmax {default}; at the initial configuration "
          f"{mjd.ncon} contacts, {mjd.nefc} constraint rows")

    from mujoco.mjx.third_party import mujoco_warp as mjw  # after the spec's checks: warp-lang is installed

    wp.launch, wp.launch_tiled = recording(wp.launch, "l"), recording(wp.launch_tiled, "t")
    m = mjw.put_model(mjm)
    for njmax in capacities:
        d = mjw.put_data(mjm, mjd, nworld=worlds, naconmax=int(warp.naconmax), njmax=njmax)
        mjw.step(m, d)  # the first call compiles and loads the modules
        LAUNCHES.clear()
        mjw.step(m, d)
        threads = sum(int(np.prod(dims)) for _, dims, _ in LAUNCHES)
        rows = sum(int(np.prod(dims)) for _, dims, _ in LAUNCHES if njmax in dims[1:])
        empty = sum(1 for _, dims, _ in LAUNCHES if not np.prod(dims))
        print(f"njmax {njmax}: {len(LAUNCHES) - empty} launches ({empty} more of size 0, which Warp skips), "
              f"{threads} threads, {rows} in launches over the rows")
        if njmax == capacities[0]:
            for (name, dims, kind), n in Counter(LAUNCHES).items():
                print(f"  {n:3d} x {kind:5s} {str(dims):16s} {name}")


if __name__ == "__main__":
    main()
