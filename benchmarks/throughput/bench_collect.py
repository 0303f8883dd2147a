"""Dataset collection throughput in MJX and in host MuJoCo (transitions/s) against OGBench's own
collection loop.

    python benchmarks/throughput/bench_collect.py                        # CPU: about 16 minutes
    python benchmarks/throughput/bench_collect.py --batches 1024 4096 --dataset-episodes 1000   # on a GPU

Rows 'mjx batch B': ``B`` navigate episodes of ``--steps`` states in antmaze-medium with the
scripted trot, one jitted call (``vmap`` over episodes, ``lax.scan`` over time). The first call
compiles and runs; the second call, on new keys, is timed alone (``block_until_ready``).
Row 'ogbench loop': OGBench's gymnasium ``antmaze-medium-v0`` stepped one environment at a time
with ``terminate_at_goal=False``, the BFS oracle queried every step as its collection script does,
and random actions instead of the SAC expert's network (so its rate is an upper bound on OGBench's).
Rows 'host batch B': the same episodes with ``collect --physics mujoco``
(:class:`aqm_mjx.data.collect.HostEpisodes`: MuJoCo's C library with OGBench's static walls, one
``MjData`` per episode, the expert jitted over the batch once per step), timed the same way, with
the ratio to the MJX row of the same batch; one row per ``--host-threads`` count (threads stepping the
batch's episodes, the same data for every count; 0: one per core), with the ratio to one thread.
Rows 'navigate 100K': :func:`aqm_mjx.data.collect.collect` end to end for ``--dataset-episodes`` episodes of
1001 states plus the tenth for validation, compile included, with each ``--dataset-physics``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

from aqm_mjx import envs
from aqm_mjx.data import collect

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def rate(env_name, batch, steps, physics='mjx', seed=0, threads=1):
    """The row of ``batch`` navigate episodes of ``steps`` states in ``physics`` ('mjx' or 'mujoco'): a first
    call (compile and run), then a second on new keys timed alone."""
    env = envs.make(env_name, max_episode_steps=steps, terminate_at_goal=False)
    if physics == 'mjx':
        run = jax.jit(jax.vmap(collect.episode_fn(env, 'navigate', steps, 0.2)))
    else:
        run = collect.HostEpisodes(env, 'navigate', steps, 0.2, threads=threads)
    keys = jax.random.split(jax.random.PRNGKey(seed), 2 * batch)
    t0 = time.perf_counter()
    jax.block_until_ready(run(keys[:batch]))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(run(keys[batch:]))
    second = time.perf_counter() - t0
    name = 'mjx' if physics == 'mjx' else f'host ({run.threads} thread{"s" * (run.threads > 1)})'
    return dict(row=f'{name} batch {batch}', batch=batch, steps=steps,
                transitions=batch * steps, compile_s=round(first - second, 1), run_s=round(second, 2),
                transitions_per_s=round(batch * steps / second, 1),
                flipped=int((~np.asarray(out['upright'][:, -1])).sum()))


def ogbench_rate(n_steps, seed=0):
    import gymnasium  # pylint: disable=import-outside-toplevel
    import ogbench.locomaze  # noqa: F401  pylint: disable=import-outside-toplevel,unused-import

    env = gymnasium.make('antmaze-medium-v0', terminate_at_goal=False, max_episode_steps=1001)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    u = env.unwrapped
    t0 = time.perf_counter()
    for t in range(n_steps):
        xy = u.get_xy()
        u.get_oracle_subgoal(xy, u.cur_goal_xy)
        _, _, term, trunc, _ = env.step(rng.uniform(-1, 1, 8))
        if term or trunc:
            env.reset()
    dt = time.perf_counter() - t0
    return dict(row='ogbench loop (1 env, oracle, no network)', transitions=n_steps, run_s=round(dt, 2),
                transitions_per_s=round(n_steps / dt, 1))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--env', default='antmaze-medium')
    p.add_argument('--batches', type=int, nargs='*', default=[64, 256])
    p.add_argument('--steps', type=int, default=201, help='states per episode in the throughput rows')
    p.add_argument('--ogbench-steps', type=int, default=3000)
    p.add_argument('--dataset-episodes', type=int, default=100,
                   help='navigate episodes of 1001 states for the end-to-end row (0 skips it)')
    p.add_argument('--dataset-batch', type=int, default=110)
    p.add_argument('--dataset-physics', nargs='*', default=['mjx', 'mujoco'], choices=collect.PHYSICS)
    p.add_argument('--no-host', action='store_true', help='skip the host rows')
    p.add_argument('--host-threads', type=int, nargs='*', default=[1, 0],
                   help='threads of the host rows (0: one per core)')
    p.add_argument('--no-ogbench', action='store_true', help="skip OGBench's loop (the ratios to it too)")
    p.add_argument('--out', default=None, help='JSON file for the rows')
    a = p.parse_args()
    rows = []
    base = None if a.no_ogbench else ogbench_rate(a.ogbench_steps)
    if base:
        print(base, flush=True)
        rows.append(base)
    for b in a.batches:
        r = rate(a.env, b, a.steps)
        if base:
            r['vs_ogbench_loop'] = round(r['transitions_per_s'] / base['transitions_per_s'], 2)
        print(r, flush=True)
        rows.append(r)
        one = None
        for threads in [] if a.no_host else a.host_threads:
            h = rate(a.env, b, a.steps, 'mujoco', threads=threads)
            if base:
                h['vs_ogbench_loop'] = round(h['transitions_per_s'] / base['transitions_per_s'], 2)
            h['vs_mjx_same_batch'] = round(h['transitions_per_s'] / r['transitions_per_s'], 2)
            one = one or h
            h['vs_first_host_row'] = round(h['transitions_per_s'] / one['transitions_per_s'], 2)
            print(h, flush=True)
            rows.append(h)
    for physics in a.dataset_physics if a.dataset_episodes else []:
        res = collect.collect(collect.CollectConfig(env=a.env, style='navigate', episodes=a.dataset_episodes,
                                                    batch=a.dataset_batch, physics=physics), progress=False)
        s = res.stats
        r = dict(row=f'navigate {s["episodes"]}+{s["val_episodes"]} episodes x {s["steps"]} ({physics})',
                 transitions=s['transitions'], train_transitions=s['episodes'] * s['steps'], batch=s['batch'],
                 wall_s_incl_compile=s['wall_s'], transitions_per_s_incl_compile=round(s['transitions'] / s['wall_s'], 1),
                 goals_reached_per_episode=round(s['goals_reached_mean'], 2), flipped_episodes=s['flipped_episodes'])
        if base:
            r['vs_ogbench_loop_time'] = round((s['transitions'] / base['transitions_per_s']) / s['wall_s'], 2)
        print(r, flush=True)
        rows.append(r)
    finish(rows, a.out)


if __name__ == '__main__':
    main()
