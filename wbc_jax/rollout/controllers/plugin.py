"""Controllers defined outside the package: a subclass of a built-in controller, named ``"module:Class"``.

A spec's ``[plugin]`` table (:mod:`wbc_jax.campaign.spec_controller`) names the class and sets its own fields::

    [plugin]
    class = "examples.torque_lag:TorqueLag"   # module:Class, the module importable from the current folder
    time_constant = 0.02                      # a field of the class (its default otherwise)

The class subclasses the spec's controller (:class:`TransportController` for ``controller = "transport"``,
:class:`CentroidalController` for ``"centroidal"``) as ``@dataclass(frozen=True, eq=False)`` (equal definitions
share compiled programs: :class:`wbc_jax.runtime.static.ByValue`), its own fields with defaults of type bool, int,
float or str; a ``ValueError`` from its ``__post_init__`` (also run with ``cfg`` None when the spec is read) refuses
the values. It inherits its family's planner, gains, metrics, results columns and report, and overrides what it
changes: typically ``control`` (the torques that drive the motors) and, for memory of its own, ``init_state``,
``freeze`` and (transport) ``variant`` and ``with_variant``. A float or bool field a spec varies per run (a
``plugin.<field>`` factor) lives in its state and is set by ``with_params``; columns of its own in results.csv
are named by the class attribute ``extra_columns`` and returned by its ``finalize``. ``examples/torque_lag.py`` is
one.

Programs of a plug-in are not kept on disk as exported programs (:mod:`wbc_jax.runtime.aot` keys those by the
package's sources, not the plug-in's); XLA's compilation cache still applies. Its module file's sha256 is part of
the spec's hash, so a checkpoint, a baseline or a replay notices an edited plug-in.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import inspect
import os
import sys

from wbc_jax.runtime.static import ByValue

FIELD_TYPES = (bool, int, float, str)
_SEEN: dict = {}  # module name -> its file's sha256 when last imported by load()


def load(path: str, family: type) -> type:
    """The class ``path`` (``"module:Class"``, ``Class`` may be dotted) checked to be a by-value dataclass
    subclass of ``family``. The current folder is put first on ``sys.path`` (as ``python -m`` does) if absent.
    Raises ValueError (one line) naming what is wrong."""
    module_name, sep, qualname = path.partition(":")
    if not sep or not module_name or not qualname:
        raise ValueError(f"{path!r}: expected \"module:Class\" (e.g. \"examples.torque_lag:TorqueLag\")")
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        obj = _import(module_name)
    except ImportError as e:
        raise ValueError(f"{path!r}: cannot import module {module_name!r} ({e}); run from the folder that holds it "
                         "or put it on PYTHONPATH") from None
    except Exception as e:  # the user's module raised while importing
        raise ValueError(f"{path!r}: importing {module_name!r} raised {type(e).__name__}: {e}") from None
    for part in qualname.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"{path!r}: module {module_name!r} has no {qualname!r}")
        obj = getattr(obj, part)
    if not (isinstance(obj, type) and issubclass(obj, family)):
        raise ValueError(f"{path!r}: expected a subclass of wbc_jax.rollout.controllers.{family.__name__}")
    if not dataclasses.is_dataclass(obj) or obj.__eq__ is not ByValue.__eq__ or obj.__hash__ is not ByValue.__hash__:
        raise ValueError(f"{path!r}: declare it @dataclass(frozen=True, eq=False) (compared by value)")
    return obj


def _import(name: str):
    """Module ``name``, imported again where its file changed since this function last imported it (so the code
    that runs is the code :func:`source_sha256` hashes, also in a long-lived Python session)."""
    module = importlib.import_module(name)
    file = getattr(module, "__file__", None)
    if file is None or not os.path.isfile(file):  # no file (an interactive session): source_sha256 refuses it
        return module
    digest = _file_sha256(file)
    if _SEEN.get(name, digest) != digest:
        module = importlib.reload(module)
    _SEEN[name] = digest
    return module


def _file_sha256(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def settable_fields(cls: type) -> dict:
    """The fields a spec may set (name -> default): the class's dataclass fields but ``cfg``. Raises ValueError for
    a field without a default or of a type other than :data:`FIELD_TYPES`."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.name == "cfg":
            continue
        if f.default is dataclasses.MISSING or type(f.default) not in FIELD_TYPES:
            raise ValueError(f"{cls.__qualname__}.{f.name}: a plug-in's own field needs a default of type bool, int, "
                             "float or str")
        out[f.name] = f.default
    return out


def source_sha256(cls: type) -> str:
    """sha256 of the file that defines ``cls`` (what it imports beyond it is not covered). Raises ValueError where
    it has none (a class defined in an interactive session or a notebook)."""
    try:
        path = inspect.getsourcefile(cls)
        return _file_sha256(path)
    except (TypeError, OSError):
        raise ValueError(f"{cls.__module__}:{cls.__qualname__}: no source file to hash; define it in a module "
                         "file") from None


def built_in(controller) -> bool:
    """``controller`` (an instance) is one of the package's own definitions."""
    return type(controller).__module__.startswith("wbc_jax.")
