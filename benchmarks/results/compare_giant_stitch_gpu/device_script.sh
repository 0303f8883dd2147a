#!/bin/bash
# The giant stitch comparison's baselines at the cpu-giant preset on a lent GPU: the 500-episode stitch data
# (24.5 MB) travels in the call's carry (runs/giant/stitch500), is checked by SHA-256, then one
# `aqm-mjx compare` trains and evaluates (OGBench's environments in worker processes on the host's cores).
set -o pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD:/tmp/site MUJOCO_GL=disable XLA_PYTHON_CLIENT_PREALLOCATE=false
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache
t0=$(date +%s)
if [ ! -d /tmp/site/mujoco ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl 2>&1 | tail -3
fi
[ "${SETUP_ONLY:-0}" = 1 ] && { python3 -c "import mujoco, ogbench, jax; from mujoco import mjx; print('ok', mujoco.__version__, jax.devices())" 2>&1 | grep -v "warp"; exit 0; }
D=runs/giant/stitch500/antmaze-giant-stitch.npz
sha256sum $D | tee $OUT/data_sha.txt
[ "$(sha256sum $D | cut -c1-64)" = ed97ec624a17b15f2351e6ad787d5112682a1768df533a2c59aef3c58bcd4d60 ] || { echo "data differ"; exit 4; }
echo "setup $(( $(date +%s) - t0 )) s"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee $OUT/machine.txt
M="${METHODS:-gas hiql saw hilp gcivl}"
S=""
for m in $M; do S="$S --set $m:protocol.curve_episodes=0 --set $m:checkpoint_every=25000"; done
timeout ${TLIM:-480} python3 -m aqm_mjx.cli compare --env antmaze-giant --preset cpu-giant --seeds 3 \
  --methods $M --dataset $D --backend ogbench --workers ${WORKERS:-12} $S \
  --out /tmp/gs 2>&1 | tr '\r' '\n' | grep --line-buffered -v "WARNING\|warp" | tee $OUT/compare_log.txt
echo "rc $? at $(( $(date +%s) - t0 )) s" | tee -a $OUT/compare_log.txt
cp /tmp/gs/results.json /tmp/gs/table.md /tmp/gs/success.png /tmp/gs/compare.json $OUT/ 2>/dev/null
(cd /tmp/gs && tar czf $OUT/seeds_meta.tgz $(find . \( -name '*.json' -o -name '*.jsonl' -o -name '*.png' -o -name '*.md' \) | grep -v checkpoints) 2>/dev/null)
ls -la $OUT
echo "== done $(( $(date +%s) - t0 )) s"
