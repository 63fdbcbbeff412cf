"""One process per host (or per GPU): ``jax.distributed`` set up from flags or the cluster's environment.

A multi-process run needs three things in every process, before anything touches a device: the coordinator's
``host:port`` (process 0 serves it), the process count and this process's id. :func:`resolve` takes them, in
this order, from the command's flags (``--coordinator``, ``--num-processes``, ``--process-id``), from
``JAX_COORDINATOR_ADDRESS`` / ``JAX_NUM_PROCESSES`` / ``JAX_PROCESS_ID``, or from a SLURM job step
(``SLURM_STEP_NUM_TASKS`` or ``SLURM_NTASKS`` > 1, ``SLURM_PROCID``; the coordinator is the step's first node,
from ``SLURM_STEP_NODELIST`` / ``SLURM_JOB_NODELIST``, else ``SLURM_LAUNCH_NODE_IPADDR``, at port
``JAX_COORDINATOR_PORT`` or :data:`DEFAULT_PORT`). Nothing configured, or one process: no distributed
initialisation at all (a single-process run is unchanged).

:func:`initialize` then calls ``jax.distributed.initialize`` (with the CPU's cross-process collectives, gloo,
switched on: without them a CPU computation cannot span processes). ``jax.devices()`` lists every device of
every process; a campaign spreads its run axis over all of them (:func:`wbc_jax.rollout.sharding.run_mesh`), every
process builds the same batch (the design is deterministic), and only :func:`is_writer` (process 0) writes.
:func:`agree` makes a user error found by process 0 alone (its output folder, its checkpoint) every process's
error, so that no process waits for a partner that has left; before its first collective it stops a run where two
processes of one host share a GPU (:func:`check_own_gpus`), which NCCL cannot serve.
"""

from __future__ import annotations

import json
import os
import re
import socket
from typing import Mapping, NamedTuple, Sequence

from wbc_jax.errors import InputError, WbcJaxError

DEFAULT_PORT = 12355  # coordinator port when only the host is known (SLURM)
MESSAGE_BYTES = 4096  # longest error message :func:`agree` carries to the other processes
HOST_WAIT_S = 24 * 3600.0  # longest a process waits at a host barrier or for a shared value (a partner's chunk)


class Layout(NamedTuple):
    """How to join a multi-process run (see the module docstring)."""

    coordinator: str  # host:port of process 0's coordination service
    num_processes: int
    process_id: int
    local_device_ids: tuple[int, ...] | None  # the devices this process uses (None: all it sees)
    source: str  # where the settings came from: "flags", "JAX_* environment" or "SLURM"


_ACTIVE: Layout | None = None
_GPUS_CHECKED = False  # check_own_gpus has run in this process


def _int(text, what: str, lo: int, hi: int | None = None) -> int:
    try:
        v = int(str(text).strip())
    except ValueError:
        v = None
    if v is None or v < lo or (hi is not None and v > hi):
        rng = f"{lo} <= value" + (f" <= {hi}" if hi is not None else "")
        raise InputError(f"{what} = {text!r}: expected an integer, {rng}")
    return v


def _address(text: str, what: str) -> str:
    host, sep, port = str(text).strip().rpartition(":")
    if not sep or not host or not re.fullmatch(r"[A-Za-z0-9_.\-\[\]:]+", host):
        raise InputError(f"{what} = {text!r}: expected HOST:PORT, e.g. 10.0.0.1:12355 or localhost:12355")
    _int(port, f"{what} port", 1, 65535)
    return f"{host}:{int(port)}"


def first_host(nodelist: str) -> str:
    """The first host of a SLURM node list: ``"gpu[003-005,9],cpu1"`` -> ``"gpu003"``."""
    m = re.match(r"\s*([^,\[]*)(?:\[([^\]]*)\])?", nodelist)
    prefix, ranges = (m.group(1), m.group(2)) if m else ("", None)
    if ranges:
        prefix += re.split(r"[-,]", ranges)[0]
    if not prefix:
        raise InputError(f"SLURM node list {nodelist!r}: no host name")
    return prefix


def _device_ids(text: str, what: str) -> tuple[int, ...]:
    parts = [p for p in str(text).split(",") if p.strip()]
    if not parts:
        raise InputError(f"{what} = {text!r}: expected comma-separated device ids, e.g. 0 or 0,1")
    return tuple(_int(p, what, 0) for p in parts)


def resolve(coordinator: str | None = None, num_processes: int | str | None = None,
            process_id: int | str | None = None, local_device_ids: str | None = None,
            env: Mapping[str, str] | None = None) -> Layout | None:
    """This process's place in a multi-process run, or None for a single-process run.

    Args:
        coordinator, num_processes, process_id, local_device_ids: the command's flags (None: not given); a flag
            wins over the environment.
        env: environment variables (default ``os.environ``).

    Returns:
        The validated Layout; None when nothing is configured or the run has one process.

    Raises:
        InputError: a value is malformed or out of range (one line naming the flag or variable), or a
            multi-process run lacks the coordinator or this process's id.
    """
    env = os.environ if env is None else env
    flags = dict(coordinator=coordinator, num_processes=num_processes, process_id=process_id)
    names = dict(coordinator="--coordinator", num_processes="--num-processes", process_id="--process-id")
    source = "flags" if any(v is not None for v in flags.values()) else None
    jax_env = dict(coordinator="JAX_COORDINATOR_ADDRESS", num_processes="JAX_NUM_PROCESSES",
                   process_id="JAX_PROCESS_ID")
    for k, var in jax_env.items():
        if flags[k] is None and env.get(var, "").strip():
            flags[k], names[k] = env[var], var
            source = source or "JAX_* environment"
    slurm_n = env.get("SLURM_STEP_NUM_TASKS") or env.get("SLURM_NTASKS")
    if source is None and slurm_n and "SLURM_PROCID" in env and _int(slurm_n, "SLURM_NTASKS", 1) > 1:
        source = "SLURM"
        flags["num_processes"], names["num_processes"] = slurm_n, "SLURM_NTASKS"
        flags["process_id"], names["process_id"] = env["SLURM_PROCID"], "SLURM_PROCID"
        nodes = env.get("SLURM_STEP_NODELIST") or env.get("SLURM_JOB_NODELIST")
        host = first_host(nodes) if nodes else env.get("SLURM_LAUNCH_NODE_IPADDR")
        if host:
            port = env.get("JAX_COORDINATOR_PORT", str(DEFAULT_PORT))
            flags["coordinator"], names["coordinator"] = f"{host}:{port}", "SLURM node list:JAX_COORDINATOR_PORT"
    if source is None:
        return None
    n = _int(flags["num_processes"], names["num_processes"], 1) if flags["num_processes"] is not None else None
    if n is None:
        raise InputError(f"{names['num_processes']} missing: a multi-process run needs the process count "
                         "(--num-processes or JAX_NUM_PROCESSES)")
    if n == 1:
        return None
    missing = [names[k] for k in ("coordinator", "process_id") if flags[k] is None]
    if missing:
        raise InputError(f"{' and '.join(missing)} missing: a run of {n} processes needs the coordinator's "
                         "HOST:PORT and this process's id in every process")
    pid = _int(flags["process_id"], names["process_id"], 0, n - 1)
    ids = _device_ids(local_device_ids, "--local-device-ids") if local_device_ids is not None else None
    return Layout(_address(flags["coordinator"], names["coordinator"]), n, pid, ids, source)


def initialize(layout: Layout | None) -> None:
    """``jax.distributed.initialize`` for ``layout`` (nothing for None); call before anything touches a device.
    A second call with the same layout does nothing."""
    global _ACTIVE
    if layout is None or _ACTIVE == layout:
        return
    if _ACTIVE is not None:
        raise WbcJaxError(f"this process already joined {_ACTIVE.coordinator} as process {_ACTIVE.process_id}")
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU programs across processes
    try:
        jax.distributed.initialize(layout.coordinator, layout.num_processes, layout.process_id,
                                   local_device_ids=list(layout.local_device_ids) if layout.local_device_ids
                                   else None)
    except (RuntimeError, ValueError) as e:  # unreachable coordinator, timeout, a second process with this id
        why = " ".join(str(e).split())[:300]
        raise WbcJaxError(f"process {layout.process_id} of {layout.num_processes} could not join the coordinator "
                          f"{layout.coordinator} ({layout.source}): {why}") from None
    _ACTIVE = layout


def is_multiprocess() -> bool:
    """Whether this process is one of several (:func:`initialize` was called with more than one)."""
    return _ACTIVE is not None


def is_writer() -> bool:
    """Whether this process writes results, reports, manifests and checkpoints: process 0 (or the only one)."""
    import jax

    return _ACTIVE is None or jax.process_index() == 0


def leave() -> None:
    """End this process's part in a multi-process run that succeeded (nothing with one process): XLA's warnings off,
    then ``jax.distributed.shutdown()``, which waits for every process (a failing one shuts down in JAX's exit
    handler) for at most the coordination service's shutdown timeout (``jax.distributed.initialize``'s default, 300 s)
    and stops this process's client and, in process 0, the service. The warnings are off because the PJRT client
    outlives the service until the process ends, and a GPU client's task watcher then logs ``WatchTasksAsync failed``.
    """
    if _ACTIVE is None:
        return
    import jax

    try:
        jax.config.update("jax_logging_level", "ERROR")  # Python and C++ loggers: errors still show
        jax.distributed.shutdown()
    except Exception:  # the command succeeded and wrote its results; a failed teardown does not undo that
        pass


def layout_record() -> dict:
    """The process and device layout, for a manifest: process count, this process's index, where the settings
    came from, and every device as (id, process, kind)."""
    import jax

    return dict(processes=jax.process_count(), process_index=jax.process_index(),
                source=_ACTIVE.source if _ACTIVE else "single process",
                coordinator=_ACTIVE.coordinator if _ACTIVE else None,
                local_device_count=jax.local_device_count(),
                devices=[dict(id=d.id, process=d.process_index, kind=d.device_kind) for d in jax.devices()])


def shared_gpu(owners: Mapping[int, tuple[str, Sequence[str]]]) -> str | None:
    """The first GPU that two processes of one host both use, as a one-line error message; None when none does.

    Args:
        owners: process index -> (its host's name, the PCI bus ids of the GPUs it uses). A GPU is known by its bus
            id, as NCCL knows it: ``CUDA_VISIBLE_DEVICES`` and device numbers differ between processes (a cluster's
            per-task device isolation shows every task its GPU as device 0).
    """
    seen: dict[tuple[str, str], int] = {}
    for p in sorted(owners):
        host, gpus = owners[p]
        for g in gpus:
            q = seen.setdefault((host, str(g)), p)
            if q != p:
                return (f"processes {q} and {p} both use the GPU at PCI bus {g} of host {host}: give each process "
                        "its own GPUs (--local-device-ids, or CUDA_VISIBLE_DEVICES per process)")
    return None


def _bus_id(ordinal: int) -> str | None:
    """The PCI bus id (``"0000:60:00.0"``) of this process's CUDA device ``ordinal`` from the CUDA driver, or None
    where the driver cannot tell."""
    import ctypes

    try:
        cuda = ctypes.CDLL("libcuda.so.1")
        dev, buf = ctypes.c_int(), ctypes.create_string_buffer(64)
        ok = (cuda.cuInit(0) == 0 and cuda.cuDeviceGet(ctypes.byref(dev), int(ordinal)) == 0
              and cuda.cuDeviceGetPCIBusId(buf, 64, dev) == 0)
    except (OSError, AttributeError):  # no CUDA driver here
        return None
    return buf.value.decode() if ok and buf.value else None


def _physical_gpus() -> list[str]:
    """The PCI bus ids of this process's GPUs (:func:`shared_gpu`); empty without GPUs, a GPU whose id the driver
    does not give left out."""
    import jax

    ids = [_bus_id(d.local_hardware_id) for d in jax.local_devices()
           if d.platform == "gpu" and d.local_hardware_id is not None]
    return [i for i in ids if i is not None]


def check_own_gpus(timeout_s: float = HOST_WAIT_S) -> None:
    """Raise an :class:`InputError` (:func:`shared_gpu`'s message) in every process where two processes of one host
    use the same GPU, before their first device collective, which would fail inside NCCL ("Duplicate GPU
    detected"). Host-side, through the coordination service; once per process (later calls return at once);
    nothing with one process. Every process must call it (:func:`agree` does, first)."""
    global _GPUS_CHECKED
    if _ACTIVE is None or _GPUS_CHECKED:
        return
    share(f"wbc-jax/gpus/{_ACTIVE.process_id}", json.dumps([socket.gethostname(), _physical_gpus()]))
    owners = {p: tuple(json.loads(shared(f"wbc-jax/gpus/{p}", timeout_s))) for p in range(_ACTIVE.num_processes)}
    _GPUS_CHECKED = True
    message = shared_gpu(owners)
    if message is not None:
        raise InputError(message)


def agree(error: WbcJaxError | None) -> None:
    """Raise process 0's user error (None: none) in every process.

    Single process: raises ``error`` if given. Several: a collective (every process must call it at the same
    point), after :func:`check_own_gpus`; process 0's message reaches the others, which raise it as a WbcJaxError.
    """
    if _ACTIVE is None:
        if error is not None:
            raise error
        return
    check_own_gpus()
    import numpy as np
    from jax.experimental import multihost_utils

    buf = np.zeros(MESSAGE_BYTES + 1, np.uint8)
    if error is not None:
        text = str(error).encode()[:MESSAGE_BYTES]
        buf[0], buf[1:1 + len(text)] = 1, np.frombuffer(text, np.uint8)
    got = np.asarray(multihost_utils.broadcast_one_to_all(buf))
    if error is not None and is_writer():
        raise error
    if got[0]:
        raise WbcJaxError(bytes(got[1:]).rstrip(b"\0").decode(errors="replace"))


def _client():
    from jax._src import distributed as jax_distributed

    return jax_distributed.global_state.client


def host_barrier(name: str, timeout_s: float = HOST_WAIT_S) -> None:
    """Wait until every process has reached ``host_barrier(name)`` (a fresh name per meeting). Host-side only,
    through the coordination service: the devices keep running what was dispatched to them. Nothing with one
    process. A process that leaves ends the others' wait with an error (the service's heartbeat)."""
    if _ACTIVE is not None:
        _client().wait_at_barrier(name, int(timeout_s * 1000))


def share(key: str, value: str) -> None:
    """Publish ``value`` under ``key`` (set once) for every process's :func:`shared` (the coordination service's
    key-value store; several processes only)."""
    _client().key_value_set(key, value)


def shared(key: str, timeout_s: float = HOST_WAIT_S) -> str:
    """The value some process published under ``key`` with :func:`share` (waits for it; several processes only)."""
    return _client().blocking_key_value_get(key, int(timeout_s * 1000))
