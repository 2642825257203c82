#!/usr/bin/env bash
# The default report computed from scratch on another machine (the lent device's CPUs, its own
# library versions), for issue 29's "the report is a function of the code, on any machine".
# Compare the result with the committed report here: python scripts/compare_reports.py.
#
# Run on the device with the missing pure-Python packages carried as wheels in .whl/:
#   python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
#   export PYTHONPATH=/tmp/site:$PWD CUDA_VISIBLE_DEVICES= JAX_PLATFORMS=cpu
#   bash scripts/device_cross_machine.sh [SECONDS [EXPERIMENT ...]]
# Writes to $OUT: env.txt (CPU and versions), log.txt, rep.tgz (REPORT.md, tables, figures),
# store.sqlite.gz (the results store, for re-rendering).
set -uo pipefail
limit=${1:-430}
shift || true
exps=()
[ $# -gt 0 ] && exps=(--experiments "$@")
out=${OUT:-/tmp/out}
mkdir -p "$out"
{
  lscpu | grep -E 'Model name|^CPU\(s\)|Flags' | cut -c1-400
  python3 -c "import sys; print(sys.version)"
  python3 - <<'EOF'
import importlib.metadata as m
for p in ["numpy", "scipy", "scikit-learn", "scikit-optimize", "emcee", "jax", "jaxlib",
          "numpyro", "numba", "llvmlite", "torch", "pandas", "pysindy", "pydmd"]:
    try:
        print(p, m.version(p))
    except m.PackageNotFoundError:
        print(p, "missing")
import numpy
numpy.show_config()
EOF
} > "$out/env.txt" 2>&1
workers=$(nproc)
timeout "$limit" python3 -m sysid_bench.report --no-progress --workers "$workers" \
  --run-dir /tmp/dev --out /tmp/rep "${exps[@]}" 2>&1 | grep -v -e SyntaxWarning -e '^  """' \
  | tee "$out/log.txt"
echo "report exit: $?" | tee -a "$out/log.txt"
if [ ! -f /tmp/rep/REPORT.md ]; then
  # killed at the limit: render what the store holds
  python3 -m sysid_bench.report --from-store /tmp/dev/results.sqlite --out /tmp/rep \
    2>&1 | tail -5 | tee -a "$out/log.txt"
fi
tar czf "$out/rep.tgz" -C /tmp rep
gzip -c /tmp/dev/results.sqlite > "$out/store.sqlite.gz"
ls -la "$out"
