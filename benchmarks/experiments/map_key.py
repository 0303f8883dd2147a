"""How much the map's key moves a trained AQM model's success: the learning curve's map and the
report's map (the two keys ``aqm-mjx compare`` uses: ``stage_keys(PRNGKey(eval_seed))[2]``'s first half
and ``[1]``), each on the curve's episodes (development split, ``--curve-episodes`` a task, the
curve's own key) and on the report episodes (``--episodes`` a task). The planner without pruning, as
the curve runs it, with every map slot kept; the dataset and configs are those the evaluation in
``RUN/eval/aqm/aqm:seed_S/results.json`` recorded.

    python benchmarks/experiments/map_key.py --run runs/giant_stitch --seed 0 \
        --out benchmarks/results/compare_giant_stitch/map_key_seed_0.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax

from aqm_mjx import assess, envs
from aqm_mjx.evaluation.evaluate import evaluate
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import method_map
from aqm_mjx.pipeline import RunConfig, stage_keys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--run', required=True, help='an aqm-mjx compare folder that trained and evaluated aqm')
    p.add_argument('--seed', type=int, default=0, help='which of its seeds')
    p.add_argument('--eval-seed', type=int, default=0, help="the comparison's episode key (its --eval-seed)")
    p.add_argument('--episodes', type=int, default=10, help='report episodes a task')
    p.add_argument('--curve-episodes', type=int, default=2, help="the curve's development episodes a task")
    p.add_argument('--out', help='write the rows as JSON here')
    a = p.parse_args()
    ev_path = os.path.join(a.run, 'eval', 'aqm', f'aqm:seed_{a.seed}', 'results.json')
    if not os.path.exists(ev_path):
        p.error(f'{ev_path} does not exist: give a compare folder whose aqm seed {a.seed} was evaluated')
    ev = json.load(open(ev_path))
    cfg = RunConfig.from_dict(ev['config'])
    trained = fit.load(os.path.join(a.run, 'train', 'aqm', f'seed_{a.seed}'), log=lambda *_: None)
    env = envs.make(cfg.train.env)
    data = assess.read_data(ev['dataset'], env)
    _, k_map_report, k_eval_report = stage_keys(jax.random.PRNGKey(a.eval_seed))
    # compare hands the curve stage_keys(...)[2]; the curve's protocol and agent settings, as it runs them
    curve, agent_cfg, k_map_curve, k_eval_curve = assess.curve_setup(cfg, k_eval_report, a.curve_episodes)
    report = dataclasses.replace(cfg.protocol, ablations=(), calibrate='none', split='report', episodes=a.episodes)
    variants = {'base': env.layout}
    maps = {}
    for name, key in (('report', k_map_report), ('curve', k_map_curve)):
        t0 = time.perf_counter()
        maps[name] = method_map(trained.agent, data, cfg.map, key, static=True)
        print(f"the {name}'s map: {maps[name][1]['keypoints']} keypoints ({time.perf_counter() - t0:.1f} s)",
              flush=True)
    rows = []
    for episodes, proto, key in (('curve', curve, k_eval_curve), ('report', report, k_eval_report)):
        for name, (graph, info) in maps.items():
            t0 = time.perf_counter()
            res = evaluate(env, trained.agent, graph, agent_cfg, proto, variants, key, progress=False)
            s = res.summary[res.agents[0]]['base']
            tasks = [s[f'task_{t}'] for t in res.tasks]
            n = len(tasks) * proto.episodes
            rows.append(dict(seed=a.seed, step=trained.step, map=name, keypoints=info['keypoints'], episodes=episodes,
                             split=proto.split, n=n, success=s['mean'], tasks=tasks,
                             seconds=time.perf_counter() - t0))
            print(f"seed {a.seed}, the {name}'s map, the {episodes} episodes ({proto.split}, {proto.episodes} a task): "
                  f"{100 * s['mean']:.0f}% of {n} (tasks {', '.join(f'{100 * x:.0f}' for x in tasks)}) "
                  f'[{time.perf_counter() - t0:.0f} s]', flush=True)
    finish(rows, a.out)


if __name__ == '__main__':
    main()
