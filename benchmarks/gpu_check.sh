#!/usr/bin/env bash
# The GPU check of issue #37: what a session lent a GPU machine runs there through the
# device tool, from the repository root, in one call (about 4-6 minutes, most of it the
# first compile of the CPU kernels; at most 9: each step has its own timeout):
#
#   bash benchmarks/gpu_check.sh            # the GPU tests for real, then bench_gpu.py
#                                           # (the device tool: run it with timeout_s 580)
#   bash benchmarks/gpu_check.sh --simulate # dry run here: numba's CUDA simulator, tiny sizes
#
# The machine's image has numpy, scipy, numba, numba-cuda and pytest, and neither VTK nor
# ../shared: only the numeric core runs (tests/test_cuda_*.py, whose VTK tests skip, and
# benchmarks/bench_gpu.py). The resample rows time the 256^3 embryo's scene when
# benchmarks/out/embryo_scene.npz is there -- write it here first, and name it in the
# device tool's carry:
#
#   python benchmarks/bench_gpu.py --prepare-embryo benchmarks/out/embryo_scene.npz
#
# else a synthetic 256^3 volume. Wheels carried in .whl/ (see the device tool's README)
# are installed first if there are any; nothing else is installed.
# Results go to $OUT (the device tool brings them back): env.txt, tests.txt, bench.log
# and bench_gpu.md (the table). Other arguments go to bench_gpu.py (e.g. -r 3).
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/vhm_gpu_check}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
simulate=0
if [ "${1:-}" = "--simulate" ]; then
  simulate=1
  shift
fi
export PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/vhm_numba_cache}
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
if ls .whl/*.whl >/dev/null 2>&1; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/vhm_site .whl/*.whl || exit 1
  export PYTHONPATH=$PYTHONPATH:/tmp/vhm_site
fi
if [ "$simulate" = 1 ]; then
  export NUMBA_ENABLE_CUDASIM=1
  bench_args=(--quick)
else
  export VHM_TEST_REAL_GPU=1  # tests/test_cuda_map.py: the child runs on the device
  bench_args=()
  if [ -f benchmarks/out/embryo_scene.npz ]; then
    bench_args=(--embryo benchmarks/out/embryo_scene.npz)
  fi
fi

{
  date -u
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true
  "$PY" -c 'import sys, numpy, numba; from numba import cuda
print(sys.version.split()[0], "numpy", numpy.__version__, "numba", numba.__version__,
      "cuda available", cuda.is_available())' 2>&1
} | tee "$OUT/env.txt"

echo "== GPU tests (tests/test_cuda_*.py)"
timeout 240 "$PY" -m pytest -q -p no:cacheprovider tests/test_cuda_*.py 2>&1 \
  | tee "$OUT/tests.txt"
tests_status=${PIPESTATUS[0]}

echo "== bench_gpu.py"
timeout 300 "$PY" benchmarks/bench_gpu.py --out "$OUT/bench_gpu.md" "${bench_args[@]}" "$@" 2>&1 \
  | tee "$OUT/bench.log"
bench_status=${PIPESTATUS[0]}

echo "tests exit $tests_status, bench exit $bench_status" | tee -a "$OUT/env.txt"
[ "$tests_status" = 0 ] && [ "$bench_status" = 0 ]
