"""Training updates/s at the paper's shapes and at the CPU preset, compile time apart.

    python benchmarks/bench_train.py                    # CPU: about 3 minutes
    python benchmarks/bench_train.py --presets paper --calls 5     # on a GPU

Each row builds the learner for antmaze (29-d observations, 8-d actions) on a random dataset of
100K states in 100 trajectories, runs one jitted chunk of ``updates_per_call`` updates (compile +
run), then ``--calls`` more, timed with ``block_until_ready``. ``--updates-per-call`` overrides the
preset's scan length (the paper preset's 1000 updates take minutes per call on a CPU).
The 'hours for the preset' column is the preset's total updates at the measured rate.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from aqm_mjx.data import dataset as dsm
from aqm_mjx.learn import aqm, fit

from _report import finish  # benchmarks/_report.py (the script's folder is on sys.path)


def rate(preset, calls, upc, objective='saw'):
    over = dict(objective=objective)
    if upc:
        over.update(updates_per_call=upc, log_every=upc, checkpoint_every=upc, steps=upc)
    cfg = aqm.AQMConfig.preset(preset, env='antmaze-medium', **over)
    rng = np.random.default_rng(0)
    n = 100_000
    term = np.zeros(n, bool)
    term[999::1000] = True
    data = dict(observations=rng.normal(size=(n, 29)).astype(np.float32),
                actions=rng.uniform(-1, 1, (n, 8)).astype(np.float32), terminals=term)
    learner = aqm.make(cfg, 29, 8)
    ds = dsm.to_device(data)
    state = learner.init(jax.random.PRNGKey(0))
    chunk = jax.jit(fit.chunk_step(learner.update, cfg.updates_per_call), donate_argnums=0)
    t0 = time.perf_counter()
    state, m = jax.block_until_ready(chunk(state, ds))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(calls):
        state, m = chunk(state, ds)
    jax.block_until_ready(state)
    dt = (time.perf_counter() - t0) / calls
    per_s = cfg.updates_per_call / dt
    full = aqm.AQMConfig.preset(preset).steps
    return dict(preset=preset, objective=objective, batch=cfg.batch_size, q_hidden=list(cfg.q_hidden),
                latent=f'{cfg.n_components}x{cfg.component_size}', pi_hidden=list(cfg.pi_hidden),
                updates_per_call=cfg.updates_per_call, compile_s=round(first - dt, 1), updates_per_s=round(per_s, 1),
                hours_for_preset=round(full / per_s / 3600, 2), finite=bool(np.isfinite(float(m['qrl/loss']))))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--presets', nargs='*', default=['cpu', 'paper'])
    p.add_argument('--calls', type=int, default=2)
    p.add_argument('--updates-per-call', type=int, default=None)
    p.add_argument('--objectives', nargs='*', default=['saw'])
    p.add_argument('--out', default=None)
    a = p.parse_args()
    rows = []
    for preset in a.presets:
        for obj in a.objectives:
            upc = a.updates_per_call or (20 if preset == 'paper' and jax.default_backend() == 'cpu' else None)
            r = rate(preset, a.calls, upc, obj)
            print(r, flush=True)
            rows.append(r)
    finish(rows, a.out)


if __name__ == '__main__':
    main()
