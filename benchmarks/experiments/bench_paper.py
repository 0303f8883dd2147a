"""AQM at the paper's scale: one command for a GPU.

    python benchmarks/experiments/bench_paper.py --out runs/paper                 # all six cases, 4 seeds each
    python benchmarks/experiments/bench_paper.py --cases medium-navigate --seeds 2 --out runs/paper
    python benchmarks/experiments/bench_paper.py --cases medium-navigate large-navigate --seeds 2 \
        --methods aqm gcbc gcivl gciql qrl crl hiql saw --out runs/paper-baselines   # the baselines at the paper preset

For every case ``MAZE-STYLE`` (antmaze medium / large / giant, navigate / stitch):

1. **Data** collected in MJX with OGBench's recipe *and size* (:func:`aqm_mjx.data.collect.recipe`:
   navigate 1,000 x 1,001 states, giant 500 x 2,001; stitch 5,000 x 201), plus a tenth for validation;
2. **Training** at the ``paper`` preset (10^6 updates, batch 1024, 3 x 512, Appendix 10), ``--seeds``
   seeds as one vmapped program, for AQM and any of the baselines given to ``--methods`` (each at its
   own ``paper`` preset: OGBench's settings for the style);
3. **Evaluation** with OGBench's protocol (``paper`` run preset: 5 tasks x 50 episodes, kappa 0.25).

Each case is an ordinary ``aqm-mjx compare`` folder ``OUT/MAZE-STYLE`` (its ``results.json``, table and
bar chart), so an interrupted run resumes where it stopped. Prints and writes ``OUT/paper.json``: per
case the wall-clock seconds of the whole case and each method's success with its 95% interval. On a CPU the
paper preset takes days (about 72 h per seed here), so the script refuses to start without ``--force``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax

from aqm_mjx import compare, envs, files
from aqm_mjx.data import collect

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

CASES = tuple(f'{m}-{s}' for m in ('medium', 'large', 'giant') for s in ('navigate', 'stitch'))


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--cases', nargs='+', default=list(CASES), choices=CASES)
    p.add_argument('--seeds', type=int, default=4, help='seeds per method and case, trained as one vmapped program')
    p.add_argument('--methods', nargs='+', default=['aqm'], help='methods per case (any of `aqm-mjx methods`)')
    p.add_argument('--collect-episodes', type=int, default=None, help="episodes per case (default: OGBench's)")
    p.add_argument('--collect-batch', type=int, default=1000, help='episodes collected side by side')
    p.add_argument('--set', action='append', default=[], help='override, as aqm-mjx compare --set')
    p.add_argument('--force', action='store_true', help='run on a CPU anyway (days)')
    p.add_argument('--out', required=True, help='folder of the cases')
    return p.parse_args(argv)


def main(argv=None):
    a = parse(argv)
    if jax.default_backend() == 'cpu' and not a.force:
        raise SystemExit('bench_paper: the paper preset takes days on a CPU (about 72 h per seed on 2 cores); '
                         'run it where JAX sees a GPU, or pass --force')
    rows = []
    for case in a.cases:
        maze, style = case.split('-')
        env = f'antmaze-{maze}'
        envs.parse_name(env)
        size = collect.recipe(maze, style)
        episodes = size.episodes if a.collect_episodes is None else a.collect_episodes
        t0 = time.perf_counter()
        res = compare.compare(env, a.methods, a.seeds, os.path.join(a.out, case), preset='paper', style=style,
                              collect_episodes=episodes, collect_batch=a.collect_batch, overrides=a.set)
        row = dict(case=case, seeds=a.seeds, episodes=episodes, states_per_episode=size.steps,
                   wall_s=round(time.perf_counter() - t0, 1), **{m: res['rows'][m]['base'] for m in a.methods})
        rows.append(row)
        print(row, flush=True)
        files.write_json(os.path.join(a.out, 'paper.json'), dict(rows=rows), makedirs=True)
    finish(rows, None)


if __name__ == '__main__':
    main()
