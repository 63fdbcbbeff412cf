#!/usr/bin/env bash
# The README's test command: fresh venv, install with test extras, run pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q -e '.[test]'
export WBC_JAX_CACHE="${WBC_JAX_CACHE:-$PWD/.venv/jax-cache}"
if [ "$#" -gt 0 ]; then
  exec .venv/bin/python -m pytest -q "$@"
fi
# The whole suite in three pytest processes (sharing the persistent compilation cache): in one process of ~350
# tests XLA's CPU compiler aborted three times on 2026-11-25 near the end of the suite (in compile or in the cache's
# executable serialization, at test_window / test_transport), while each of those tests passes alone. They run in
# two lanes at once (the first third, then the other two in turn), each lane's output shown when it ends: most of
# the suite is single-threaded XLA compilation, so two cores do two at a time.
mapfile -t files < <(ls tests/test_*.py | sort)
n=${#files[@]}
a=$(( n / 3 )); b=$(( 2 * n / 3 ))
logs=$(mktemp -d)
( .venv/bin/python -m pytest -q "${files[@]:0:a}" > "$logs/1" 2>&1 ) & first=$!
rc=0
( r=0; .venv/bin/python -m pytest -q "${files[@]:a:b-a}" || r=$?
  .venv/bin/python -m pytest -q "${files[@]:b}" || r=$?; exit "$r" ) > "$logs/2" 2>&1 || rc=$?
wait "$first" || rc=$?
cat "$logs/1" "$logs/2"
rm -rf "$logs"
exit "$rc"
