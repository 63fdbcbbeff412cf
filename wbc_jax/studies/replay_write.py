"""One replayed run's folder ``OUT/run_N/``: trajectory, plots, video and a manifest, written atomically."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from wbc_jax.campaign.manifest import device_record, git_commit, versions
from wbc_jax.io_utils import atomic_dir, write_json_atomic
from wbc_jax.metrics.paper import FALL_Z_COURSE, FALL_Z_FLAT
from wbc_jax.physics.clearance import clearance_pairs
from wbc_jax.planner.scene_geometry import scene_geometry
from wbc_jax.robot.scenario import single_run_mj_model
from wbc_jax.runtime import jaxcfg
from wbc_jax.studies.replay_check import Check, outcome
from wbc_jax.studies.replay_inputs import Recorded
from wbc_jax.studies.replay_output import clearance, sample_times, write_plots, write_trajectory
from wbc_jax.studies.replay_sim import Replayed
from wbc_jax.studies.replay_video import write_video

COMMAND = "wbc-jax replay"
BEFORE_FAILURE_S = 5.0  # [s] a failed run's default video window starts this long before the failure
AFTER_FAILURE_S = 1.0  # [s] and ends this long after it (the run is frozen from then on)


def _plain(x):
    """A JSON value: NaN and inf as None, numpy scalars as Python values, containers element by element."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def default_window(time_s: np.ndarray, failure_s: float) -> tuple[float, float]:
    """The video's window [s] when none is given: the whole run; for a failed run the seconds around its failure
    (:data:`BEFORE_FAILURE_S` before to :data:`AFTER_FAILURE_S` after)."""
    if not math.isfinite(failure_s):
        return 0.0, float(time_s[-1])
    return max(0.0, failure_s - BEFORE_FAILURE_S), min(float(time_s[-1]), failure_s + AFTER_FAILURE_S)


def levels_text(recorded: Recorded, run: int) -> str:
    """``"m 0.2, mu 0.4, d 0.06, rep 0"``: the run's factor levels and repetition from results.csv."""
    row = recorded.results.iloc[run]
    return ", ".join([*(f"{k} {row[k]}" for k in recorded.spec.factors), f"rep {row['rep']}"])


def _manifest(recorded: Recorded, replayed: Replayed, check: Check, run: int, window, video: tuple) -> dict:
    """The run folder's ``manifest.json``: what was replayed, how, where, and the comparison with the campaign."""
    man, built = recorded.manifest, replayed.built
    row = recorded.results.iloc[run]
    return _plain(dict(
        command=COMMAND, campaign=str(recorded.folder), run=run,
        levels={k: row[k] for k in recorded.spec.factors}, rep=row["rep"], seed=row["seed"],
        spec_path=str(recorded.spec.path), spec_hash=man["spec_hash"], gains_hash=man["gains_hash"],
        physics_backend=man["physics_backend"], sensing=man["sensing"],
        batch=dict(campaign_runs=built.design.n, chunks=built.n_chunks, same_layout=replayed.same_layout,
                   batches=[len(rows) for rows in replayed.batches],
                   whole_batch=all(np.array_equal(rows, np.minimum(np.arange(len(rows)) + rows[0], built.design.n - 1))
                                   for rows in replayed.batches)),
        xla=jaxcfg.xla_record(), campaign_program=man.get("program"), notes=replayed.notes,
        device=device_record(), campaign_device=man.get("device"), versions=versions(), git_commit=git_commit(),
        campaign_git_commit=man.get("git_commit"), outcome=outcome(check.replay),
        check=dict(equal=check.equal, bit_for_bit=check.bit_for_bit, max_relative_difference=check.max_rel,
                   differences=check.differences, campaign=check.campaign, replay=check.replay),
        window_s=list(window), video=video[0], video_note=video[1], wall_s=replayed.wall_s,
        written=time.strftime("%Y-%m-%d %H:%M:%S %z")))


def _events(replayed: Replayed, run: int, failure_s: float, window, times: np.ndarray) -> dict:
    """What ``plots.png`` marks: the run's push (start [s], duration [s], force [N]), its failure instant [s] and
    the video's window (None when it spans the whole run)."""
    push = replayed.built.batch.push
    force = float(np.linalg.norm(np.asarray(push.force)[run]))
    whole = window[0] <= times[0] and window[1] >= times[-1]
    return dict(push=(float(np.asarray(push.t0)[run]), float(np.asarray(push.duration)[run]), force),
                failure_s=failure_s, window=None if whole else window)


def write_run(folder: Path, recorded: Recorded, replayed: Replayed, check: Check, window=None,
              video: bool = True) -> str:
    """Write ``folder`` (new, or an earlier replay's with the caller's ``--force`` checked): ``trajectory.npz``,
    ``plots.png``, ``video.mp4`` or ``video.gif`` and ``manifest.json``. ``window``: (start, end) [s] of the video
    (None: :func:`default_window`). Returns the video's note: why none or a GIF was written ("" for an MP4, or
    without ``video``)."""
    sim, dz = replayed.built.sim, replayed.built.design
    logs, result = replayed.logs[check.run], replayed.results[check.run]
    times = sample_times(len(np.asarray(logs.t)), sim.log_every, sim.dt_control)
    failure_s = float(result.get("failure_s", math.nan))
    window = tuple(window) if window is not None else default_window(times, failure_s)
    mj_model = single_run_mj_model(sim.robot.path, float(dz.m[check.run]), float(dz.mu[check.run]),
                                   float(dz.d[check.run]))
    clear_m, closest = clearance(mj_model, clearance_pairs(sim.robot), np.asarray(logs.qpos, float))
    course = scene_geometry(sim.robot).is_course
    limits = dict(tau_max=np.asarray(sim.robot.ids.tau_max), fall_z=FALL_Z_COURSE if course else FALL_Z_FLAT)
    title = (f"campaign {recorded.spec.campaign['name']!r}, run {check.run} ({levels_text(recorded, check.run)}): "
             f"{outcome(check.replay)}")
    with atomic_dir(folder, command=COMMAND) as tmp:
        write_trajectory(tmp / "trajectory.npz", logs, times, dict(
            clearance_m=clear_m, clearance_pair=closest, tau_max=limits["tau_max"], failure_s=failure_s,
            run=check.run, m=dz.m[check.run], mu=dz.mu[check.run], d=dz.d[check.run]))
        write_plots(tmp / "plots.png", times, logs, limits, clear_m * 1e3, _events(replayed, check.run, failure_s,
                                                                                   window, times), title)
        made = (write_video(tmp, mj_model, np.asarray(logs.qpos, float), times, window,
                            (failure_s, check.replay["fail_reason"]), sim.robot.ids.trunk_body)
                if video else (None, "not rendered (--no-video)"))
        write_json_atomic(tmp / "manifest.json", _manifest(recorded, replayed, check, check.run, window, made))
    return made[1] if video else ""
