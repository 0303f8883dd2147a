"""Success against map size, with the planning cost at each size: the paper's Table 2 and Figure 2
(AQM's sparse quasimetric graph against GAS's dense one).

    python benchmarks/experiments/node_count.py --aqm RUN_AQM --gas RUN_GAS --deltas 4 8 16 --gas-h 2 4 8 \\
        --episodes 10 --split dev --out benchmarks/results/node_count_medium
    python benchmarks/experiments/node_count.py --aqm RUN_GIANT --deltas 8 12 16 24 --set map.max_keypoints=512 \\
        --split report --out runs/node_count_giant

For a trained AQM run and a trained GAS run (each ``aqm-mjx train`` folders on the same data), every
setting builds its map from the run's dataset and evaluates it on the same episodes (OGBench's
protocol, ``--episodes`` per task, the split named): AQM at each IWE repel radius ``delta`` (map
option ``map.delta``), GAS at each horizon ``H`` (``way_steps``: clustering radius H/2, edges and
subgoal radius H; its trained networks unchanged). Per setting it records

- nodes: keypoints (AQM) or TD-aware clusters (GAS);
- map_s: building the map (jitted, first call, compile included) and map_warm_s (second call);
- fw_s: Floyd-Warshall with next hops on the map's weights, after a compile call;
- bytes_per_env and bytes_shared: the agent state a batch of environments carries (``Decide.init``'s
  output shapes: AQM's own weights, distances and next hops per environment; GAS's goal distances
  per environment and one all-pairs matrix);
- success, its Wilson 95% interval over the episodes, and the evaluation's control steps/s with the
  planner: ``env_steps_per_s`` after the first chunk (when there are several) and
  ``env_steps_per_s_all`` over the whole evaluation, the first call's compile included.

Writes ``OUT/node_count.json`` and ``OUT/node_count.png`` (success against nodes, both methods, with
intervals; planning cost against nodes). Only AQM's agent row and GAS's planner row are run.
``--with EARLIER/node_count.json`` adds the rows of an earlier run of this script to the table and the
picture (marked with the file they come from), after checking that it evaluated the same episodes
(episodes per task, split, backend, seed); that both used the same dataset is the caller's to say.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import assess, files
from aqm_mjx.agent import plan
from aqm_mjx.agent.rollout import episode_inputs, make_decide
from aqm_mjx.evaluation import stats
from aqm_mjx.learn import fit, methods
from aqm_mjx.mapping import build
from aqm_mjx.pipeline import stage_keys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def state_bytes(agent, cfg, graph, obs_size: int) -> tuple[int, int]:
    """``(per environment, shared)`` bytes of the agent state ``Decide.init`` makes (from its shapes)."""
    decide = make_decide(agent, cfg)

    def size(b):
        z = jnp.zeros((b, obs_size), jnp.float32)
        inputs = episode_inputs(jnp.zeros((b, 2, 2), jnp.uint32), jnp.ones(b, jnp.int32), jnp.zeros((3, 3)), 1.0, True)
        shapes = jax.eval_shape(decide.init, agent.aux, graph, z, z, inputs)
        return sum(int(np.prod(x.shape)) * x.dtype.itemsize for x in jax.tree.leaves(shapes))

    one, two = size(1), size(2)
    return two - one, 2 * one - two


def fw_seconds(w) -> float:
    fn = jax.jit(plan.floyd_warshall)
    jax.block_until_ready(fn(w))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(w))
    return time.perf_counter() - t0


def setting(method: str, trained, env, data, cfg, variants, k_map, k_eval, out: str) -> dict:
    """Map, costs and evaluation of one trained run at one setting."""
    agent = trained.agent
    t0 = time.perf_counter()
    graph, m = build.method_map(agent, data, cfg.map, k_map)
    map_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    build.method_map(agent, data, cfg.map, k_map)
    warm = time.perf_counter() - t0
    per_env, shared = state_bytes(agent, cfg.agent, graph, env.obs_size)
    res, _ = assess.map_and_evaluate(trained, env, data, cfg, variants, k_map, k_eval, out, {}, log=lambda *_: None)
    ok = np.asarray(res.success)[np.asarray(res.table.agent) == 0] > 0
    lo, hi = stats.wilson(int(ok.sum()), len(ok))
    return dict(method=method, nodes=int(m['keypoints']), map_s=round(map_s, 3), map_warm_s=round(warm, 3),
                fw_s=round(fw_seconds(graph.w), 5), bytes_per_env=int(per_env), bytes_shared=int(shared),
                success=float(ok.mean()), ci95=[lo, hi], episodes=int(len(ok)),
                env_steps_per_s=res.timing.get('env_steps_per_s_after_first_chunk'), eval_s=res.timing['total_s'],
                env_steps_per_s_all=res.timing['env_steps_per_s_all_chunks'])


SAME_EPISODES = ('episodes', 'split', 'backend', 'seed')


def earlier_rows(path: str, args: dict) -> list:
    """The rows of an earlier ``node_count.json``, each marked with ``from_file``; a ValueError when that
    run evaluated other episodes (:data:`SAME_EPISODES` differ) or the file holds no rows."""
    with open(path, encoding='utf-8') as f:
        old = json.load(f)
    if not isinstance(old, dict) or not old.get('rows') or 'args' not in old:
        raise ValueError(f'{path}: not a node_count.json with rows and args')
    diff = [f"{k} {old['args'].get(k)!r} there, {args[k]!r} here" for k in SAME_EPISODES
            if old['args'].get(k) != args[k]]
    if diff:
        raise ValueError(f'{path} evaluated other episodes: ' + '; '.join(diff))
    return [dict(r, from_file=path) for r in old['rows'] if 'from_file' not in r]


def plot(rows: list, path: str) -> None:
    import matplotlib  # pylint: disable=import-outside-toplevel
    import matplotlib.ticker  # pylint: disable=import-outside-toplevel
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel

    fig, ax = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    for method, colour in (('aqm', 'tab:blue'), ('gas', 'tab:orange')):
        rs = sorted((r for r in rows if r['method'] == method), key=lambda r: r['nodes'])
        if not rs:
            continue
        n = [r['nodes'] for r in rs]
        s = np.array([r['success'] for r in rs])
        err = np.array([[r['success'] - r['ci95'][0], r['ci95'][1] - r['success']] for r in rs]).T
        ax[0].errorbar(n, 100 * s, yerr=100 * err, marker='o', capsize=3, color=colour, label=method.upper())
        ax[1].plot(n, [1e3 * r['fw_s'] for r in rs], marker='o', color=colour, label=f'{method.upper()}: Floyd-Warshall')
        ax[1].plot(n, [r['bytes_per_env'] / 1e3 for r in rs], marker='s', ls='--', color=colour,
                   label=f'{method.upper()}: kB per environment')
    ax[0].set(xscale='log', xlabel='map nodes', ylabel='success (%), 95% Wilson interval', ylim=(0, 100),
              title='success against map size')
    ax[1].set(xscale='log', yscale='log', xlabel='map nodes', ylabel='ms  /  kB', title='planning cost against map size')
    for a in ax:
        a.legend(fontsize=8)
        a.xaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        a.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--aqm', help='an AQM run folder')
    p.add_argument('--gas', help='a GAS run folder')
    p.add_argument('--deltas', type=float, nargs='*', default=[4.0, 8.0, 16.0])
    p.add_argument('--gas-h', type=int, nargs='*', default=[2, 4, 8])
    p.add_argument('--episodes', type=int, default=10, help='episodes per task')
    p.add_argument('--split', default='dev', choices=('dev', 'report'))
    p.add_argument('--backend', default='ogbench', choices=('mjx', 'ogbench'))
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--set', action='append', default=[], metavar='SECTION.FIELD=VALUE',
                   help='override a map, agent or protocol field for every setting, e.g. map.max_keypoints=512')
    p.add_argument('--with', dest='earlier', metavar='NODE_COUNT_JSON',
                   help="an earlier run's node_count.json whose rows join the table and the picture")
    p.add_argument('--out', required=True)
    a = p.parse_args(argv)
    if not (a.aqm or a.gas):
        p.error('give --aqm RUN and/or --gas RUN')
    earlier = earlier_rows(a.earlier, vars(a)) if a.earlier else []
    os.makedirs(a.out, exist_ok=True)
    over = [f'protocol.episodes={a.episodes}', f'protocol.split={a.split}', f'protocol.backend={a.backend}',
            'protocol.workers=1', 'protocol.ablations=', *a.set]
    _, k_map, k_eval = stage_keys(jax.random.PRNGKey(a.seed))
    rows = []
    for method, run, values in (('aqm', a.aqm, a.deltas), ('gas', a.gas, a.gas_h)):
        if not run:
            continue
        env, variants, base_cfg, path = assess.prepare_evaluation(run, None, None, 'base', over)
        base, data = fit.load(run, log=lambda *_: None), assess.read_data(path, env)  # once per run
        for v in values:
            cfg, trained = base_cfg, base
            if method == 'aqm':
                cfg = dataclasses.replace(cfg, map=dataclasses.replace(cfg.map, delta=float(v)))
            else:
                c = dataclasses.replace(base.config, way_steps=int(v))
                trained = base._replace(config=c, learner=methods.get(base.method).make(c, env.obs_size,
                                                                                       env.action_size))
            row = dict(setting=f'{method}: {"delta" if method == "aqm" else "H"} {v:g}',
                       **setting(method, trained, env, data, cfg, variants, k_map, k_eval,
                                 os.path.join(a.out, f'{method}_{v:g}')))
            rows.append(row)
            print(f"{row['setting']:14} {row['nodes']:6d} nodes  success {100 * row['success']:5.1f}% "
                  f"[{100 * row['ci95'][0]:.0f}-{100 * row['ci95'][1]:.0f}]  map {row['map_s']:.1f} s "
                  f"(warm {row['map_warm_s']:.2f})  FW {1e3 * row['fw_s']:.2f} ms  "
                  f"{row['bytes_per_env'] / 1e3:.1f} kB/env + {row['bytes_shared'] / 1e3:.1f} kB shared  "
                  f"eval {row['env_steps_per_s_all']:.0f} steps/s", flush=True)
            files.write_json(os.path.join(a.out, 'node_count.json'), dict(rows=rows + earlier, args=vars(a)))
    plot(rows + earlier, os.path.join(a.out, 'node_count.png'))
    finish(rows + earlier, None)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
