"""Checks of the ``wbc-jax`` commands' arguments: bad values are one-line user errors before anything is built."""

from __future__ import annotations

import argparse

MAX_SECONDS = 600.0  # longest simulated time of demo / trot [s] (a campaign's max_seconds has the same bound)
DISTANCE_RANGE = (0.05, 10.0)  # demo --distance [m], as a campaign spec's campaign.distance


def bench_args(args: argparse.Namespace) -> list[int] | None:
    """The ``--batches`` sizes (None when not given); bad ``bench`` arguments as user errors (flag, value, expected
    range) before anything is compiled."""
    from wbc_jax.errors import InputError

    sizes = None
    if args.batches is not None:
        try:
            sizes = [int(x) for x in args.batches.split(",")]
        except ValueError:
            sizes = []
        if not sizes or min(sizes) < 1:
            raise InputError(f"--batches {args.batches!r}: expected comma-separated integers >= 1, e.g. 1,1024")
    for flag in ("steps", "iters", "substeps", "rounds"):
        if getattr(args, flag) is not None and getattr(args, flag) < 1:
            raise InputError(f"--{flag} {getattr(args, flag)}: expected an integer >= 1")
    if args.cold_warm:
        from wbc_jax.rollout import distributed

        if args.what != "rollout" or args.campaign is None:
            raise InputError("--cold-warm: expected with rollout --campaign SPEC (the spec's campaign run fresh, then "
                             "warm)")
        if distributed.resolve(args.coordinator, args.num_processes, args.process_id,
                               args.local_device_ids) is not None:
            raise InputError("--cold-warm: expected in a one-process bench (its runs are one-GPU campaigns); drop "
                             "--coordinator / --num-processes")
    if args.qp is not None:
        from wbc_jax.bench.qp_audit import variants

        try:
            variants([args.qp])
        except ValueError as e:
            raise InputError(f"--qp: {e}") from None
    if args.what in ("rollout", "trace"):
        from wbc_jax.physics.backend import BACKENDS, resolve_backend
        from wbc_jax.rollout import resolve_sensing

        names = [x for x in str(args.backend).split(",") if x]
        try:
            if not names:
                raise ValueError("empty list")
            if args.what == "trace" and len(names) > 1:
                raise ValueError("trace takes one backend")
            for x in names:
                name, _, sensing = x.partition(":")
                resolve_sensing(sensing or "auto", resolve_backend(name), args.substeps)
        except ValueError as e:
            raise InputError(f"--backend {args.backend!r}: {e} (expected a comma-separated list of "
                             f"{', '.join(BACKENDS)}, each optionally with :auto, :exact or :delayed)") from None
    return sizes


def demo_args(args: argparse.Namespace) -> None:
    """Bounded, finite demo arguments (user errors before anything is built)."""
    from wbc_jax.errors import LimitError

    lo, hi = DISTANCE_RANGE
    bounds = {"seconds": (0.0, MAX_SECONDS, "0 < value <= 600 [s]"), "distance": (lo, hi, f"{lo} <= value <= {hi} [m]"),
              "push_at": (0.0, 1.0, "0 < value < 1 (fraction of the planned duration)")}
    for name, (a, b, text) in bounds.items():
        v = getattr(args, name)
        if v is not None and not (a < v <= b if name == "seconds" else a <= v <= b if name == "distance"
                                  else a < v < b):
            raise LimitError(f"--{name.replace('_', '-')} = {v}: expected {text}")
    if not 1 <= args.iters <= 1000:
        raise LimitError(f"--iters = {args.iters}: expected 1 <= value <= 1000")
