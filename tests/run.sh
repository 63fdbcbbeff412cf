#!/usr/bin/env bash
# The README's test command and CI's (.ci/run): a fresh venv, the package installed with its test extras, ruff, pytest.
#   bash tests/run.sh          the suite without the tests marked `slow` (long closed loops whose parts cheaper tests
#                              check; pyproject.toml registers the markers `slow` and `gpu`)
#   bash tests/run.sh --all    every test, the slow ones included
#   bash tests/run.sh ARGS     one pytest process on ARGS, e.g. `bash tests/run.sh tests/test_qp.py`, `-m slow`
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install -q -e '.[test]'
.venv/bin/ruff check wbc_jax tests examples
export WBC_JAX_CACHE="${WBC_JAX_CACHE:-$PWD/.venv/jax-cache}"
select=(-m "not slow")
if [ "${1:-}" = "--all" ]; then
  select=()
  shift
fi
if [ "$#" -gt 0 ]; then
  exec .venv/bin/python -m pytest -q "$@"
fi
# The suite is a queue of groups of test files, each group one pytest process; two workers take the next unclaimed
# group until none is left, so both cores of a 2-core CI machine stay busy to the end (most of the time is
# single-threaded XLA compilation; one process of the whole suite also made XLA's CPU compiler abort). The groups
# share the persistent compilation cache. A group's files run in one process so that the programs they share are
# traced once (test_campaign's tiny campaign, reused by test_replay, test_window, test_sharding, test_tune and
# test_plugin; the flat-scene chunk program of test_transport and test_backends' JAX walk; the transport scene's
# sensing pass of test_clearance and test_model; test_factors' tiny campaign, reused by test_freeze); the longest
# groups come first, test_backends' group first of all (it compiles MuJoCo Warp's CPU kernels, which the later Warp
# tests load from the kernel cache), then the files that compile little, longest first (the report's figures and
# subprocesses, then `light2`, then `light`, the shortest), so the two workers end close together. A test file in no
# group runs in a group of its own, before `light2` and `light`. A group that selects a test marked `llvm_default`
# compiles at LLVM's default level, the others at -O0 (tests/conftest.py); by default that is `light` alone
# (test_qp_fma).
# Each group prints a line when it ends; the outputs follow, in group order, at the end.
groups=(
  "transport backends"
  "campaign replay window sharding tune plugin dry_run"
  "substeps factors freeze"
  "course clearance model metrics"
  "qp"
  "report report_latex sensitivity cli_docs stats safety"
  "trot_campaign"
)
light="reliability planner zmp capture_point interaction kernel_trace snapshots spec_docs packed aot api architecture
  progress qp_fma gpu_lowering jaxcfg transfer"
light2="centroidal bench_campaign distributed envelope s_cause warmup checkpoint_writer blocks"
named=" ${groups[*]} $light $light2 "
rest=()
for f in tests/test_*.py; do
  n=${f#tests/test_}
  n=${n%.py}
  [[ "$named" == *[[:space:]]"$n"[[:space:]]* ]] || rest+=("$n")
done
for n in "${rest[@]}"; do groups+=("$n"); done
groups+=("$light2" "$light")
logs=$(mktemp -d)
run_group() {  # $1: the group's index
  local files=() n r=0 t0=$SECONDS
  for n in ${groups[$1]}; do
    if [ -f "tests/test_$n.py" ]; then files+=("tests/test_$n.py"); fi
  done
  if [ "${#files[@]}" -gt 0 ]; then
    .venv/bin/python -m pytest -q "${select[@]}" "${files[@]}" > "$logs/$1.log" 2>&1 || r=$?
  fi
  if [ "$r" -eq 5 ]; then r=0; fi  # every test of the group deselected
  echo "$r" > "$logs/$1.rc"
  echo "tests/run.sh: group $1 ended after $((SECONDS - t0)) s, exit $r: ${groups[$1]//$'\n'/}" | tr -s ' '
}
worker() {
  local i
  for i in "${!groups[@]}"; do
    if mkdir "$logs/claim.$i" 2> /dev/null; then run_group "$i"; fi
  done
}
worker & other=$!
worker
wait "$other"
rc=0
for i in "${!groups[@]}"; do
  cat "$logs/$i.log" 2> /dev/null || true
  r=$(cat "$logs/$i.rc" 2> /dev/null || echo 1)
  if [ "$r" -ne 0 ]; then rc=$r; fi
done
rm -rf "$logs"
exit "$rc"
