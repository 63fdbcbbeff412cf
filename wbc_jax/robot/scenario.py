"""Factor values (object mass m, tray friction mu, object side d) applied to models.

Batching follows MuJoCo Playground's domain randomisation: :func:`batch_model` returns
``(batched_model, in_axes)`` where only the object fields carry a leading run axis, for use as
``jax.vmap(f, in_axes=(in_axes, 0))(batched_model, data)``. Derived fields are kept consistent:
cube inertia from m and d, contact-sphere positions and box size from d, the constraint
inverse weights of the object's body and dofs from its mass and inertia.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path
from typing import NamedTuple

import jax
import mujoco
import numpy as np

from wbc_jax.errors import FactorError
from wbc_jax.robot.model import mjcf_dir, scene_path
from wbc_jax.runtime.transfer import to_device
from wbc_jax.spatial import cube_inertia
from wbc_jax.types import RobotIds

MU_RANGE = (0.0, 5.0)  # exclusive lower bound, inclusive upper [-]
M_RANGE = (0.0, 20.0)  # object mass [kg]
# torsional / rolling friction of the object contacts (MuJoCo pair friction entries 3..5)
PAIR_FRICTION_TAIL = (0.005, 0.0001, 0.0001)


class Factors(NamedTuple):
    """Per-run factor values, each (B,).

    Attributes:
        m: object mass [kg].
        mu: object/tray Coulomb friction [-].
        d: object side length [m].
    """

    m: np.ndarray
    mu: np.ndarray
    d: np.ndarray


def validate_factors(ids: RobotIds, m, mu, d) -> Factors:
    """Check physical ranges; return float arrays of one common length B.

    Raises:
        FactorError: naming the offending value and the allowed range.
    """
    m, mu, d = (np.atleast_1d(np.asarray(x, dtype=float)) for x in (m, mu, d))
    try:
        m, mu, d = np.broadcast_arrays(m, mu, d)
    except ValueError:
        raise FactorError(f"factor arrays have incompatible lengths: m {m.shape}, mu {mu.shape}, d {d.shape}") from None
    d_max = float(2 * min(ids.tray_half[0], ids.tray_half[1]))
    d_min = float(2 * ids.obj_sphere_radius)
    checks = (
        ("m", m, M_RANGE[0], M_RANGE[1], "kg"),
        ("mu", mu, MU_RANGE[0], MU_RANGE[1], ""),
        ("d", d, d_min, d_max, "m"),
    )
    for name, x, lo, hi, unit in checks:
        bad = ~np.isfinite(x) | (x <= lo) | (x > hi)
        if bad.any():
            v = x[np.argmax(bad)]
            raise FactorError(
                f"factor {name} = {v:g} {unit} is out of range: expected {lo:g} < {name} <= {hi:g} {unit}".rstrip()
            )
    return Factors(m.copy(), mu.copy(), d.copy())


def object_fields(ids: RobotIds, f: Factors, geom_pos0: np.ndarray) -> dict[str, np.ndarray]:
    """Per-run values (leading axis B) of the model fields that depend on the factors.

    Args:
        ids: static ids.
        f: validated factors, each (B,).
        geom_pos0: (ngeom, 3) nominal geom positions (used for the contact-sphere signs).

    Returns:
        dict field name -> rows for the object's entries only:
        body_mass (B,), body_inertia (B, 3), box size (B, 3), sphere pos (B, 4, 3),
        pair_friction (B, 4, 5), body_invweight0 (B, 2), dof_invweight0 (B, 6).
    """
    B = f.m.shape[0]
    half = f.d / 2
    inertia = cube_inertia(f.m, f.d)
    r = ids.obj_sphere_radius
    signs = np.sign(geom_pos0[ids.obj_contact_geom])  # (4, 3)
    off = (half - r)[:, None, None] * np.ones((1, 4, 3))
    sphere_pos = signs[None] * off
    fr = np.concatenate([np.stack([f.mu, f.mu], -1), np.broadcast_to(PAIR_FRICTION_TAIL, (B, 3))], -1)
    return {
        "body_mass": f.m,
        "body_inertia": np.repeat(inertia[:, None], 3, axis=1),
        "box_size": np.repeat(half[:, None], 3, axis=1),
        "sphere_pos": sphere_pos,
        "pair_friction": np.repeat(fr[:, None, :], 4, axis=1),
        # free body with its CoM at the body origin: M = diag(m I3, I I3)
        "body_invweight0": np.stack([1.0 / f.m, 1.0 / inertia], -1),
        "dof_invweight0": np.concatenate([np.repeat(1.0 / f.m[:, None], 3, 1),
                                          np.repeat(1.0 / inertia[:, None], 3, 1)], -1),
    }


def batch_model(mjx_model, mj_model: mujoco.MjModel, ids: RobotIds, f: Factors, ground_mu=None):
    """A batched mjx.Model with per-run object fields, and its vmap ``in_axes``.

    Args:
        mjx_model: the unbatched MJX model.
        mj_model: the MuJoCo C model it came from (for nominal values).
        ids: static ids (the scene must contain the object).
        f: validated factors, each (B,).
        ground_mu: (B,) sliding friction of every foot/ground pair (``ids.foot_pair``) per run; None: the scene's.

    Returns:
        (batched_model, in_axes): fields body_mass, body_inertia, body_invweight0, geom_size,
        geom_pos, pair_friction and dof_invweight0 carry a leading axis B; in_axes has 0 there and
        None elsewhere.
    """
    B = f.m.shape[0]
    v = object_fields(ids, f, mj_model.geom_pos)
    ob, dof = ids.obj_body, ids.obj_dof_adr

    def field(name, cols, value):
        """(B, ...) copy of mjx_model's field with [:, cols] = value, built on the host, placed once."""
        x = np.asarray(getattr(mjx_model, name))
        out = np.array(np.broadcast_to(x, (B,) + x.shape))
        out[:, cols] = np.asarray(value, x.dtype)
        return out

    friction = field("pair_friction", ids.obj_pair, v["pair_friction"])
    if ground_mu is not None:  # both sliding entries of the foot pairs; torsional and rolling stay the scene's
        feet = np.asarray(ids.foot_pair).ravel()
        friction[:, feet, 0:2] = np.asarray(ground_mu, friction.dtype).reshape(B, 1, 1)

    fields = {
        "body_mass": field("body_mass", ob, v["body_mass"]),
        "body_inertia": field("body_inertia", ob, v["body_inertia"]),
        "body_invweight0": field("body_invweight0", ob, v["body_invweight0"]),
        "dof_invweight0": field("dof_invweight0", slice(dof, dof + 6), v["dof_invweight0"]),
        "geom_size": field("geom_size", ids.obj_box_geom, v["box_size"]),
        "geom_pos": field("geom_pos", ids.obj_contact_geom, v["sphere_pos"]),
        "pair_friction": friction,
    }
    fields = {k: to_device(x) for k, x in fields.items()}
    batched = mjx_model.tree_replace(fields)
    in_axes = jax.tree_util.tree_map(lambda _: None, mjx_model)
    in_axes = in_axes.tree_replace({k: 0 for k in fields})
    return batched, in_axes


def single_run_mj_model(scene_xml: str, m: float, mu: float, d: float) -> mujoco.MjModel:
    """Compile a MuJoCo C model of one run from the scene XML with the factor values set in the spec.

    This is an independent path (MuJoCo's compiler derives inertia-dependent constants itself),
    used as the reference for :func:`batch_model`.
    """
    spec = mujoco.MjSpec.from_file(str(scene_xml))
    body = spec.body("object")
    body.mass = float(m)
    body.inertia = [m * d**2 / 6.0] * 3
    box = spec.geom("object")
    box.size = [d / 2] * 3
    for i in range(4):
        g = spec.geom(f"obj_c{i}")
        r = g.size[0]
        g.pos = np.sign(np.asarray(g.pos)) * (d / 2 - r)
        p = spec.pair(f"obj_c{i}_tray")
        p.friction = [mu, mu, *PAIR_FRICTION_TAIL]
    return spec.compile()


def scene_variant(scene: str, options: dict | None = None, obj_solref: tuple | None = None,
                  obj_solimp: tuple | None = None, out_dir: str | None = None) -> str:
    """A copy of scene ``scene`` ('flat', 'transport' or a path) with MuJoCo's contact law changed.

    Args:
        options: ``<option>`` attributes to set, e.g. ``{"cone": "elliptic", "impratio": 1, "iterations": 50,
            "noslip_iterations": 10}``.
        obj_solref, obj_solimp: the object/tray pairs' ``solref`` (2 numbers) and ``solimp`` (5 numbers).
        out_dir: folder for the copy (beside a copy of the robot file it includes); None: a new temporary folder.

    Returns:
        The new scene file's path.
    """
    src = scene_path(scene)
    text = src.read_text()
    for key, value in (options or {}).items():
        value = f"{value:g}" if isinstance(value, float) else str(value)
        if re.search(rf'<option[^>]*\b{key}="', text):
            text = re.sub(rf'(<option[^>]*\b{key}=")[^"]*"', rf'\g<1>{value}"', text, count=1)
        else:
            text = text.replace("<option ", f'<option {key}="{value}" ', 1)
    for attr, value in (("solref", obj_solref), ("solimp", obj_solimp)):
        if value is not None:
            words = " ".join(f"{v:g}" for v in value)
            text = re.sub(rf'(<pair name="obj_c\d_tray"[^>]*\b{attr}=")[^"]*"', rf'\g<1>{words}"', text)
    folder = Path(out_dir or tempfile.mkdtemp(prefix="wbc_scene_"))
    folder.mkdir(parents=True, exist_ok=True)
    for name in re.findall(r'<include file="([^"]+)"', text):
        _write_atomic(folder / name, (mjcf_dir() / name).read_text())
    out = folder / src.name
    _write_atomic(out, text)
    return str(out)


def _write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename (processes writing the same scene at once
    never read a partial file)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
