"""What a campaign records about itself: the run's identity (what a checkpoint must match) and ``manifest.json``.

:func:`run_identity` names everything that determines a campaign's results (spec, gains, backend, numerics
versions, run count); :func:`campaign_manifest` assembles ``manifest.json``: provenance (spec, gains, versions, git
commit), device, layout and what shaped the compiled program, the design's size, timings and the outcome
(successes, failures, warnings, metric means); :func:`study_manifest` the same provenance for ``demo`` and ``trot``.
"""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
import time
from importlib import metadata
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from wbc_jax.campaign import controllers
from wbc_jax.campaign.results import Summary, nan_none
from wbc_jax.campaign.size import n_runs_of
from wbc_jax.campaign.spec import Spec
from wbc_jax.rollout import distributed
from wbc_jax.runtime import jaxcfg

COMMAND = "wbc-jax campaign"
PACKAGES = ("wbc_jax", "jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy", "scipy", "statsmodels", "pandas")
NUMERICS = ("wbc_jax", "jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy")  # their versions can change a rollout


class Timing(NamedTuple):
    """Wall-clock figures of a campaign [s].

    Attributes:
        total: the whole command (imports included; earlier sessions of a resumed run included).
        rollout: the chunks (earlier sessions included).
        imports: importing the rollout's modules.
        setup: from the imports to the first chunk's dispatch (spec, checks, build).
        compile_estimate: the first chunk's wall time less a steady chunk's (None with no steady chunk).
        first_chunk: the first chunk of this process (None when none ran).
        env_steps_per_s: physics steps of all runs per second of steady chunks.
        chunk_walls: each chunk's wall time in order, every session's (a session's first includes compilation).
    """

    total: float
    rollout: float
    imports: float
    setup: float
    compile_estimate: float | None
    first_chunk: float | None
    env_steps_per_s: float
    chunk_walls: tuple = ()


def versions() -> dict:
    """The Python version and those of :data:`PACKAGES` (None for one not installed)."""
    out = {"python": platform.python_version()}
    for p in PACKAGES:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = None
    return out


def git_commit(package_dir: Path | None = None) -> str | None:
    """HEAD of this project's checkout, with ``-dirty`` when tracked files differ from it; None when the package
    is not in its own repository (outside git, or inside another repository that does not track this package).

    Args:
        package_dir: the ``wbc_jax`` folder (default: this package's).
    """
    pkg = (package_dir or Path(__file__).resolve().parents[1]).resolve()
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=pkg, capture_output=True, text=True,
                             timeout=5)
        root = Path(top.stdout.strip()).resolve() if top.returncode == 0 and top.stdout.strip() else None
        if root is None or pkg.parent != root:  # the project's root holds wbc_jax/ (pyproject.toml beside it)
            return None
        tracked = subprocess.run(["git", "ls-files", "--error-unmatch", "wbc_jax/__init__.py", "pyproject.toml"],
                                 cwd=root, capture_output=True, text=True, timeout=5)
        if tracked.returncode != 0:
            return None
        r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
        head = r.stdout.strip()
        if r.returncode != 0 or not head:
            return None
        st = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True,
                            text=True, timeout=10)
        return head + ("-dirty" if st.returncode != 0 or st.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def gains_hash(gains=None) -> str:
    """SHA-256 of every gains leaf's dtype, shape and value (None: the transport's default gains)."""
    from wbc_jax.control.transport import default_gains

    h = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(default_gains() if gains is None else gains):
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def run_identity(spec: Spec, gains=None, n_runs: int | None = None, backend: str = "jax") -> dict:
    """Everything that determines a campaign's results, as the dict a checkpoint must match.

    Args:
        spec: the validated spec (its hash).
        gains: controller gains (None: the defaults, hashed as such).
        n_runs: number of runs (default: the spec's design size).
        backend: the simulation backend ("jax").

    Returns:
        dict with ``spec_hash``, ``gains_hash`` (:func:`gains_hash`), ``backend``, ``platform`` (jax's default
        backend: cpu, gpu, ...), ``versions`` (of :data:`NUMERICS`), ``n_runs`` and ``deterministic_ops`` (XLA's
        GPU deterministic ops: :func:`wbc_jax.runtime.jaxcfg.deterministic_ops`).
    """
    found = versions()
    return dict(spec_hash=spec.hash, gains_hash=gains_hash(gains), backend=backend, platform=jax.default_backend(),
                versions={p: found.get(p) for p in NUMERICS},
                n_runs=int(n_runs if n_runs is not None else n_runs_of(spec)),
                deterministic_ops=jaxcfg.deterministic_ops())


def device_record() -> dict:
    """This process's device: backend, kind, count, host name and CPU count."""
    return dict(backend=jax.default_backend(), kind=jax.devices()[0].device_kind, count=jax.device_count(),
                host=platform.node(), cpu_count=os.cpu_count())


def program_record(n_runs: int, spread_mode: str, logs_per_chunk: int, n_chunks: int) -> dict:
    """What shaped the campaign's compiled chunk program, as a replay needs it to compile the same one.

    Returns:
        dict with ``spread`` (one, mesh, blocks: :mod:`wbc_jax.rollout.spread`), ``devices`` (the devices one
        program spans: the mesh's size, else 1), ``parts`` (the batch's parts: devices of the mesh, processes of
        the blocks, else 1), ``per_device_runs`` (the runs each part's program steps, padding included), ``dealt``
        (the runs dealt to the parts in turn, run r to part r % parts: the blocks; else cut in contiguous parts),
        ``padded_runs`` (parts x per_device_runs; the padding repeats the last run), ``logs_per_chunk``,
        ``n_chunks``, ``platform`` and ``xla`` (:func:`wbc_jax.runtime.jaxcfg.xla_record`).
    """
    parts = {"mesh": jax.device_count(), "blocks": jax.process_count()}.get(spread_mode, 1)
    per_device = -(-int(n_runs) // parts)
    return dict(spread=spread_mode, devices=parts if spread_mode == "mesh" else 1, parts=parts,
                per_device_runs=per_device, padded_runs=per_device * parts, dealt=spread_mode == "blocks",
                logs_per_chunk=int(logs_per_chunk),
                n_chunks=int(n_chunks), platform=jax.default_backend(), xla=jaxcfg.xla_record())


def session_record(chunks_before: int) -> dict:
    """This process's session of a campaign (a resumed one has several): git commit, versions, host, start time
    and the chunks done before it."""
    return dict(git_commit=git_commit(), versions=versions(), host=platform.node(),
                started=time.strftime("%Y-%m-%d %H:%M:%S %z"), chunks_before=int(chunks_before))


def study_manifest(command: str, *, arguments: dict, clock_s: dict, seeds=(), physics_backend: str | None = None,
                   sensing: str | None = None) -> dict:
    """``manifest.json`` of a study command (``wbc-jax demo``, ``wbc-jax trot``): what ran, with which code, where.

    Args:
        command: the command, e.g. "wbc-jax demo".
        arguments: its arguments (JSON values).
        clock_s: clock (wall) times of its stages [s], e.g. ``total``, ``compile_and_first_chunk``.
        seeds: the random seeds of its runs (none: the runs draw nothing random).
        physics_backend, sensing: the rollout's physics backend and sensing (None: not a transport rollout).

    Returns:
        dict with the command, arguments, versions, git commit, device, XLA settings, physics backend, sensing,
        seeds, ``clock_time_s`` and when it was written.
    """
    return dict(command=command, arguments=arguments, versions=versions(), git_commit=git_commit(),
                device=device_record(), xla=jaxcfg.xla_record(), physics_backend=physics_backend, sensing=sensing,
                seeds=[int(s) for s in seeds], clock_time_s=clock_s, written=time.strftime("%Y-%m-%d %H:%M:%S %z"))


def campaign_manifest(spec: Spec, built, df, summary: Summary, timing: Timing, *, identity: dict, gains,
                      sensing: str, spread_mode: str, chunk_s: float, sessions: list, files: list) -> dict:
    """The content of ``manifest.json``.

    Args:
        spec: the campaign's spec.
        built: its :class:`wbc_jax.campaign.build.Built` (Sim, design, planned duration, chunk count).
        df: the results table (one row per run).
        summary: :func:`wbc_jax.campaign.results.summarize` of ``df``.
        timing: the wall-clock figures.
        identity: :func:`run_identity` of the run.
        gains: the gains given (None: the defaults).
        sensing: the resolved ``campaign.sensing``.
        spread_mode: how the runs were spread over devices (``wbc_jax.rollout.spread``: one, mesh, blocks).
        chunk_s: simulated seconds per chunk.
        sessions: :func:`session_record` of every session (more than one: resumed; each commit and version).
        files: what the campaign writes into its folder (``--force`` replaces only these).
    """
    sim = built.sim
    ok = df.success
    return dict(
        command=COMMAND, spec_path=str(spec.path), spec_hash=spec.hash, spec_file_sha256=spec.text_sha256,
        spec=spec.canonical(), **({"plugin_sha256": spec.plugin_sha256} if spec.plugin else {}),
        default_gains=gains is None, gains_hash=identity["gains_hash"], versions=versions(),
        git_commit=git_commit(), git_commits=sorted({s["git_commit"] for s in sessions if s.get("git_commit")}),
        sessions=sessions,
        physics_backend=identity["backend"], sensing=sensing, device=device_record(),
        layout=dict(distributed.layout_record(), spread=spread_mode),
        program=program_record(built.design.n, spread_mode, built.logs_per_chunk, built.n_chunks),
        n_runs=built.design.n, n_cells=summary.n_cells, reps=spec.reps, seeds=[int(s) for s in built.design.seed],
        simulated_s=built.n_chunks * chunk_s, planned_s=built.planned_s, chunk_s=chunk_s, n_chunks=built.n_chunks,
        control_dt_s=sim.dt_control, wall_s_total=timing.total, wall_s_rollout=timing.rollout,
        import_s=timing.imports, setup_s=timing.setup, compile_s_estimate=timing.compile_estimate,
        first_chunk_s=timing.first_chunk, env_steps_per_s=timing.env_steps_per_s,
        chunk_wall_s=[round(w, 3) for w in timing.chunk_walls],
        resumed=len(sessions) > 1, n_success=int(ok.sum()), failures_per_cell=summary.failures_per_cell,
        failed_runs=summary.failed_runs, qp_flagged_runs=summary.qp_flagged_runs,
        qp_flag_fraction_max=nan_none(df.qp_flag_fraction.max()), warnings=summary.warnings,
        metric_means={k: float(df.loc[ok, k].mean()) if ok.any() else None
                      for k in controllers.info(spec.campaign).means},
        constraint_solver=dict(iterations=int(sim.robot.mj_model.opt.iterations),
                               cap_fraction_mean=nan_none(df.solver_cap_fraction.mean()),
                               cap_fraction_max=nan_none(df.solver_cap_fraction.max())),
        files=files)


def setup_figures(clock: dict) -> dict:
    """The manifest's figures of a Warp campaign's setup from its ``clock``: MuJoCo Warp's kernels compiled (or
    loaded from its cache) during setup, the model's own kernels compiled at each Warp callable's first call, the
    chunk program traced and compiled from the batch's shapes."""
    out = {}
    if "warp_preload_s" in clock:
        out["warp_preload_s"] = clock["warp_preload_s"]
    if "warp_ahead" in clock:
        out["warp_compile_ahead"] = clock["warp_ahead"].summary()
    if "chunk_ahead_s" in clock:
        out["chunk_compiled_ahead_s"] = round(clock["chunk_ahead_s"], 3)
    return out
