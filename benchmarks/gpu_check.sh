#!/usr/bin/env bash
# The GPU check, unattended on a CUDA machine, each step under its own time limit: the CUDA
# tests, then the GPU table (benchmarks/gpu_table.py). Uses the machine's own python3 with a
# CUDA torch; packages it lacks (trimesh, cholespy) may travel as wheels in .whl/ (see the
# device notes). Writes gpu_tests.log and gpu_table.json to $OUT when set, else to the current
# folder.
set -uo pipefail
cd "$(dirname "$0")/.."
out="${OUT:-.}"
export PYTHONUNBUFFERED=1
if compgen -G ".whl/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl && export PYTHONPATH="/tmp/site:${PYTHONPATH:-}"
fi
export PYTHONPATH="$PWD:${PYTHONPATH:-}"
python3 -c "import torch; assert torch.cuda.is_available(), 'no CUDA device'; \
print('torch', torch.__version__, '|', torch.cuda.get_device_name())" || exit 2

# CUDA tests: every test whose name says cuda -- the [cuda] case of each test that takes the
# `device` fixture of tests/conftest.py (operators, products, solves, eigs, nn layers, losses,
# apps, calculus, gradient features, vector: about 190), skipped on machines without a GPU --
# and the 20-odd compile tests (the inductor step included). The slowest are listed, to keep
# this step inside its limit.
timeout 420 python3 -m pytest -q -p no:cacheprovider --runslow --durations=15 \
    -k "cuda or compile" tests 2>&1 | tee "$out/gpu_tests.log"
tests_rc=${PIPESTATUS[0]}

timeout 240 python3 benchmarks/gpu_table.py --json "$out/gpu_table.json"
table_rc=$?

# the compiled training step on the GPU (inductor, fullgraph) against eager, and a batch
(cd benchmarks && timeout 300 python3 bench_training_step.py --device cuda --sizes 100000 1000000 \
    --batch-sizes 10000 --repeats 5 --json "$out/gpu_training_step.json")
step_rc=$?
echo "gpu_check: tests exit $tests_rc, table exit $table_rc, training step exit $step_rc"
[ "$tests_rc" -eq 0 ] && [ "$table_rc" -eq 0 ] && [ "$step_rc" -eq 0 ]
