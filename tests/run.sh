#!/usr/bin/env bash
# The README's test command: fresh venv, install with test extras, run pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q -e '.[test]'
export WBC_JAX_CACHE="${WBC_JAX_CACHE:-$PWD/.venv/jax-cache}"
exec .venv/bin/python -m pytest -q "$@"
