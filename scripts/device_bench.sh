#!/usr/bin/env bash
# Labelled benchmark runs on the GPU machine, from the tree the device tool carries there.
#
#   bash scripts/device_bench.sh COMMIT STEP...
#
# COMMIT: the commit the carried tree holds (the GPU machine has no git; it goes into each JSON).
# PYTHON: the interpreter (default python3, with the staged packages in /tmp/site).
# STEP:   LABEL:ARGS, ARGS being scripts/bench.py's options with '+' between them, for example
#         p256-1:--piles+256+--skip+paper,mixed,cg+--deviation=
#         A LABEL starting with "newton" runs scripts/bench_newton.py with ARGS instead (it takes no label).
#
# Reads the folders docs/performance.md ("On the GPU machine") says to carry: .bench-assets (the shared
# meshes), .cache-gpu (their preprocessing) and, where present, .warp-cache-gpu (kernels built ahead for the
# GPU). Each step's JSON and log go to runs/, packed into $OUT/runs.tgz after every step, so the steps that
# finished come back even when a later one is cut short.
set -u
if [ $# -lt 2 ]; then
  echo "device_bench.sh: expected COMMIT STEP... (STEP: LABEL:ARGS)" >&2
  exit 2
fi
commit=$1
shift
for step in "$@"; do
  if [[ ! $step =~ ^[A-Za-z0-9._-]+: ]]; then
    echo "device_bench.sh: step '$step': expected LABEL:ARGS (LABEL of letters, digits, '.', '_', '-')" >&2
    exit 2
  fi
done
export PYTHONPATH=$PWD:/tmp/site WARPFEM_COMMIT=$commit
[ -e warpfem/kernels ] || ln -sfn ../kernels warpfem/kernels  # the package's kernels, as an install maps them
if [ -d .warp-cache-gpu ]; then
  cache=$("${PYTHON:-python3}" -c "import warp as wp; wp.config.quiet = True; wp.init(); print(wp.config.kernel_cache_dir)" | tail -1)
  mkdir -p "$cache" && cp -rn .warp-cache-gpu/. "$cache/" 2>/dev/null  # kept where already built
fi
mkdir -p runs
for step in "$@"; do
  label=${step%%:*}
  args=${step#*:}
  args=${args//+/ }
  if [[ $label == newton* ]]; then
    command=("${PYTHON:-python3}" scripts/bench_newton.py)
  else
    command=("${PYTHON:-python3}" scripts/bench.py --label "$label")
  fi
  start=$(date +%s)
  # shellcheck disable=SC2086  # ARGS split into bench.py's options on purpose
  "${command[@]}" --assets .bench-assets --cache-dir .cache-gpu --out runs $args > "runs/$label.log" 2>&1
  echo "$label: rc=$? in $(($(date +%s) - start)) s"
  grep -h "ms/frame" "runs/$label.log" | tail -12
  if [ -n "${OUT:-}" ]; then mkdir -p "$OUT" && tar czf "$OUT/runs.tgz" runs; fi
done
