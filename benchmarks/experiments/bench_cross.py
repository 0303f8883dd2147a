"""The training-layout half of the paper's Figure 3: one model per training layout, every
model on every layout, as a cross heatmap (rows: training layout, columns: evaluation layout).

    python benchmarks/experiments/bench_cross.py --env antmaze-medium --layouts base close-3-3 close-6-2 \
        --seeds 1 --episodes 10 --out /tmp/cross

For every training layout ``L`` (``base`` or a variant of :mod:`aqm_mjx.envs.shifts`):

1. **Data** collected in MJX on ``L`` (``--collect-episodes`` navigate episodes; the walls, starts,
   goals and the expert's waypoints are ``L``'s): ``OUT/data/ENV-navigate[-L].npz``.
2. **Training**: AQM at ``--preset``, ``--seeds`` seeds as one vmapped program:
   ``OUT/train/L/seed_S`` (ordinary run folders; resumed, or skipped when complete).
3. **Calibration and evaluation** as ``bench_budgets.py``: the agent without pruning on ``L``
   (other episodes) calibrates the fixed rule's kappa and the stall rule's patience at
   ``--false-alarm``; then every rule (paper's fixed kappa, calibrated kappa, calibrated stall, no
   pruning) runs on the same episodes of every layout of ``--layouts``: ``OUT/eval/L/seed_S.json``
   (kept: a re-run evaluates only what is missing).

Prints one matrix per rule (success pooled over seeds, [95% Wilson], n episodes per cell) and writes
``OUT/cross.json`` and ``OUT/cross.png`` (rows ``training layout / rule``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import envs, files
from aqm_mjx.envs import shifts
from aqm_mjx.evaluation import plots, stats
from aqm_mjx.learn import fit
from aqm_mjx import presets
from aqm_mjx.pipeline import RunConfig, stage_keys
from aqm_mjx.assess import read_data
from aqm_mjx.run import data_stage

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402
from bench_budgets import one_seed

PICTURED = ('fixed, calibrated kappa', 'no pruning')  # the heatmap's rules


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--env', default='antmaze-medium')
    p.add_argument('--layouts', nargs='+', default=['base', 'close-3-3', 'close-6-2'],
                   help='training layouts, which are also the evaluation layouts')
    p.add_argument('--seeds', type=int, default=1, help='AQM seeds per training layout (vmapped)')
    p.add_argument('--preset', default=presets.DEFAULT, choices=presets.names())
    p.add_argument('--collect-episodes', type=int, default=100, help='navigate episodes per training layout')
    p.add_argument('--collect-batch', type=int, default=55)
    p.add_argument('--episodes', type=int, default=10, help='evaluation episodes per task, rule and layout')
    p.add_argument('--calibration-episodes', type=int, default=100,
                   help='calibration episodes (between cells no evaluation task uses)')
    p.add_argument('--split', default='report', choices=('dev', 'report'), help='evaluation episodes')
    p.add_argument('--false-alarm', type=float, default=0.02, help='fraction of traversable legs cut')
    p.add_argument('--seed', type=int, default=0, help='map and episode keys: stage_keys(PRNGKey(seed))')
    p.add_argument('--set', action='append', default=[], help='map/agent/protocol override, e.g. protocol.backend=ogbench')
    p.add_argument('--no-progress', dest='progress', action='store_false')
    p.add_argument('--out', required=True, help='folder for data, run folders, evaluations and the heatmap')
    a = p.parse_args(argv)
    maze = envs.parse_name(a.env)[1]
    for layout in a.layouts:  # unknown names fail here, before any collection
        shifts.variant(maze, layout)
    if len(set(a.layouts)) != len(a.layouts):
        raise SystemExit(f'--layouts repeat: {a.layouts}')
    if not 0 < a.false_alarm < 1:
        raise SystemExit(f'--false-alarm must be in (0, 1); got {a.false_alarm}')
    # bench_budgets.one_seed reads these
    a.false_alarm, a.flat, a.shift, a.dataset, a.cut_slack, a.short = [a.false_alarm], False, 'base', None, [], False
    return a


def train_layout(a, layout: str, log=print) -> list[str]:
    """Collect on ``layout`` and train ``a.seeds`` AQM seeds on it; returns their run folders."""
    env = envs.make(a.env)
    path = data_stage(a.env, a.out, None, a.collect_episodes, a.collect_batch, log, layout=layout)
    cfg = RunConfig.preset(a.preset, method='aqm', env=a.env, style='navigate')
    seeds = list(range(a.seeds))
    folders = [os.path.join(a.out, 'train', layout, f'seed_{s}') for s in seeds]
    keys = jnp.stack([stage_keys(jax.random.PRNGKey(s))[0] for s in seeds])
    fit.train_seeds('aqm', [dataclasses.replace(cfg.train, seed=s) for s in seeds], read_data(path, env), folders, keys,
                    dataset_path=os.path.abspath(path), progress=a.progress, log=log)
    return folders


def cross(a, log=print) -> dict:
    """``{rule: {train layout: {test layout: [successes, episodes]}}}`` over every seed."""
    table: dict = {}
    for layout in a.layouts:
        t0 = time.perf_counter()
        for s, folder in enumerate(train_layout(a, layout, log)):
            path = os.path.join(a.out, 'eval', layout, f'seed_{s}.json')
            if os.path.exists(path):
                res = files.read_json(path, 'an evaluation written by bench_cross.py')
                log(f'{layout} seed {s}: evaluated already ({path})')
            else:
                r = one_seed(folder, a, log, train_layout=layout, layouts=a.layouts)
                res = dict(checkpoint=folder, train_layout=layout, kappa=r['kappa'], patience=r['patience'],
                           calibration=r['calibration'], keypoints=r['keypoints'],
                           rows=[dict(rule=rule, layout=v, success=x['success'], n=x['n'], pruned=x['pruned'])
                                 for (rule, v), x in r['rows'].items()])
                files.write_json(path, res, makedirs=True)
            for row in res['rows']:
                cell = table.setdefault(row['rule'], {}).setdefault(layout, {}).setdefault(row['layout'], [0, 0])
                cell[0] += row['success']
                cell[1] += row['n']
        log(f'training layout {layout}: {time.perf_counter() - t0:.0f} s')
    return table


def main(argv=None):
    a = parse(argv)
    files.check_writable(a.out, what='the benchmark')
    t0 = time.perf_counter()
    table = cross(a)
    print(f'\n{a.env}: {a.preset} preset, {a.collect_episodes} navigate episodes per training layout, {a.seeds} seed(s), '
          f'{a.episodes} episodes per task; success pooled over seeds [95% Wilson] (rows: training layout)')
    out_rows = []
    width = max([len('trained on')] + [len(v) for v in a.layouts])
    for rule, per in table.items():
        print(f'\n{rule}\n{"trained on":<{width}}  ' + '  '.join(f'{v:>18}' for v in a.layouts))
        for tr in a.layouts:
            cells = []
            for te in a.layouts:
                k, n = per[tr][te]
                lo, hi = stats.wilson(k, n)
                cells.append(f'{100 * k / n:5.1f} [{100 * lo:3.0f}-{100 * hi:3.0f}]')
                out_rows.append(dict(rule=rule, train=tr, test=te, success=k, n=n, wilson=[lo, hi]))
            print(f'{tr:<{width}}  ' + '  '.join(f'{c:>18}' for c in cells))
    names = [f'{tr} / {rule}' for rule in PICTURED if rule in table for tr in a.layouts]
    values = np.array([[table[rule][tr][te][0] / table[rule][tr][te][1] for te in a.layouts]
                       for rule in PICTURED if rule in table for tr in a.layouts])
    png = os.path.join(a.out, 'cross.png')
    plots.heatmap(names, a.layouts, values, png, ylabel='trained on / rule',
                  title=f'{a.env}: trained on one layout, tested on each ({a.seeds} seed(s), {a.preset})')
    print(f'\n{time.perf_counter() - t0:.0f} s in all; wrote {png}')
    finish(out_rows, os.path.join(a.out, 'cross.json'))


if __name__ == '__main__':
    main()
