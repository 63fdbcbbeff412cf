"""Command line of the S study (:mod:`wbc_jax.studies.s_cause`).

``python -m wbc_jax.studies.s_cause_cli record --out REC.npz [--spec FILE] [--seconds 3] [--option cone=elliptic]``
runs a small batch with the dense log (default: :data:`DEFAULT_SPEC`, flat ground, mu 0.4 / 0.7 / 1.0 x velocity
noise 0 / 0.02 x 2 repetitions with common random numbers); ``--option KEY=VALUE`` sets a MuJoCo ``<option>``
attribute of the scene for the closed loop.

``python -m wbc_jax.studies.s_cause_cli analyse REC.npz [--from 1.5] [--option KEY=VALUE ...]`` prints, per run, S
and the parts of the object's acceleration over the steps after ``--from`` seconds
(:func:`wbc_jax.studies.s_cause_replay.decompose`), then S of each run's tray motion replayed in MuJoCo C at mu 0.4,
0.7 and 1.0 under the recording's contact law and under each ``--option`` set (a comma-separated list of KEY=VALUE
per ``--option``, e.g. ``--option cone=elliptic,impratio=1``).
"""

from __future__ import annotations

import argparse

from wbc_jax.studies import s_cause_replay as replay

DEFAULT_SPEC = {
    "campaign": dict(name="s_cause", reps=2, seed=11, scene="flat", distance=0.3, speed=0.13, extra_seconds=0.0,
                     qp_iters=4),
    "factors": dict(mu=[0.4, 0.7, 1.0], qvel_noise_std=[0.0, 0.02]),
    "perturbations": dict(object_xy_mm=3.0, object_yaw_deg=3.0, base_speed_std=0.02),
}
REPLAY_MU = (0.4, 0.7, 1.0)


def _options(text: str) -> dict:
    """``"cone=elliptic,impratio=1"`` -> {"cone": "elliptic", "impratio": 1.0} (numbers as floats)."""
    out = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            out[key.strip()] = value.strip()
    return out


def _record(args) -> int:
    from wbc_jax.campaign.spec import load_spec, parse_spec
    from wbc_jax.robot.scenario import scene_variant
    from wbc_jax.runtime.jaxcfg import configure
    from wbc_jax.studies import s_cause

    configure()
    spec = load_spec(args.spec) if args.spec else parse_spec(DEFAULT_SPEC, "<s_cause default>")
    options = {k: v for text in args.option for k, v in _options(text).items()}
    scene = scene_variant(spec.campaign["scene"], options) if options else None
    rec = s_cause.record(spec, args.seconds, scene_file=scene)
    s_cause.save(rec, args.out)
    print(f"wrote {args.out}: {rec.qvel.shape[0]} runs x {rec.qvel.shape[1]} steps")
    return 0


def _analyse(args) -> int:
    from wbc_jax.robot.scenario import scene_variant
    from wbc_jax.studies import s_cause

    rec = s_cause.load(args.recording)
    dz = rec.design
    span = rec.t > args.start
    adr = replay.resolve_ids(replay.single_run_mj_model(rec.scene, 0.3, 0.7, 0.08)).obj_dof_adr
    print(f"closed loop, steps after {args.start:g} s: S and the mean parts of ||vdot_b|| [m/s^2]")
    for i in range(dz.n):
        parts = replay.decompose(rec, i, walk_start_s=args.start)["walking"]
        print(f"run {i:2d} mu {dz.mu[i]:.2f} noise {dz.qvel_noise_std[i]:.3f}: S {1 / parts.total:.4f} "
              + " ".join(f"{k} {v:.4f}" for k, v in parts._asdict().items()))
    laws = {"recorded": None}
    laws.update({text: scene_variant(rec.scene, _options(text)) for text in args.option})
    print("replay in MuJoCo C (the run's tray motion, only the object free): S at mu "
          + " / ".join(f"{mu:g}" for mu in REPLAY_MU))
    for name, scene in laws.items():
        for i in range(dz.n):
            s = [replay.smoothness(rec.qvel0[i], replay.replay_object(rec, i, scene, mu), adr, rec.dt, span)
                 for mu in REPLAY_MU]
            print(f"{name}: run {i:2d} (mu {dz.mu[i]:.2f}, noise {dz.qvel_noise_std[i]:.3f}): "
                  + " / ".join(f"{x:.4f}" for x in s) + f"  (change mu 0.4 -> 1.0: {100 * (s[-1] / s[0] - 1):+.1f} %)")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m wbc_jax.studies.s_cause_cli", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="run a small batch with a dense per-step log")
    rec.add_argument("--out", required=True, help="the recording (.npz)")
    rec.add_argument("--spec", help="campaign spec (default: the built-in flat-ground spec)")
    rec.add_argument("--seconds", type=float, default=3.0, help="simulated time [s]")
    rec.add_argument("--option", action="append", default=[], help="KEY=VALUE[,KEY=VALUE] MuJoCo <option> attributes")
    ana = sub.add_parser("analyse", help="decompose a recording's object acceleration and replay it in MuJoCo C")
    ana.add_argument("recording")
    ana.add_argument("--from", dest="start", type=float, default=1.5, help="first time analysed [s]")
    ana.add_argument("--option", action="append", default=[], help="KEY=VALUE[,KEY=VALUE]: a contact law to replay")
    args = ap.parse_args(argv)
    return _record(args) if args.command == "record" else _analyse(args)


if __name__ == "__main__":
    raise SystemExit(main())
