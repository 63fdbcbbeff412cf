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
# two lanes at once (the first lane, then the other two in turn), each lane's output shown when it ends: most of
# the suite is single-threaded XLA compilation, so two cores do two at a time.
# The lanes are split by measured cost (2 cores, empty cache), not alphabetically, and ordered so that programs
# several files compile are compiled once and then read from the shared cache: lane 1 starts with test_campaign
# (the flat scene's contact slots and the tiny campaign's chunk and init programs, which test_sharding, test_tune's
# CEM run and test_window reuse in lane 3; test_window after the other two, which load them into that process),
# while lane 2 starts with test_qp (no MJX model) so as not to compile the same programs at the same time.
# test_model (~180 s, programs of its own) ends lane 2. test_clearance (42 s) ends lane 1, moved from lane 2 when
# test_transport stopped compiling its chunk program (test_backends' JAX walk, early in lane 1, compiles the same
# one) and test_distributed's second process its programs; by the run below's per-file times, in lane 2 it would give
# 1,978 / 2,007 s instead. Measured with these lists (empty cache, this 2-core machine, 2026-11-27): on a clean
# clone with nothing else running, lane 1 1,064 s, lanes 2+3 992 s (367 + 625 s), 385 passed, 18 min 43 s in all;
# with another user's test runs on the same 2 cores for most of it, 2,020 / 1,965 s. Under load the long B=1
# rollouts slow most: test_course's wall passage took 504 s there (206 s in the clean run).
# After test_distributed's Warp reference moved ahead of its processes (85dba08), clean clone: lane 1 928 s,
# lanes 2+3 863 s (355 + 508 s), 16 min 20 s. At a44d8b4 (among others the controller's point Jacobians without
# MJX's body-tree scans), clean clone: lane 1 840 s, lanes 2+3 805 s (304 + 501 s), 14 min 48 s; the same code
# (docs and one controller line later) took 17 min 9 s and 20 min 7 s in two runs after it, with 4-6.5 min more
# CPU time and the load average at 3.5-4 on 2 cores (other tenants): the machine's speed varies more than the
# changes of these sessions, so compare CPU time (`time`'s user) as well as the wall time.
# A test file in none of the lists runs at the end of lane 3.
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
