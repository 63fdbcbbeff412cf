#!/usr/bin/env bash
# The README's test command and CI's (.ci/run): a fresh venv, the package installed with its test extras, ruff, pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q --upgrade pip
.venv/bin/pip install -q -e '.[test]'
.venv/bin/ruff check wbc_jax tests examples
export WBC_JAX_CACHE="${WBC_JAX_CACHE:-$PWD/.venv/jax-cache}"
if [ "$#" -gt 0 ]; then
  exec .venv/bin/python -m pytest -q "$@"
fi
# Without arguments: the whole suite in three pytest processes ("lanes"), two at a time (lane 1 alongside lanes 2
# then 3), each lane's output shown when it ends. Most of the suite's time is single-threaded XLA compilation, so on
# a 2-core CI machine two processes run at once; one process of the whole suite also made XLA's CPU compiler abort.
# The lanes share the persistent compilation cache, and their lists and order are chosen so that a program several
# files compile is compiled once and then read from the cache (lane 1 starts with the tiny campaign's programs, lane
# 2 with the QP tests, which need no MJX model), keeping the suite under ~15 minutes on 2 cores. A test file in none
# of the lists runs at the end of lane 3. With arguments: one pytest process on them, e.g. `bash tests/run.sh
# tests/test_qp.py`; `bash tests/run.sh -m "not slow"` gives a quick pass that skips the tests marked `slow` (the
# markers `slow` and `gpu` are registered in pyproject.toml).
lane1=(campaign backends centroidal course aot api distributed clearance)
lane2=(qp metrics packed planner interaction kernel_trace reliability snapshots spec_docs stats model)
lane3=(sharding tune window transport substeps factors report)
named=" ${lane1[*]} ${lane2[*]} ${lane3[*]} "
paths() { for f in "$@"; do [ -f "tests/test_$f.py" ] && echo "tests/test_$f.py"; done; }
mapfile -t files1 < <(paths "${lane1[@]}")
mapfile -t files2 < <(paths "${lane2[@]}")
mapfile -t files3 < <(paths "${lane3[@]}"; for f in $(ls tests/test_*.py | sort); do
  n=${f#tests/test_}; n=${n%.py}; [[ "$named" == *" $n "* ]] || echo "$f"; done)
logs=$(mktemp -d)
( .venv/bin/python -m pytest -q "${files1[@]}" > "$logs/1" 2>&1 ) & first=$!
rc=0
( r=0; .venv/bin/python -m pytest -q "${files2[@]}" || r=$?
  .venv/bin/python -m pytest -q "${files3[@]}" || r=$?; exit "$r" ) > "$logs/2" 2>&1 || rc=$?
wait "$first" || rc=$?
cat "$logs/1" "$logs/2"
rm -rf "$logs"
exit "$rc"
