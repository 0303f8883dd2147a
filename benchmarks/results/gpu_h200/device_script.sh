#!/bin/bash
# One device session: install the carried wheels over the image's JAX, then the three measurements, each
# under its own timeout, every log and JSON written to $OUT as it goes.
set -o pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD:/tmp/site MUJOCO_GL=egl XLA_PYTHON_CLIENT_PREALLOCATE=false
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache
t0=$(date +%s)
if [ ! -d /tmp/site/mujoco ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl 2>&1 | tail -3
fi
{ nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv; nproc; uname -m
  python3 -c "import jax, jaxlib, mujoco, flax, optax, chex, numpy; import orbax.checkpoint as o; from mujoco import mjx; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, jax.devices(), 'mujoco', mujoco.__version__, 'flax', flax.__version__, 'optax', optax.__version__, 'numpy', numpy.__version__)"
} 2>&1 | tee $OUT/machine.txt
echo "setup $(( $(date +%s) - t0 )) s"
python3 -c "
import time, jax, jax.numpy as jnp
from aqm_mjx import envs
env = envs.make('antmaze-medium'); t = time.time()
s = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 8), jnp.arange(8) % 5 + 1)
print('smoke: reset ok', s.obs.shape, round(time.time() - t, 1), 's')" 2>&1 | tail -3 | tee $OUT/smoke.txt || exit 3
[ "${SMOKE_ONLY:-0}" = 1 ] && exit 0
if [ "${RUN_EVAL:-1}" = 1 ]; then
echo "== evaluate $(( $(date +%s) - t0 )) s"
timeout ${T_EVAL:-270} python3 benchmarks/throughput/bench_evaluate.py --batches ${BATCHES:-4096 16384} --steps ${STEPS:-50} \
  --ogbench-steps 1000 --out $OUT/evaluate_h200.json 2>&1 | grep -v "^WARNING" | tee $OUT/evaluate_h200.txt
fi
if [ "${RUN_TRAIN:-1}" = 1 ]; then
echo "== train $(( $(date +%s) - t0 )) s"
timeout ${T_TRAIN:-200} python3 benchmarks/throughput/bench_train.py --presets paper --calls 3 --vmap-presets paper \
  --vmap-seeds 4 --methods aqm hiql saw gas hilp gcivl gcbc gciql qrl crl --out $OUT/train_h200.json 2>&1 \
  | grep -v "^WARNING" | tee $OUT/train_h200.txt
fi
echo "== done $(( $(date +%s) - t0 )) s"
