"""A spec's controller: the factors and keys it accepts, and a plug-in subclass of it (the ``[plugin]`` table).

``[campaign] controller`` names a built-in controller (:mod:`wbc_jax.campaign.controllers`); a ``[plugin]`` table
names a subclass of it from outside the package and sets the subclass's own fields
(:mod:`wbc_jax.rollout.controllers.plugin`)::

    [plugin]
    class = "examples.torque_lag:TorqueLag"   # module:Class, the module importable from the current folder
    time_constant = 0.02                      # its own fields (the class's defaults otherwise)

The campaign, its results columns, report and ``regress`` bands are the named controller's. Loading a spec with a
plug-in imports its module (and JAX); the module file's sha256 joins the spec's hash (``Spec.plugin_sha256``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from wbc_jax.campaign import controllers as controllers_mod
from wbc_jax.campaign import factors as factors_mod
from wbc_jax.errors import SpecError

PREFIX = factors_mod.PLUGIN_PREFIX
# the results table's own columns besides the controller's (wbc_jax.campaign.results.results_table)
TABLE_COLUMNS = ("run", "m", "mu", "d", "rep", "seed", "success", "obj_dx_mm", "obj_dy_mm", "obj_yaw_deg", "push_N")
CENTROIDAL_KEYS = ("mass_error", "walk_seconds", "step_time", "four_foot")  # campaign keys of the centroidal only
TRANSPORT_KEYS = ("distance", "variant", "terrain", "com_plan", "obj_accel")  # ... of the transport only


def check_controller(path, camp: dict, factors: dict, schema: dict) -> None:
    """The factors and keys of the spec's controller: a factor it cannot vary, or a key of the other one away
    from its default (``schema``: the campaign table's key -> (type, default, ...)), is an error; the centroidal
    trot's four-foot support is shorter than its half-cycle. Raises SpecError naming the key."""
    name = camp["controller"]
    for key in factors:
        if not controllers_mod.may_vary(name, key):
            allowed = [f for f in factors_mod.REGISTRY if controllers_mod.may_vary(name, f)]
            raise SpecError(f"{path}: factors.{key}: not a factor of controller {name!r}; expected one of "
                            f"{', '.join(allowed)}")
    for key in CENTROIDAL_KEYS if name == "transport" else TRANSPORT_KEYS:
        if camp[key] != schema[key][1]:
            raise SpecError(f"{path}: campaign.{key}: = {camp[key]!r}: not used by controller {name!r}; leave it out")
    if name == "centroidal" and not camp["four_foot"] < camp["step_time"]:
        raise SpecError(f"{path}: campaign.four_foot: = {camp['four_foot']}: expected < campaign.step_time "
                        f"({camp['step_time']})")


class Plugin(NamedTuple):
    """A spec's parsed ``[plugin]`` table: ``values`` ({"class": "module:Class", field: value ...}, defaults filled
    in, the fields a factor varies left out; {} without a table), ``sha256`` (its module file's; "" without),
    ``fields`` (the class's own fields, name -> default: what ``plugin.<field>`` factors may name)."""

    values: dict
    sha256: str
    fields: dict


def parse_plugin(path, raw, family: str, raw_factors=None) -> Plugin:
    """The ``[plugin]`` table ``raw`` (None: the spec has none) of a spec whose controller is ``family``, with the
    ``plugin.<field>`` keys of its raw ``[factors]`` table ``raw_factors`` checked against the class.

    Raises:
        SpecError: naming ``plugin.class`` (not "module:Class", no such module or class, not a by-value dataclass
            subclass of the ``family`` controller, no source file, ``extra_columns`` that are not new column
            names), ``plugin.<field>`` (not a field of the class, a value of another type than its default's, a
            field its factor varies) or ``factors.plugin.<field>`` (no ``[plugin]`` table, not a float or bool
            field, a class without ``with_params``), or the ValueError of the class's own ``__post_init__`` checks
            (run with ``cfg`` None).
    """
    varied = [k for k in (raw_factors if isinstance(raw_factors, dict) else {}) if k.startswith(PREFIX)]
    if raw is None:
        if varied:
            raise SpecError(f"{path}: factors.{varied[0]}: a plug-in's field; add a [plugin] table naming its class")
        return Plugin({}, "", {})
    if not isinstance(raw, dict):
        raise SpecError(f"{path}: plugin: expected a table [plugin], got {type(raw).__name__}")
    name = raw.get("class")
    if not isinstance(name, str):
        raise SpecError(f"{path}: plugin.class: expected \"module:Class\", a subclass of the {family} controller, "
                        f"got {name!r}")
    from wbc_jax.rollout.controllers import Controller, controller_class  # JAX, only for a spec with a plug-in
    from wbc_jax.rollout.controllers import plugin as plugins

    try:
        cls = controller_class(family, name)
        own = plugins.settable_fields(cls)
        digest = plugins.source_sha256(cls)
    except ValueError as e:
        raise SpecError(f"{path}: plugin.class: {e}") from None
    taken = {*controllers_mod.CONTROLLERS[family].columns, *TABLE_COLUMNS,
             *(raw_factors if isinstance(raw_factors, dict) else {})}
    extra = cls.extra_columns
    if not isinstance(extra, tuple) or not all(isinstance(c, str) and c and c not in taken for c in extra):
        raise SpecError(f"{path}: plugin.class: {name}.extra_columns = {extra!r}: expected a tuple of new column "
                        "names (not the results table's own)")
    for key in raw:
        if key != "class" and key not in own:
            raise SpecError(f"{path}: plugin.{key}: not a field of {name}; expected one of "
                            f"{', '.join(own) or '(it has none)'}")
    variable = [f for f, v in own.items() if factors_mod.plugin_factor(v) is not None]  # fields a factor may vary
    for key in varied:
        field = key[len(PREFIX):]
        if field not in variable:
            raise SpecError(f"{path}: factors.{key}: not a float or bool field of {name}; expected one of "
                            f"{', '.join(PREFIX + f for f in variable) or '(it has none)'}")
        if field in raw:
            raise SpecError(f"{path}: plugin.{field}: = {raw[field]!r}: the factor {key} is varied; leave it out")
        if cls.with_params is Controller.with_params:
            raise SpecError(f"{path}: factors.{key}: {name} does not implement with_params(state, params), which "
                            "sets its fields per run")
    values = {key: _value(path, key, raw.get(key, default), default) for key, default in own.items()
              if PREFIX + key not in varied}  # a varied field's static value stays the class's default
    _post_init(path, "plugin", cls, values)
    for key in varied:  # each level through the class's own checks too
        for level in raw_factors[key] if isinstance(raw_factors[key], list) else []:
            if isinstance(level, (int, float)) and not isinstance(level, bool):
                _post_init(path, f"factors.{key}", cls, {**values, key[len(PREFIX):]: float(level)})
    return Plugin({"class": name, **values}, digest, own)


def _post_init(path, where: str, cls: type, values: dict) -> None:
    """The class's own checks of its field ``values`` (a ValueError from ``__post_init__``, run with ``cfg`` None)
    as a SpecError naming ``where``; a check that needs the settings runs when the Sim is made."""
    try:
        cls(None, **values)
    except ValueError as e:
        raise SpecError(f"{path}: {where}: {e}") from None
    except Exception:  # noqa: BLE001
        pass


def _value(path, key: str, v, default):
    """``v`` checked to be of the type of ``default`` (an int is taken for a float field); SpecError otherwise."""
    typ = type(default)
    ok = (isinstance(v, bool) if typ is bool else isinstance(v, str) if typ is str
          else isinstance(v, int) and not isinstance(v, bool) if typ is int
          else isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v))
    if not ok:
        raise SpecError(f"{path}: plugin.{key}: expected a{'n' if typ is int else ''} {typ.__name__} like its "
                        f"default {default!r}, got {v!r}")
    return typ(v)


def controller_label(spec) -> str:
    """The controller a spec runs, as the console names it: its ``[plugin]`` class, else ``campaign.controller``."""
    return spec.plugin.get("class", spec.campaign["controller"])


def plugin_of(spec) -> tuple:
    """A spec's plug-in: ``()``, or (``"module:Class"``, ((field, value), ...) in name order, its module file's
    sha256); the first two as :func:`wbc_jax.rollout.make_sim` takes them, the sha256 for cache keys."""
    p = spec.plugin
    fields = tuple(sorted((k, v) for k, v in p.items() if k != "class"))
    return (p["class"], fields, spec.plugin_sha256) if p else ()
