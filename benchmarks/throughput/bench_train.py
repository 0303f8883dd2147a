"""Training updates/s of every registered method at the ``cpu`` and ``paper`` shapes, compile time
apart, and seeds vmapped against one seed, in one run.

    python benchmarks/throughput/bench_train.py                                   # CPU: every method, 25-35 min on 2 cores
    python benchmarks/throughput/bench_train.py --methods aqm hiql --presets cpu  # some of them
    python benchmarks/throughput/bench_train.py --presets paper --calls 5         # on a GPU
    python benchmarks/throughput/bench_train.py --methods aqm --presets cpu-long --vmap-seeds 1 \
        --push-pairs sampled rolled                                               # AQM's push pairings, as a ratio

Each row builds a method's learner for antmaze (29-d observations, 8-d actions) on a random dataset
of 100K states in 100 trajectories, runs one jitted chunk of ``updates_per_call`` updates (compile +
run), then ``--calls`` more, timed with ``block_until_ready``. On a CPU the paper preset's chunk is
cut to 20 updates (its 1000 take minutes per call). At the presets in ``--vmap-presets`` the same
chunk also runs for ``--vmap-seeds`` seeds under ``jax.vmap`` with their step shared
(``fit.seeds_chunk``, what ``aqm-mjx compare`` does) and the row gives seed-updates/s and the ratio
to one seed measured in the same run; ``--per-seed-step`` also times the vmap that gives each seed
its own step (a branch on the step, as GAS's phase, then computes both sides), as a ratio.
``--phase2`` starts GAS's states at its phase boundary, so that its skill policy's updates are timed
rather than its representation's. 'hours for the preset' is the preset's total updates at the
measured one-seed rate. ``--push-pairs`` times AQM's rows once per pairing of its push term (``rolled``:
the batch's own next states; ``sampled``: B more dataset states through the encoder) and prints the ratio.

    python benchmarks/throughput/bench_train.py --methods gas --presets cpu --vmap-seeds 3 --per-seed-step --phase2
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.data import dataset as dsm
from aqm_mjx.learn import fit, methods

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def _dataset():
    rng = np.random.default_rng(0)
    n = 100_000
    term = np.zeros(n, bool)
    term[999::1000] = True
    return dsm.to_device(dict(observations=rng.normal(size=(n, 29)).astype(np.float32),
                              actions=rng.uniform(-1, 1, (n, 8)).astype(np.float32), terminals=term))


def _timed(chunk, state, ds, calls):
    """(compile + first call s, mean s of ``calls`` more calls, last metrics)."""
    t0 = time.perf_counter()
    state, m = jax.block_until_ready(chunk(state, ds))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(calls):
        state, m = chunk(state, ds)
    jax.block_until_ready(state)
    return first, (time.perf_counter() - t0) / calls, m


def _widths(cfg) -> dict:
    d = cfg.to_dict()
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()
            if k.endswith('hidden') or k in ('latent', 'rep_dim', 'n_components', 'component_size')}


def rate(preset, calls, upc, objective='saw', method='aqm', seeds=1, per_seed_step=False, phase2=False,
         push_pairs=None):
    """One row: ``method`` at ``preset`` (AQM's ``objective`` and ``push_pairs``), one seed, and ``seeds`` vmapped
    if > 1 (step shared; also each seed's own with ``per_seed_step``); GAS from its phase boundary with ``phase2``."""
    entry = methods.get(method)
    over = dict(objective=objective) if 'objective' in entry.config.__dataclass_fields__ else {}
    if push_pairs and 'push_pairs' in entry.config.__dataclass_fields__:
        over['push_pairs'] = push_pairs
    if upc:
        over.update(updates_per_call=upc, log_every=upc, checkpoint_every=upc, steps=upc)
    cfg = entry.preset(preset, env='antmaze-medium', **over)
    learner = entry.make(cfg, 29, 8)
    ds = _dataset()
    start = getattr(cfg, 'tdr_steps', 0) if phase2 else 0

    def init(i):
        return learner.init(jax.random.PRNGKey(i)).replace(step=jnp.int32(start))

    step = fit.chunk_step(learner.update, cfg.updates_per_call)
    first, dt, m = _timed(jax.jit(step, donate_argnums=0), init(0), ds, calls)
    per_s = cfg.updates_per_call / dt
    full = entry.preset(preset).steps
    row = dict(method=method, preset=preset, batch=cfg.batch_size, **_widths(cfg), updates_per_call=cfg.updates_per_call,
               compile_s=round(first - dt, 1), updates_per_s=round(per_s, 1),
               hours_for_preset=round(full / per_s / 3600, 2),
               finite=bool(all(np.isfinite(float(v)) for v in m.values())))
    if method == 'aqm':
        row.update(objective=objective, push_pairs=cfg.push_pairs)
    if phase2:
        row['start_step'] = start
    if seeds > 1:
        def stacked():
            return jax.tree.map(lambda *x: jnp.stack(x), *[init(i) for i in range(seeds)])

        vm = jax.jit(fit.seeds_chunk(learner.update, cfg.updates_per_call), donate_argnums=0)
        first_v, dt_v, _ = _timed(vm, stacked(), ds, calls)
        row.update(vmap_seeds=seeds, vmap_compile_s=round(first_v - dt_v, 1),
                   vmap_seed_updates_per_s=round(seeds * cfg.updates_per_call / dt_v, 1),
                   vmap_vs_one_seed=round(seeds * dt / dt_v, 2))
        if per_seed_step:
            own = jax.jit(jax.vmap(step, in_axes=(0, None)), donate_argnums=0)
            first_o, dt_o, _ = _timed(own, stacked(), ds, calls)
            row.update(per_seed_step_compile_s=round(first_o - dt_o, 1),
                       per_seed_step_seed_updates_per_s=round(seeds * cfg.updates_per_call / dt_o, 1),
                       shared_vs_per_seed_step=round(dt_o / dt_v, 2))
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--methods', nargs='*', default=methods.names(), choices=methods.names())
    p.add_argument('--presets', nargs='*', default=['cpu', 'paper'])
    p.add_argument('--calls', type=int, default=2)
    p.add_argument('--updates-per-call', type=int, default=None)
    p.add_argument('--objectives', nargs='*', default=['saw'], help="AQM's objectives (aqm rows)")
    p.add_argument('--push-pairs', nargs='*', default=[None], choices=['rolled', 'sampled'],
                   help="AQM's push-term pairings (aqm rows; default the preset's)")
    p.add_argument('--vmap-seeds', type=int, default=2, help='seeds under vmap (1: not measured)')
    p.add_argument('--vmap-presets', nargs='*', default=['cpu'], help='presets where vmapped seeds are measured')
    p.add_argument('--per-seed-step', action='store_true',
                   help="also time the vmap that gives each seed its own step (the alternative to compare's)")
    p.add_argument('--phase2', action='store_true', help="start GAS's states at its phase boundary")
    p.add_argument('--out', default=None)
    a = p.parse_args()
    rows = []
    print(f'{"method":<13}{"preset":<9}{"batch":>6}{"upd/call":>9}{"compile s":>10}{"upd/s":>9}{"h for preset":>13}'
          f'{"seeds":>6}{"vmapped seed-upd/s":>20}{"ratio":>7}')
    for preset in a.presets:
        upc = a.updates_per_call or (20 if preset == 'paper' and jax.default_backend() == 'cpu' else None)
        for method in a.methods:
            variants = [(o, pp) for o in a.objectives for pp in a.push_pairs] if method == 'aqm' else [('saw', None)]
            for obj, pairs in variants:
                seeds = a.vmap_seeds if preset in a.vmap_presets else 1
                r = rate(preset, a.calls, upc, obj, method, seeds, a.per_seed_step, a.phase2, pairs)
                label = method if method != 'aqm' or len(variants) == 1 else (
                    'aqm:' + ':'.join(x for x in (obj if len(a.objectives) > 1 else None, pairs) if x))
                vm = (f'{seeds:>6}{r["vmap_seed_updates_per_s"]:>20.1f}{r["vmap_vs_one_seed"]:>7.2f}' if seeds > 1
                      else f'{"-":>6}{"-":>20}{"-":>7}')
                print(f'{label:<13}{preset:<9}{r["batch"]:>6}{r["updates_per_call"]:>9}{r["compile_s"]:>10.1f}'
                      f'{r["updates_per_s"]:>9.1f}{r["hours_for_preset"]:>13.2f}' + vm + ('' if r['finite'] else
                                                                                             '  NON-FINITE'), flush=True)
                if 'shared_vs_per_seed_step' in r:
                    print(f'{"":<13}each seed its own step: {r["per_seed_step_seed_updates_per_s"]:.1f} seed-upd/s '
                          f'(compile {r["per_seed_step_compile_s"]:.1f} s); the shared step '
                          f'x{r["shared_vs_per_seed_step"]:.2f}', flush=True)
                rows.append(r)
                if a.out:  # rows so far, so that a run cut short keeps what it measured
                    with open(a.out, 'w') as f:
                        json.dump(dict(rows=rows, complete=False), f, indent=1)
    by_pairs = {(r['preset'], r.get('objective'), r.get('push_pairs')): r['updates_per_s'] for r in rows}
    for (preset, obj, pairs), ups in by_pairs.items():
        if pairs == 'rolled' and (preset, obj, 'sampled') in by_pairs:
            print(f'aqm {preset} {obj}: rolled push pairs {ups / by_pairs[(preset, obj, "sampled")]:.2f}x the '
                  f'updates/s of sampled ones', flush=True)
    finish(rows, a.out)


if __name__ == '__main__':
    main()
