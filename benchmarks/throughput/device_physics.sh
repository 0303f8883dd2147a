#!/bin/bash
# The fast-physics device check (issue 66), one call under 8 minutes on a lent GPU:
#   1. physics and whole-agent control steps/s at 4k, 16k and 64k environments, ogbench against fast;
#   2. the shipped checkpoint's success on the device in fast mode (5 tasks x 50 report episodes, the
#      closures) beside OGBench's environments on the host (the reference of RESULTS 7.6).
# Every line printed and every JSON goes to $OUT (default ./device_out) as it is made.
#
#   OUT=/tmp/dev bash benchmarks/throughput/device_physics.sh           # on the device (wheels in .whl/)
#   TINY=1 OUT=/tmp/dev bash benchmarks/throughput/device_physics.sh    # on a CPU: tiny sizes, the script's test
#
# Wheels: the device image has its own JAX and no package index; the wheels that travel in `carry`
# (mujoco, mujoco-mjx, ogbench, ...) are installed from .whl/ into /tmp/site when it holds any.
set -o pipefail
OUT=${OUT:-device_out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD:/tmp/site${PYTHONPATH:+:$PYTHONPATH} XLA_PYTHON_CLIENT_PREALLOCATE=false
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/jaxcache}
PY=${PY:-python3}
t0=$(date +%s)
if ls .whl/*.whl >/dev/null 2>&1 && [ ! -d /tmp/site/mujoco ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl 2>&1 | tail -3
fi
if [ "${TINY:-0}" = 1 ]; then
  BATCHES=${BATCHES:-"8 16"}; STEPS=${STEPS:-3}; EPISODES=${EPISODES:-1}; ENVS=${ENVS:-5}; SHIFT=${SHIFT:-base}
  ITERS=${ITERS:-2}; T_EACH=${T_EACH:-900}
else
  BATCHES=${BATCHES:-"4096 16384 65536"}; STEPS=${STEPS:-20}; EPISODES=${EPISODES:-50}; ENVS=${ENVS:-4096}
  SHIFT=${SHIFT:-closures}; ITERS=${ITERS:-5}; T_EACH=${T_EACH:-150}
fi
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null || echo "no nvidia-smi"; nproc
  $PY -c "import jax, mujoco; print('jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__)"
} 2>&1 | tee "$OUT/machine.txt"
echo "setup $(( $(date +%s) - t0 )) s" | tee -a "$OUT/machine.txt"
for preset in ogbench fast; do
  echo "== physics $preset $(( $(date +%s) - t0 )) s"
  timeout "$T_EACH" $PY benchmarks/throughput/bench_env.py --physics-preset "$preset" --mazes medium --batches $BATCHES \
    --iters "$ITERS" --mujoco-steps 200 --json "$OUT/env_$preset.json" 2>&1 | grep -v "^WARNING" | tee "$OUT/env_$preset.txt"
  echo "== whole agent $preset $(( $(date +%s) - t0 )) s"
  timeout "$T_EACH" $PY benchmarks/throughput/bench_evaluate.py --physics-preset "$preset" --batches $BATCHES \
    --steps "$STEPS" --ogbench-steps 200 --checkpoint checkpoints/aqm-antmaze-medium-navigate-cpu-long \
    --out "$OUT/agent_$preset.json" 2>&1 | grep -v "^WARNING" | tee "$OUT/agent_$preset.txt"
done
echo "== closed loop, fast $(( $(date +%s) - t0 )) s"
timeout $(( 2 * T_EACH )) $PY benchmarks/experiments/physics_fidelity.py --parts closed --closed-settings fast \
  --closed-episodes "$EPISODES" --closed-envs "$ENVS" --shift "$SHIFT" --out "$OUT/closed" 2>&1 \
  | grep -v "^WARNING" | grep -v "it/s\|ep/s" | tee "$OUT/closed.txt"
echo "== done $(( $(date +%s) - t0 )) s"
