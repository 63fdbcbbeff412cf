"""Transport-controller gains as TOML: ``best_gains.toml`` of ``wbc-jax tune``, read by ``wbc-jax campaign --gains``.

File format (stdlib ``tomllib``)::

    [gains]                     # any subset of the TransportGains leaves; the others keep their defaults
    kp_com = [2000.0, 2000.0, 2000.0]   # vector leaves: a list of their length, or one number for every component
    kp_obj = 250.0
    ...
    [info]                      # optional, free-form, not read (the tuner writes where the gains came from)

Every value must be finite and >= 0 (``tau_margin``: 0 < value <= 1); the QP's regularization weights
(:data:`REGULARIZATION`) must be > 0 and ``f_min`` <= ``f_max`` (otherwise every control step's QP is singular or
infeasible). An unknown table or leaf, a wrong type, a wrong length or an out-of-range value raises
:class:`wbc_jax.errors.SpecError` with one line naming the file and the key; the CLI turns it into exit code 2
before anything is written. :func:`check_design` applies the same rules to a spec's ``gain.*`` factors.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from wbc_jax.campaign.factors import GAIN_PREFIX, REGULARIZATION
from wbc_jax.campaign.spec import checked_number, spec_error
from wbc_jax.errors import InputError, SpecError
from wbc_jax.io_utils import read_capped

GAIN_MAX = 1e9  # largest accepted value of any leaf (a typo guard, far above any sensible gain)


def _defaults():
    from wbc_jax.control.transport import default_gains

    return default_gains()


def _toml_value(x: np.ndarray) -> str:
    """A finite number or vector as TOML, each number the shortest text that reads back to the same value of
    x's floating dtype (float32 gains stay exact through a write and a read)."""
    x = np.asarray(x)
    x = x.astype(x.dtype if np.issubdtype(x.dtype, np.floating) else float)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"gains must be finite to be written, got {x}")
    text = [_float(v) for v in x.ravel()]
    return text[0] if x.ndim == 0 else "[" + ", ".join(text) + "]"


def _float(v: np.floating) -> str:
    s = np.format_float_positional(v, unique=True, trim="0") if 1e-4 <= abs(v) < 1e16 or v == 0 else \
        np.format_float_scientific(v, unique=True, trim="0")
    return s.replace("e+", "e")


def gains_toml(gains, header: str = "", info: dict | None = None) -> str:
    """TOML text of a full (unbatched) TransportGains, ``header`` as leading comment lines, ``info`` (flat dict
    of numbers, strings, booleans or number lists) as the ``[info]`` table."""
    lines = [f"# {h}" if h else "#" for h in header.splitlines()]
    lines.append("[gains]")
    for name, v in zip(gains._fields, gains):
        lines.append(f"{name} = {_toml_value(np.asarray(v))}")
    if info:
        lines.append("")
        lines.append("[info]")
        for k, v in info.items():
            if isinstance(v, str):
                lines.append(f"{k} = {_toml_str(v)}")
            elif isinstance(v, bool):
                lines.append(f"{k} = {'true' if v else 'false'}")
            elif isinstance(v, (int, np.integer)):
                lines.append(f"{k} = {int(v)}")
            else:
                arr = np.asarray(v, dtype=float)
                lines.append(f"{k} = {_toml_value(arr) if np.all(np.isfinite(arr)) else _toml_str(str(v))}")
    return "\n".join(lines) + "\n"


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'


def parse_gains(data: dict, path: str = "<gains>"):
    """Validate a gains dict (as read by tomllib) into a TransportGains (float32 leaves, unbatched)."""
    import jax.numpy as jnp

    unknown = sorted(set(data) - {"gains", "info"})
    if unknown:
        raise spec_error(path, unknown[0], "unknown table; expected gains (and an optional info)")
    raw = data.get("gains")
    if not isinstance(raw, dict):
        raise spec_error(path, "gains", "missing table [gains] (TransportGains leaves)")
    base = _defaults()
    bad = sorted(set(raw) - set(base._fields))
    if bad:
        raise spec_error(path, f"gains.{bad[0]}", f"unknown leaf; expected one of {', '.join(base._fields)}")
    out = {}
    for name, default in zip(base._fields, base):
        if name not in raw:
            out[name] = default
            continue
        key, v, shape = f"gains.{name}", raw[name], np.shape(default)
        hi, lo_open = (1.0, True) if name == "tau_margin" else (GAIN_MAX, False)
        if isinstance(v, list):
            if len(shape) != 1 or len(v) != shape[0]:
                want = f"a list of {shape[0]} numbers or one number" if shape else "one number"
                raise spec_error(path, key, f"expected {want}, got a list of {len(v)}")
            vals = [checked_number(path, key, x, float, 0.0, hi, lo_open, "(gain)") for x in v]
        else:
            vals = checked_number(path, key, v, float, 0.0, hi, lo_open, "(gain)")
        out[name] = jnp.broadcast_to(jnp.asarray(vals, dtype=default.dtype), shape)
    gains = type(base)(**out)
    problem = feasibility(gains)
    if problem:
        key, msg = problem
        raise spec_error(path, f"gains.{key}", msg)
    return gains


def feasibility(gains, scale: dict | None = None) -> tuple[str, str] | None:
    """(leaf, message) of the first rule the gains break, or None: the regularization weights > 0 and
    ``f_min`` <= ``f_max``. ``scale``: leaf -> the multipliers a spec's ``gain.<leaf>`` factor applies (every
    combination of levels is a run of the design)."""
    scale = scale or {}

    def extreme(name, pick):
        leaf = np.asarray(getattr(gains, name), dtype=float)
        return pick(leaf) * pick(np.asarray(scale.get(name, [1.0]), dtype=float))

    for name in REGULARIZATION:
        if extreme(name, np.min) <= 0:
            return name, (f"= {extreme(name, np.min):g}: a regularization weight must be > 0 (the QP would be "
                          "singular)")
    f_min, f_max = extreme("f_min", np.max), extreme("f_max", np.min)
    if f_min > f_max:
        return "f_min", (f"f_min {f_min:g} N > f_max {f_max:g} N: no contact force would satisfy the QP's bounds, "
                         "so every control step would be infeasible")
    return None


def check_design(spec, gains=None) -> None:
    """Refuse a spec whose ``gain.*`` factors, applied to ``gains`` (None: the defaults), break
    :func:`feasibility` in some run (before anything is built).

    Raises:
        SpecError: naming the spec, the factor (or the gains leaf) and the rule.
    """
    scale = {k[len(GAIN_PREFIX):]: v for k, v in spec.factors.items() if k.startswith(GAIN_PREFIX)}
    if not scale:
        return
    problem = feasibility(_defaults() if gains is None else gains, scale)
    if problem:
        key, msg = problem
        leaves = ("f_min", "f_max") if key == "f_min" else (key,)
        varied = [f"{GAIN_PREFIX}{k}" for k in leaves if f"{GAIN_PREFIX}{k}" in spec.factors]
        raise spec_error(spec.path, f"factors.{varied[0]}" if varied else f"gains.{key}",
                         f"{msg} (with the factors' levels)")


def load_gains(path: str | Path):
    """Read and validate a gains TOML file (module docstring). Raises SpecError (one line: file, key)."""
    try:
        text = read_capped(path, what="gains").decode("utf-8-sig")  # a byte-order mark is dropped
    except (OSError, UnicodeDecodeError, InputError) as e:
        raise SpecError(f"{path}: cannot read gains file ({getattr(e, 'strerror', None) or e})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SpecError(f"{path}: not valid TOML ({str(e).splitlines()[0]})") from None
    return parse_gains(data, str(path))


def gains_equal(a, b, rtol: float = 0.0) -> bool:
    """Leafwise comparison of two unbatched TransportGains (exact by default)."""
    return all(np.allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=0.0) for x, y in zip(a, b))

