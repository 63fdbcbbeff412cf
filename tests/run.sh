#!/usr/bin/env bash
# The README's test command: fresh venv, install with test extras, run pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q -e '.[test]'
# The persistent compilation cache stays off in the suite's own processes unless asked for: in the full suite (one
# long process, ~350 tests) XLA's CPU executable serialization for the cache crashed twice on 2026-11-25 (segfault /
# abort in compilation_cache.put_executable_and_time, at a different test each time; each test passes alone).
export WBC_JAX_CACHE="${WBC_JAX_CACHE:-off}"
exec .venv/bin/python -m pytest -q "$@"
