"""The whole run as one program: N seeds in one vmapped call against N sequential calls.

    python benchmarks/throughput/bench_pipeline.py                         # CPU: a few minutes
    python benchmarks/throughput/bench_pipeline.py --env antmaze-medium --seeds 8 --updates 2000   # on a GPU

A small run (``tiny`` training preset, ``--updates`` updates; IWE on the dataset; 2 agents x 2 tasks x
``--episodes`` episodes of ``--steps`` control steps) on random point walks in pointmaze-medium
(``aqm_mjx.data.synthetic.point_walks``) or, for an ant maze, on ``--dataset``. 'vmapped': ``jax.jit(
jax.vmap(run))`` over N keys, one call. 'sequential': ``jax.jit(run)`` compiled once, called N times.
Compile time is printed apart (``lower().compile()``); run times exclude it.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax

from aqm_mjx import envs, pipeline
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.data import synthetic

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def timed(compiled, *args):
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    return time.perf_counter() - t0


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--env', default='pointmaze-medium')
    p.add_argument('--dataset', default=None, help='OGBench .npz (needed for an ant maze)')
    p.add_argument('--seeds', type=int, nargs='*', default=[2, 4])
    p.add_argument('--updates', type=int, default=500)
    p.add_argument('--episodes', type=int, default=4)
    p.add_argument('--steps', type=int, default=200)
    p.add_argument('--out', default=None)
    a = p.parse_args()
    env = envs.make(a.env)
    if a.dataset:
        data = ds_io.read_ogbench(a.dataset, obs_size=env.obs_size, action_size=env.action_size, add_info=False)
    else:
        data = synthetic.point_walks(n_traj=200, t_len=100)
    ds = ds_io.to_device(data)
    cfg = pipeline.RunConfig.preset('ci', env=a.env).with_overrides([
        f'train.steps={a.updates}', 'train.updates_per_call=50', 'train.log_every=50', 'train.checkpoint_every=50',
        f'protocol.episodes={a.episodes}', 'protocol.tasks=1,2', f'protocol.horizon={a.steps}', 'protocol.ablations=flat',
        'map.max_keypoints=64', 'map.candidates=2000', 'agent.kappa=1', 'agent.switch_radius=10'])
    run = pipeline.make_run(cfg, env)
    rows = []
    one = jax.jit(run).lower(jax.random.PRNGKey(0), ds)
    t0 = time.perf_counter()
    one = one.compile()
    one_compile = time.perf_counter() - t0
    timed(one, jax.random.PRNGKey(0), ds)  # warm
    for n in a.seeds:
        keys = jax.random.split(jax.random.PRNGKey(1), n)
        t0 = time.perf_counter()
        many = jax.jit(jax.vmap(run, in_axes=(0, None))).lower(keys, ds).compile()
        many_compile = time.perf_counter() - t0
        t_many = timed(many, keys, ds)
        t_seq = sum(timed(one, keys[i], ds) for i in range(n))
        r = dict(seeds=n, envs_per_seed=len(run.episodes.table.task), updates=a.updates, vmapped_compile_s=round(many_compile, 1),
                 single_compile_s=round(one_compile, 1), vmapped_run_s=round(t_many, 2), sequential_run_s=round(t_seq, 2),
                 speedup=round(t_seq / t_many, 2))
        print(r, flush=True)
        rows.append(r)
    print(f'{"seeds":>5} {"vmapped s":>10} {"sequential s":>13} {"speedup":>8} {"compile (vmapped / one)":>24}')
    for r in rows:
        print(f'{r["seeds"]:>5} {r["vmapped_run_s"]:>10} {r["sequential_run_s"]:>13} {r["speedup"]:>8} '
              f'{r["vmapped_compile_s"]:>12} / {r["single_compile_s"]}')
    finish(rows, a.out)


if __name__ == '__main__':
    main()
