"""Second runs without re-tracing: jitted functions exported once (``jax.export``) and reloaded from disk.

The persistent compilation cache (:mod:`wbc_jax.runtime.jaxcfg`) skips XLA's compile on a second run, but JAX still
traces the Python function and lowers it to find the cache entry; for the MJX + WBC chunk function that is
most of a warm start (seconds). :func:`cached_jit` stores the lowered program (StableHLO, serialized
``jax.export.Exported``) next to the compilation cache; a later process with the same key deserializes it and
calls it, so nothing is traced and XLA's compile is a cache hit.

The key covers everything the program depends on: a caller-given name and static description (e.g. the
model's bytes, the solver settings), the shapes, dtypes and pytree structure of the arguments, the source of
the ``wbc_jax`` package, the versions of jax, jaxlib and mujoco, the backend and the device count. A stale
entry therefore cannot be hit after a code or version change; it is simply never read again.

Used only with one device and unsharded inputs (a sharded program also depends on the input shardings; those
calls use plain ``jax.jit``). ``WBC_JAX_CACHE=off`` turns this off along with the compilation cache.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np

from wbc_jax.runtime import jaxcfg

# custom-call targets without jax.export's compatibility guarantee that an exported program may hold (Pallas' Triton
# kernels on a GPU)
_UNGUARANTEED_CALLS = ("__gpu$xla.gpu.triton",)

_SRC_DIGEST: str | None = None
_LOADED: dict[str, Callable] = {}
_PLAIN = object()  # _LOADED marker of a key whose program could not be exported


def source_digest() -> str:
    """sha256 of the wbc_jax package's Python sources (names and contents), computed once per process."""
    global _SRC_DIGEST
    if _SRC_DIGEST is None:
        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _SRC_DIGEST = h.hexdigest()
    return _SRC_DIGEST


def model_digest(mj_model) -> str:
    """sha256 of a compiled MuJoCo model (its binary MJB form: every field, whatever the XML files were)."""
    import mujoco

    buf = np.empty(mujoco.mj_sizeModel(mj_model), np.uint8)
    mujoco.mj_saveModel(mj_model, None, buf)
    return hashlib.sha256(buf.tobytes()).hexdigest()


def _versions() -> str:
    import jaxlib
    import mujoco

    return f"jax {jax.__version__} jaxlib {jaxlib.__version__} mujoco {mujoco.__version__} " \
           f"backend {jax.default_backend()} devices {jax.device_count()} x64 {jax.config.jax_enable_x64}"


def _store() -> Path | None:
    d = jaxcfg.cache_dir()
    return None if d is None else d / "exported"


def _dtype(x):
    return x.dtype if hasattr(x, "dtype") else jax.numpy.asarray(x).dtype


def _avals(leaves) -> str:
    return ";".join(f"{np.shape(x)}:{_dtype(x)}" for x in leaves)


def _canon(x) -> str:
    """Text of a pytree node's static data by value (arrays by content; raises on objects known only by address)."""
    if isinstance(x, np.ndarray):
        return f"array({x.dtype},{x.shape},{hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest()[:16]})"
    if isinstance(x, (tuple, list)):
        return type(x).__name__ + "(" + ",".join(_canon(v) for v in x) + ")"
    if isinstance(x, dict):
        items = sorted(x.items(), key=lambda kv: repr(kv[0]))
        return "dict(" + ",".join(f"{_canon(k)}:{_canon(v)}" for k, v in items) + ")"
    if isinstance(x, type):
        return f"{x.__module__}.{x.__qualname__}"
    if isinstance(getattr(x, "array", None), np.ndarray):  # a hashable wrapper of a static array (MJX's)
        return _canon(x.array)
    text = repr(x)
    if " at 0x" in text:
        raise ValueError(f"no by-value description of {type(x)}")
    return text


def _tree_text(treedef) -> str:
    data = treedef.node_data()
    kids = ",".join(_tree_text(c) for c in treedef.children())
    return "*" if data is None else f"{_canon(data[0])}[{_canon(data[1])}]({kids})"


def _tree_digest(treedef) -> str | None:
    """Digest of a pytree structure by value (its text form names static arrays by memory address, and pickles
    differ with object sharing); None if some static data has no by-value description."""
    try:
        return hashlib.sha256(_tree_text(treedef).encode()).hexdigest()
    except Exception:
        return None


def describe(*parts) -> str:
    """Text key of static configuration: a compiled MuJoCo model (``mj_model`` attribute) by its digest, numpy
    arrays by their bytes, dataclasses field by field, anything else by ``repr``."""
    import dataclasses

    out = []
    for p in parts:
        if hasattr(p, "mj_model"):
            out.append(f"model {model_digest(p.mj_model)}")
        elif isinstance(p, np.ndarray):
            out.append(f"array {p.dtype} {p.shape} {hashlib.sha256(np.ascontiguousarray(p).tobytes()).hexdigest()}")
        elif dataclasses.is_dataclass(p) and not isinstance(p, type):
            out.append(f"{type(p).__name__}(" + ", ".join(
                f"{f.name}={describe(getattr(p, f.name))}" for f in dataclasses.fields(p)) + ")")
        else:
            text = repr(p)
            if " at 0x" in text:  # an object named by its address: describe its pytree structure by value
                text = _tree_digest(jax.tree_util.tree_structure(p)) or text
            out.append(text)
    return " | ".join(out)


def _plain(leaves) -> bool:
    """Concrete values on one device (not tracers: under an outer transformation use plain jit)."""
    for x in leaves:
        if isinstance(x, jax.core.Tracer):
            return False
        if isinstance(x, jax.Array) and len(x.sharding.device_set) > 1:
            return False
    return True


def cached_jit(name: str, fn: Callable, static: str, exportable: bool = True) -> Callable:
    """``jax.jit(fn)`` whose lowered program is kept on disk across processes (see the module docstring).

    Args:
        name: readable prefix of the cache entry (e.g. ``"chunk"``).
        fn: function of positional pytree arguments returning a pytree of arrays; it must be fully determined
            by ``static`` and the arguments' shapes and dtypes (no hidden Python state that can change between
            processes without changing the sources or ``static``).
        static: text describing fn's closed-over configuration (part of the key).
        exportable: False for programs jax.export cannot hold (MuJoCo Warp's kernels are FFI calls registered per
            process) or that depend on code outside the package (whose sources the key does not cover): plain
            ``jax.jit`` (the persistent compilation cache still applies).

    Returns:
        a callable with fn's signature and results.
    """
    jitted = jax.jit(fn)
    store = _store() if exportable else None
    if store is None:
        return jitted

    used: dict[str, Callable] = {}

    def call(*args):
        leaves, in_tree = jax.tree_util.tree_flatten(args)
        if jax.device_count() > 1 or not _plain(leaves):
            return jitted(*args)
        tree = _tree_digest(in_tree)
        if tree is None:
            return jitted(*args)
        key = hashlib.sha256("\n".join([name, static, tree, _avals(leaves), source_digest(),
                                        _versions()]).encode()).hexdigest()[:40]
        f = used.get(key) or _LOADED.get(key)
        if f is None:
            f = _load(store, name, key) or _export(store, name, key, fn, in_tree, leaves)
            if f is None:  # not exportable: plain jit for this key from now on
                _LOADED[key] = _PLAIN
                return jitted(*args)
            _LOADED[key] = f
        if f is _PLAIN:
            return jitted(*args)
        used[key] = f
        return f(*leaves)

    def cache_size() -> int:
        """Compiled variants so far (like ``jax.jit``'s ``_cache_size``): exported programs used + plain jit's."""
        return sum(f.run._cache_size() for f in used.values()) + jitted._cache_size()

    call._cache_size = cache_size
    return call


def _wrap(exp, out_tree) -> Callable:
    run = jax.jit(exp.call)

    def f(*leaves):
        return jax.tree_util.tree_unflatten(out_tree, run(*leaves))

    f.run = run
    return f


def _load(store: Path, name: str, key: str) -> Callable | None:
    path = store / f"{name}-{key}.bin"
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    try:
        out_tree, payload = pickle.loads(blob)
        return _wrap(jax.export.deserialize(bytearray(payload)), out_tree)
    except Exception:  # a damaged or foreign entry: ignore it (it is rewritten on export)
        return None


def _export(store: Path, name: str, key: str, fn: Callable, in_tree, leaves) -> Callable | None:
    """Export ``fn`` for ``leaves``' shapes, store it and return the loaded callable; None (with a warning) when
    jax.export cannot hold the program (the caller then runs plain jit)."""
    out_tree: list[Any] = []

    def flat(*xs):
        out = fn(*jax.tree_util.tree_unflatten(in_tree, xs))
        o, t = jax.tree_util.tree_flatten(out)
        out_tree.append(t)
        return o

    specs = [jax.ShapeDtypeStruct(np.shape(x), _dtype(x)) for x in leaves]
    try:
        # Pallas' Triton kernels are custom calls without jax.export's cross-version
        # guarantee; the key already pins the jax/jaxlib versions and the backend, so that guarantee is not needed.
        exp = jax.export.export(jax.jit(flat), disabled_checks=[
            jax.export.DisabledSafetyCheck.custom_call(t) for t in _UNGUARANTEED_CALLS])(*specs)
    except Exception as e:  # a program export cannot hold: plain jit (only warm starts are lost)
        warnings.warn(f"wbc_jax.runtime.aot: {name} not exported ({type(e).__name__}: {str(e)[:200]}); using plain "
                      "jit", stacklevel=2)
        return None
    try:
        store.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", dir=store)
        with os.fdopen(fd, "wb") as fh:
            pickle.dump((out_tree[0], bytes(exp.serialize())), fh)
        os.replace(tmp, store / f"{name}-{key}.bin")
    except Exception:  # a read-only or full cache directory (or no serializer) only costs the next run its trace
        pass
    return _wrap(exp, out_tree[0])


def cached_value(name: str, static: str, compute: Callable[[], Any]) -> Any:
    """``compute()`` (a picklable, deterministic result of ``static`` and the sources), kept on disk like
    :func:`cached_jit`'s programs: e.g. MJX's contact-slot layout of a model, which otherwise costs a compile."""
    store = _store()
    if store is None:
        return compute()
    key = hashlib.sha256("\n".join([name, static, source_digest(), _versions()]).encode()).hexdigest()[:40]
    path = store / f"{name}-{key}.pkl"
    try:
        return pickle.loads(path.read_bytes())
    except Exception:  # missing, damaged or foreign: compute it again
        pass
    value = compute()
    try:
        store.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", dir=store)
        with os.fdopen(fd, "wb") as fh:
            pickle.dump(value, fh)
        os.replace(tmp, path)
    except OSError:
        pass
    return value
