"""`aqm-mjx evaluate` as one process and as two processes of this machine (JAX's multi-controller
runtime over gloo, one CPU device each): wall time of each, compile included, and whether every
episode's outcome (``episodes.npz``) and the table (``results.json``) are the same.

    python benchmarks/throughput/bench_processes.py                                  # the shipped checkpoint
    python benchmarks/throughput/bench_processes.py --episodes 1 --horizon 30       # a quick look
    python benchmarks/throughput/bench_processes.py --compare --steps 2000          # compare --seeds 2, gcbc and gcivl
    python benchmarks/throughput/bench_processes.py --collect mujoco                # collect, chunks over processes

With ``--compare``: ``aqm-mjx compare --methods gcbc gcivl --seeds 2 --preset ci`` on antmaze-medium
(``--dataset``, or random antmaze-shaped data: 29-d observations, 8-d actions), one process against
two (seed i trained on process i): wall time of each and whether every final training state is the
same bit for bit, every episode and the table.

With ``--collect PHYSICS``: ``aqm-mjx collect`` of antmaze-medium navigate (``--episodes`` training
episodes, a tenth more for validation, ``--batch-of`` at a time; chunk i on process i mod 2) in
``mjx`` or ``mujoco`` (the host): wall time of each and whether both files hold the same arrays.

Both evaluations run in MJX (``--backend mjx``; OGBench's host-stepped environments run in one process),
each with an empty compilation cache of its own, in chunks of ``--envs`` environments: two processes
run every other chunk each, with the program one process runs, so every episode is the one-process
run's bit for bit (the ant's included). On 2 cores the two processes share the cores that one
process's XLA already uses, so the gain is small; the point is that the path is exact.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

SHIPPED = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), 'checkpoints',
                       'aqm-antmaze-medium-navigate-cpu-long')


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--checkpoint', default=SHIPPED)
    p.add_argument('--shift', default='base,close-3-3')
    p.add_argument('--episodes', type=int, default=2)
    p.add_argument('--horizon', type=int, default=200)
    p.add_argument('--envs', type=int, default=10, help='environments per chunk in both runs (at least two chunks '
                                                         'give the second process work)')
    p.add_argument('--compare', action='store_true', help='time `aqm-mjx compare --seeds 2` instead')
    p.add_argument('--steps', type=int, default=2000, help='--compare: training updates per seed')
    p.add_argument('--dataset', default=None, help='--compare: an antmaze-medium .npz (default: random data)')
    p.add_argument('--collect', default=None, choices=['mjx', 'mujoco'], help='time `aqm-mjx collect` instead')
    p.add_argument('--collect-episodes', type=int, default=20, help='--collect: training episodes (and a tenth more)')
    p.add_argument('--collect-steps', type=int, default=1001, help='--collect: states per episode')
    p.add_argument('--batch-of', type=int, default=6, help='--collect: episodes a chunk')
    p.add_argument('--out', default=None, help='JSON file for the rows')
    a = p.parse_args()
    work = tempfile.mkdtemp(prefix='bench-processes-')
    if a.compare:
        argv = [sys.executable, '-m', 'aqm_mjx.cli', 'compare', '--env', 'antmaze-medium', '--methods', 'gcbc',
                'gcivl', '--seeds', '2', '--preset', 'ci', '--dataset', a.dataset or _random_data(work),
                '--set', f'train.steps={a.steps}', '--set', f'protocol.episodes={a.episodes}',
                '--set', f'protocol.horizon={a.horizon}']
    elif a.collect:
        argv = [sys.executable, '-m', 'aqm_mjx.cli', 'collect', '--env', 'antmaze-medium', '--episodes',
                str(a.collect_episodes), '--steps', str(a.collect_steps), '--batch', str(a.batch_of), '--physics',
                a.collect]
    else:
        argv = [sys.executable, '-m', 'aqm_mjx.cli', 'evaluate', '--checkpoint', a.checkpoint, '--backend', 'mjx',
                '--shift', a.shift, '--episodes', str(a.episodes), '--horizon', str(a.horizon), '--ablations',
                'no-pruning', '--calibrate', 'none']
    env = dict(os.environ, JAX_PLATFORMS='cpu', XLA_FLAGS='')
    rows, outs = [], {}
    for n in (1, 2):
        out = outs[n] = os.path.join(work, f'{n}p') + ('.npz' if a.collect else '')
        run_env = dict(env, JAX_COMPILATION_CACHE_DIR=os.path.join(work, f'cache{n}'))
        with socket.socket() as s:
            s.bind(('127.0.0.1', 0))
            port = s.getsockname()[1]
        envs = [] if a.compare or a.collect else ['--envs', str(a.envs)]
        extra = (lambda i: envs) if n == 1 else (lambda i: envs + ['--coordinator', f'127.0.0.1:{port}',
                                                                   '--num-processes', '2', '--process-id', str(i)])
        t0 = time.perf_counter()
        procs = [subprocess.Popen(argv + ['--out', out] + extra(i), env=run_env, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for i in range(n)]
        done = [pr.communicate() for pr in procs]
        wall = time.perf_counter() - t0
        if any(pr.returncode for pr in procs):
            raise SystemExit(f'{n} process(es) failed:\n' + '\n'.join(e[-2000:] for _, e in done))
        if a.compare:
            rows.append(dict(row=f'{n} process{"es" * (n > 1)}', processes=n, wall_s=round(wall, 1)))
            print(rows[-1], flush=True)
            continue
        if a.collect:
            stats = json.load(open(out[:-4] + '.json'))
            rows.append(dict(row=f'{n} process{"es" * (n > 1)}', processes=n, physics=a.collect,
                             episodes=stats['episodes'] + stats['val_episodes'], steps=stats['steps'],
                             batch=stats['batch'], wall_s=round(wall, 1), collect_s=stats['wall_s'],
                             first_chunk_s=stats['first_chunk_s']))
            print(rows[-1], flush=True)
            continue
        res = json.load(open(os.path.join(out, 'results.json')))
        rows.append(dict(row=f'{n} process{"es" * (n > 1)}', processes=n, devices=res['device_count'],
                         envs_per_chunk=res['timing']['envs_per_chunk'],
                         episodes=int(len(np.load(os.path.join(out, 'episodes.npz'))['success'])),
                         wall_s=round(wall, 1), chunks=res['timing']['chunks'],
                         evaluate_s=round(res['timing']['total_s'], 1)))
        print(rows[-1], flush=True)
    if a.compare:
        rows.append(dict(row='two against one', **_same_comparison(outs[1], outs[2]),
                         wall_ratio=round(rows[0]['wall_s'] / rows[1]['wall_s'], 2)))
        print(rows[-1], flush=True)
        finish(rows, a.out)
        return
    if a.collect:
        same = all(all(np.array_equal(x[k], y[k]) for k in x.files) and sorted(x.files) == sorted(y.files)
                   for x, y in ((np.load(outs[1][:-4] + t), np.load(outs[2][:-4] + t)) for t in ('.npz', '-val.npz')))
        rows.append(dict(row='two against one', files_identical=bool(same),
                         wall_ratio=round(rows[0]['wall_s'] / rows[1]['wall_s'], 2)))
        print(rows[-1], flush=True)
        finish(rows, a.out)
        return
    a_eps, b_eps = (np.load(os.path.join(outs[n], 'episodes.npz')) for n in (1, 2))
    same = all(np.array_equal(a_eps[k], b_eps[k]) for k in a_eps.files)
    ra, rb = (json.load(open(os.path.join(outs[n], 'results.json'))) for n in (1, 2))
    rows.append(dict(row='two against one', episodes_identical=bool(same),
                     table_identical=ra['summary'] == rb['summary'] and ra['legs'] == rb['legs'],
                     wall_ratio=round(rows[0]['wall_s'] / rows[1]['wall_s'], 2)))
    print(rows[-1], flush=True)
    finish(rows, a.out)


def _random_data(work: str) -> str:
    """5,000 random antmaze-shaped states in 50 trajectories (the shapes, not a skill)."""
    rng = np.random.default_rng(0)
    terminals = np.zeros(5000, bool)
    terminals[99::100] = True
    path = os.path.join(work, 'antmaze-medium-navigate.npz')
    np.savez(path, observations=rng.normal(size=(5000, 29)).astype(np.float32),
             actions=rng.uniform(-1, 1, (5000, 8)).astype(np.float32), terminals=terminals)
    return path


def _same_comparison(one: str, two: str) -> dict:
    """Whether two comparison folders hold the same final training states (every array, bit for bit),
    the same episodes and the same table."""
    import glob  # pylint: disable=import-outside-toplevel

    import jax  # pylint: disable=import-outside-toplevel

    from aqm_mjx.learn import fit  # pylint: disable=import-outside-toplevel

    def leaves(f):
        return [np.asarray(x) for x in jax.tree.leaves(fit.load(f, log=lambda *_: None).state)]

    folders = sorted(os.path.relpath(f, one) for f in glob.glob(os.path.join(one, 'train', '*', 'seed_*')))
    states = all(len(x) == len(y) and all(np.array_equal(u, v) for u, v in zip(x, y))
                 for x, y in ((leaves(os.path.join(one, f)), leaves(os.path.join(two, f))) for f in folders))
    episodes = all(all(np.array_equal(ea[k], eb[k]) for k in ea.files) for ea, eb in (
        (np.load(e), np.load(e.replace(one, two, 1)))
        for e in glob.glob(os.path.join(one, 'eval', '*', '*', 'episodes.npz'))))
    ra, rb = (json.load(open(os.path.join(f, 'results.json'))) for f in (one, two))
    return dict(run_folders=len(folders), final_states_identical=bool(states), episodes_identical=bool(episodes),
                table_identical=ra['rows'] == rb['rows'])


if __name__ == '__main__':
    main()
