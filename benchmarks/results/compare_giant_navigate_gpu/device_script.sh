#!/bin/bash
# The giant navigate comparison's baselines at the cpu-giant preset on the H200: the 400-episode data travels
# in four pieces (.d1-.d4, earlier warm calls), is joined and checked, then one `aqm-mjx compare` trains and
# evaluates (OGBench's environments in worker processes on the host's cores) under one timeout.
#
# How it ran (one lease, 15 minutes of device time in all): call 1 carried the wheels (.whl) and this script
# and ran `SETUP_ONLY=1 bash .gpu/giant.sh`; calls 2-4 each carried one quarter of the data file
# (`split -n 4` of runs/giant/data400/antmaze-giant-navigate.npz) and copied it to /tmp (a path not carried
# again is removed there); call 5 moved the quarters back beside the fourth and ran
# `TLIM=545 bash .gpu/giant.sh` (HIQL and SAW finished, GAS reached 31,000 updates); call 6 re-ran the same
# compare command for 195 s (GAS resumed from 30,000 and did not reach its evaluation).
set -o pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD:/tmp/site MUJOCO_GL=disable XLA_PYTHON_CLIENT_PREALLOCATE=false
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache
t0=$(date +%s)
if [ ! -d /tmp/site/mujoco ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl 2>&1 | tail -3
fi
[ "${SETUP_ONLY:-0}" = 1 ] && { python3 -c "import mujoco, ogbench, jax; from mujoco import mjx; print('ok', mujoco.__version__, jax.devices())" 2>&1 | grep -v "warp"; exit 0; }
mkdir -p runs/giant/data400
D=runs/giant/data400/antmaze-giant-navigate.npz
ls -la .d1 .d2 .d3 .d4 | grep part
cat .d1/part .d2/part .d3/part .d4/part > $D
echo "$(sha256sum $D | cut -c1-64)" | tee $OUT/data_sha.txt
[ "$(sha256sum $D | cut -c1-64)" = c012dc22de4a3d57a79ad708d9eaa61d172ae5bbf63da7eaa30163c7e2f3c80d ] || { echo "data differ"; exit 4; }
echo "setup $(( $(date +%s) - t0 )) s"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee $OUT/machine.txt
S=""
for m in ${METHODS:-hiql saw gas hilp gcivl}; do S="$S --set $m:protocol.curve_episodes=0"; done
timeout ${TLIM:-480} python3 -m aqm_mjx.cli compare --env antmaze-giant --preset cpu-giant --seeds 3 \
  --methods ${METHODS:-hiql saw gas hilp gcivl} --dataset $D --backend ogbench --workers ${WORKERS:-12} $S \
  --out /tmp/gg 2>&1 | tr '\r' '\n' | grep --line-buffered -v "WARNING\|warp" | tee $OUT/compare_log.txt
echo "rc $? at $(( $(date +%s) - t0 )) s" | tee -a $OUT/compare_log.txt
cp /tmp/gg/results.json /tmp/gg/table.md /tmp/gg/success.png /tmp/gg/compare.json $OUT/ 2>/dev/null
(cd /tmp/gg && tar czf $OUT/seeds_meta.tgz $(find . \( -name '*.json' -o -name '*.jsonl' -o -name '*.png' -o -name '*.md' \) | grep -v checkpoints) 2>/dev/null)
ls -la $OUT
echo "== done $(( $(date +%s) - t0 )) s"
