"""Every stage's throughput in one table, each against the alternative measured in the same run.

    python benchmarks/throughput/run_all.py                      # CPU scale: about 3.5 minutes on 2 cores
    python benchmarks/throughput/run_all.py --scale gpu          # accelerator batches
    python benchmarks/throughput/run_all.py --out benchmarks/results/all_cpu.json

Rows (compile time is printed apart from run time; rates are from a second, timed call):

- collection: on-device navigate collection in MJX (scripted trot + BFS waypoints, antmaze-medium),
  transitions/s over the batch, against OGBench's plain-MuJoCo loop (one environment, its oracle
  subgoal each step, random actions; no expert network, so it favours OGBench);
- training: ``learner.chunk`` of the ``cpu`` preset (and ``paper`` at ``--scale gpu``) on 100K
  synthetic transitions, updates/s; no alternative is run (we have no second implementation);
- IWE: ``keypoints.iwe`` over N candidates of a 2-d latent space, seconds per selection;
- planning: ``plan.floyd_warshall_batch`` on B random directed graphs of K nodes, graphs/s,
  against SciPy's ``floyd_warshall`` called once per graph on the same graphs;
- rollouts: the whole AQM evaluation program (encode, switch, budgets, prune, replan, main policy,
  physics) in antmaze-medium, control steps/s over the batch, against the physics alone replaying the
  same actions (the overhead of the agent) and against OGBench's loop (one environment, one jitted
  policy call per step).

The per-stage scripts (``bench_collect.py``, ``bench_train.py``, ``bench_graph.py``,
``bench_evaluate.py``) measure each over more sizes; this one calls their functions once per row.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

from aqm_mjx import envs

import bench_collect
import bench_evaluate
import bench_graph
import bench_train
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

SCALES = {
    'cpu': dict(collect_batch=64, collect_steps=101, train_presets=('cpu',), iwe_n=100_000, fw_k=64, fw_b=256,
                eval_batch=64, eval_steps=20, loop_steps=1000),
    'gpu': dict(collect_batch=4096, collect_steps=201, train_presets=('cpu', 'paper'), iwe_n=1_000_000, fw_k=256,
                fw_b=4096, eval_batch=4096, eval_steps=100, loop_steps=2000),
}


def table(rows: list[dict]) -> str:
    """Fixed-width text table of the rows (stage, measured, ours, alternative, ratio, compile)."""
    head = ('stage', 'measured', 'ours', 'alternative', 'ratio', 'compile s')
    body = [(r['stage'], r['measured'], r['ours'], r.get('alternative', '-'), r.get('ratio', '-'),
             str(r.get('compile_s', '-'))) for r in rows]
    widths = [max(len(str(x[i])) for x in [head] + body) for i in range(len(head))]
    fmt = lambda xs: '  '.join(str(x).ljust(w) for x, w in zip(xs, widths))  # noqa: E731
    return '\n'.join([fmt(head), fmt(['-' * w for w in widths])] + [fmt(b) for b in body])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--scale', choices=sorted(SCALES), default='cpu')
    p.add_argument('--skip', nargs='*', default=[], choices=['collection', 'training', 'iwe', 'planning', 'rollouts'])
    p.add_argument('--out', default=None, help='JSON file for the rows')
    args = p.parse_args(argv)
    s = SCALES[args.scale]
    rows = []
    t_all = time.perf_counter()

    if 'collection' not in args.skip:
        m = bench_collect.rate('antmaze-medium', s['collect_batch'], s['collect_steps'])
        o = bench_collect.ogbench_rate(s['loop_steps'])
        rows.append(dict(stage='collection', measured=f"MJX navigate, batch {m['batch']}, {m['steps']} steps",
                         ours=f"{m['transitions_per_s']:,.0f} transitions/s",
                         alternative=f"{o['transitions_per_s']:,.0f} (OGBench loop)",
                         ratio=f"{m['transitions_per_s'] / o['transitions_per_s']:.2f}x", compile_s=m['compile_s']))
        print(rows[-1], flush=True)

    if 'training' not in args.skip:
        for preset in s['train_presets']:
            r = bench_train.rate(preset, calls=2, upc=100 if args.scale == 'cpu' else None)
            rows.append(dict(stage='training', measured=f"{preset} preset, batch {r['batch']}, pi {r['pi_hidden']}",
                             ours=f"{r['updates_per_s']:,.1f} updates/s", compile_s=r['compile_s']))
            print(rows[-1], flush=True)

    if 'iwe' not in args.skip:
        compile_s, run_s, k, overflow = bench_graph.bench_iwe(s['iwe_n'], 0.12, 256, 65536)
        rows.append(dict(stage='IWE', measured=f"{s['iwe_n']:,} candidates -> {k} keypoints{' (overflow)' if overflow else ''}",
                         ours=f'{run_s:.2f} s per selection', compile_s=round(compile_s, 1)))
        print(rows[-1], flush=True)

    if 'planning' not in args.skip:
        compile_s, jax_rate, sp_rate = bench_graph.bench_fw(s['fw_k'], s['fw_b'], 3, np.random.default_rng(0), True)
        rows.append(dict(stage='planning', measured=f"Floyd-Warshall, K {s['fw_k']}, batch {s['fw_b']}",
                         ours=f'{jax_rate:,.0f} graphs/s ({1e3 / jax_rate:.3f} ms/graph)',
                         alternative=f'{sp_rate:,.0f} graphs/s (SciPy)', ratio=f'{jax_rate / sp_rate:.2f}x',
                         compile_s=round(compile_s, 1)))
        print(rows[-1], flush=True)

    if 'rollouts' not in args.skip:
        env = envs.make('antmaze-medium')
        agent, graph, trained = bench_evaluate.make_agent(env, None, 64)
        b, steps = s['eval_batch'], s['eval_steps']
        a, (keys, ids, actions, xy) = bench_evaluate.agent_rate(env, agent, graph, b, steps, 0.0, 5.0)
        ph, xy_ph = bench_evaluate.physics_replay_rate(env, b, steps, keys, ids, actions)
        np.testing.assert_allclose(xy_ph, np.asarray(xy), atol=1e-4)  # the replay is the same motion
        lp = bench_evaluate.ogbench_loop_rate(trained, s['loop_steps'])
        rows.append(dict(stage='rollouts', measured=f'AQM agent, antmaze-medium, batch {b}, 64 keypoints',
                         ours=f"{a['control_steps_per_s']:,.0f} steps/s",
                         alternative=f"{ph['control_steps_per_s']:,.0f} (physics alone); "
                                     f"{lp['control_steps_per_s']:,.0f} (OGBench loop)",
                         ratio=f"{a['control_steps_per_s'] / ph['control_steps_per_s']:.2f}x; "
                               f"{a['control_steps_per_s'] / lp['control_steps_per_s']:.2f}x",
                         compile_s=a['compile_s']))
        print(rows[-1], flush=True)

    print()
    print(table(rows))
    print(f'scale {args.scale}; total {time.perf_counter() - t_all:.0f} s; {len(jax.devices())} device(s)')
    finish(rows, args.out)


if __name__ == '__main__':
    main()
