"""``wbc_jax.runtime.jaxcfg.start_backend``: the backend starts in a thread, which makes the first transfer (a GPU's
memory pool is set up there); its error is the main thread's."""

import os
import subprocess
import sys

SCRIPT = """
import threading
import jax
from jax._src import xla_bridge
from wbc_jax.runtime import jaxcfg
puts, put = [], jax.device_put
jax.device_put = lambda *a, **k: puts.append(threading.current_thread().name) or put(*a, **k)
jaxcfg.configure()
t = jaxcfg.start_backend()
t.join(120)
print("STARTED", t.daemon, t.is_alive(), xla_bridge.backends_are_initialized(), flush=True)
print("PUT", puts, flush=True)
import jax
print("DEVICE", jax.devices()[0].platform, flush=True)
"""


def _run(platforms: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_PLATFORMS=platforms, WBC_JAX_CACHE="off")
    return subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300)


def test_start_backend_starts_it_in_a_daemon_thread():
    r = _run("cpu")
    assert r.returncode == 0, r.stderr
    assert "STARTED True False True" in r.stdout and "DEVICE cpu" in r.stdout
    assert "PUT ['wbc-jax-backend']" in r.stdout, r.stdout


def test_a_backend_that_cannot_start_fails_in_the_main_thread_not_the_helper():
    r = _run("no_such_platform")
    assert r.returncode != 0
    assert "STARTED True False" in r.stdout and "DEVICE" not in r.stdout
    assert "no_such_platform" in r.stderr and "Exception in thread" not in r.stderr
