"""What a campaign checks before anything is built or compiled: its output folder, its checkpoint, its size.

Process 0 claims the output folder (:func:`wbc_jax.io_utils.claim_out_dir`: one command at a time) and checks it
(:func:`wbc_jax.io_utils.check_out_dir`); a checkpoint of finished chunks beside it is never discarded implicitly:
without ``--resume`` the command refuses unless ``--force``; with ``--resume`` its identity must match this run's.
Every process checks the batch's size against the machine's memory; a problem found by process 0 is every
process's (``distributed.agree``).
"""

from __future__ import annotations

from pathlib import Path

import jax

from wbc_jax.campaign import checkpoint
from wbc_jax.campaign import gains as gains_mod
from wbc_jax.campaign.build import backend_of, check_qp, qp_changes, sensing_of, with_backend
from wbc_jax.campaign.manifest import COMMAND, run_identity
from wbc_jax.campaign.size import check_size, memory_need, n_runs_of, own_memories
from wbc_jax.campaign.spec import Spec, load_spec
from wbc_jax.errors import CheckpointError, OutputError, WbcJaxError
from wbc_jax.io_utils import check_not_in_use, check_out_dir, claim_out_dir
from wbc_jax.rollout import distributed

WRITES = ("results.csv", "manifest.json", "report", "report_error.txt")  # what a campaign writes into DIR
LARGE_RUNS = 20_000  # from this many runs the setup (design, plans, initial states) takes long enough to announce


def checked_spec(spec_path: str, backend: str | None, gains) -> tuple[Spec, str, dict]:
    """The campaign's spec with ``--backend`` applied (``backend``; None: the spec's), checked before anything is
    built or written: the physics backend and its sensing, the QP's settings, ``gains`` against the design.
    Returns (spec, physics backend, the run's identity: :func:`wbc_jax.campaign.manifest.run_identity`).

    Raises:
        SpecError: a bad spec, combination or gains (one line naming the file and key).
    """
    spec = with_backend(load_spec(spec_path), backend)
    physics = backend_of(spec)
    sensing_of(spec)  # a bad combination fails here, before anything is written
    check_qp(spec)
    gains_mod.check_design(spec, gains)
    return spec, physics, run_identity(spec, gains, backend=physics)


def check_outputs(spec: Spec, out, identity: dict, *, resume: bool, force: bool, allow_large: bool,
                  inputs: tuple, backend_flag: str | None, parts: int = 1,
                  claim: bool = True) -> tuple[Path | None, Path | None]:
    """Process 0's output folder and checkpoint folder (None elsewhere), claimed and checked with the spec's size
    (``parts``: the devices the runs are split over, :func:`wbc_jax.campaign.size.memory_need`). ``claim``:
    False checks that no other command holds the folder without claiming it (a dry run: nothing is created).

    Raises:
        OutputError: DIR in use, unusable, or a checkpoint of finished chunks without ``resume`` or ``force``.
        CheckpointError: with ``resume``, a checkpoint of another run (``--backend`` named where it differs).
        LimitError: the batch would not fit in memory (without ``allow_large``).
    """
    out_p = ck = problem = None
    try:  # process 0's output folder and checkpoint (the others write nothing and read neither)
        if distributed.is_writer():
            if claim:
                claim_out_dir(out, COMMAND)
            else:
                check_not_in_use(out)
            out_p = check_out_dir(out, COMMAND, force=force, inputs=[spec.path, *inputs], writes=WRITES)
            ck = checkpoint.ckpt_dir(out_p)
            meta = checkpoint.peek(ck)
            if resume:  # meta.json and the identity before the build and the compile; the state file after it
                _check_resume_backend(ck, meta, identity, backend_flag)
                checkpoint.read_meta(ck, identity, checkpoint.n_chunks_hint(ck))
            elif meta is not None and not force:
                raise OutputError(_unfinished(out, ck, meta))
        check_size(spec, allow_large, parts)
    except WbcJaxError as e:
        problem = e
    distributed.agree(problem)
    return out_p, ck


def _unfinished(out, ck: Path, meta: dict) -> str:
    """The refusal of a rerun beside a checkpoint (``meta``: its meta.json, {} when unreadable)."""
    try:
        done, total = int(meta["chunks_done"]), int(meta["n_chunks"])
    except (KeyError, TypeError, ValueError):
        return (f"--out {out}: {ck} holds an unreadable checkpoint; pass --force to start over (it is deleted), "
                "or delete it")
    return f"--out {out}: {done} of {total} chunks finished in {ck}; continue with --resume, or --force to start over"


def _check_resume_backend(ck: Path, meta: dict | None, identity: dict, backend_flag: str | None) -> None:
    """A checkpoint made on another physics backend: one line naming both and how to resume."""
    made = ((meta or {}).get("identity") or {}).get("backend")
    if made is None or made == identity["backend"]:
        return
    now = f"--backend {backend_flag}" if backend_flag else "the spec's campaign.backend"
    raise CheckpointError(f"{ck}: the checkpoint was made with the {made!r} physics backend, this run would use "
                          f"{identity['backend']!r} ({now}); resume with --backend {made}, or start over with --force")


def notes(spec: Spec, physics_backend: str, allow_large: bool, parts: int = 1) -> list[str]:
    """Lines to print before the build: Warp physics on a CPU is slow; the QP's factors are kept with Warp physics
    only; a large campaign's setup takes a while, and its memory estimate
    (:func:`wbc_jax.campaign.size.memory_need`)."""
    out = []
    if physics_backend == "warp" and jax.default_backend() == "cpu":
        out.append("warning: physics backend 'warp' on a CPU: MuJoCo Warp's kernels run on the CPU here, many "
                   "times slower than --backend jax")
    if spec.campaign["qp_reuse_factors"] and "reuse_factors" not in dict(qp_changes(spec)):  # the rule: qp_changes
        out.append(f"note: campaign.qp_reuse_factors = 1 applies with Warp physics only; with {physics_backend!r} "
                   "physics every control step factors its QP (docs/performance.md)")
    n = n_runs_of(spec)
    if n >= LARGE_RUNS or allow_large:
        large = " (--allow-large)" if allow_large else ""
        need, avail = memory_need(spec, parts)
        memory = (f"; about {need / 2**30:,.1f} GiB" + (" per device" if own_memories(parts) > 1 else "")
                  + (f" of {avail / 2**30:,.1f} GiB available" if avail else ""))
        out.append(f"setting up {n:,} runs{large}: design, plans and initial states first, then the first chunk"
                   + memory)
    return out
