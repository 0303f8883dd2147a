"""Command line: ``aqm-mjx {run,render,envs}``.

The pipeline stages (collect -> train -> keypoints -> evaluate) are being built issue by issue;
``run`` does what exists today and says so.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def _enable_compile_cache():
    import jax  # pylint: disable=import-outside-toplevel

    jax.config.update('jax_compilation_cache_dir', os.path.expanduser('~/.cache/aqm_mjx/jax'))
    jax.config.update('jax_persistent_cache_min_compile_time_secs', 1.0)


def cmd_envs(a):
    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel

    for name in envs.ENV_NAMES:
        agent, maze = envs.parse_name(name)
        tasks = envs.mazes.tasks(maze)
        print(f'{name:<22} grid {envs.mazes.layout(maze).shape}  tasks: '
              + ', '.join(f'{t.init_ij}->{t.goal_ij}' for t in tasks))
    return 0


def keypoint_map_panels(maze: str, deltas, n_candidates: int = 20000, sub: int = 4, seed: int = 0):
    """IWE keypoints and tau = 2 delta edges with the exact maze distance as the quasimetric, one
    panel per delta (the paper's Figures 11-13, with a stand-in for a trained quasimetric)."""
    import jax  # pylint: disable=import-outside-toplevel
    import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx import graph, keypoints  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs import mazes  # pylint: disable=import-outside-toplevel

    grid = mazes.layout(maze)
    table = jnp.asarray(mazes.geodesic_table(grid, sub))
    rng = np.random.default_rng(seed)
    free = np.argwhere(grid == 0)
    xy = mazes.ij_to_xy(free[rng.integers(len(free), size=n_candidates)]) + rng.uniform(-1.9, 1.9, (n_candidates, 2))
    cand = jnp.asarray(mazes.xy_to_subcell(xy, grid.shape, sub))[:, None]

    def lookup(table):
        return lambda x, y: table[x[0], y[0]]

    # The table and candidates are arguments: captured as constants XLA would constant-fold them.
    select = jax.jit(lambda table, cand, key, delta: keypoints.iwe(lookup(table), cand, key, delta, 512))
    dist = lookup(table)
    panels = []
    for delta in deltas:
        kp = select(table, cand, jax.random.PRNGKey(seed), float(delta))
        idx = np.asarray(kp.index)[np.asarray(kp.mask)]
        w = graph.build_graph(dist, cand[jnp.asarray(idx)], jnp.ones(len(idx), bool), float(delta))
        _, ncomp = graph.components(w, jnp.ones(len(idx), bool))
        panels.append(dict(nodes_xy=xy[idx], edges=graph.edge_list(w),
                           title=f'delta {delta:g} m: {len(idx)} keypoints, {int(ncomp)} component(s)'))
    return grid, panels


def cmd_render(a):
    import numpy as np  # pylint: disable=import-outside-toplevel

    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.render import render_maze, render_panels  # pylint: disable=import-outside-toplevel

    _, maze = envs.parse_name(a.env)
    if a.deltas:
        grid, panels = keypoint_map_panels(maze, a.deltas)
        render_panels(grid, panels, a.out)
        for p in panels:
            print(p['title'])
        print(f'wrote {a.out}')
        return 0
    tasks = envs.mazes.tasks(maze)
    render_maze(envs.mazes.layout(maze), a.out, start_xy=np.array([t.init_xy for t in tasks]),
                goal_xy=np.array([t.goal_xy for t in tasks]), title=f'{a.env}: evaluation tasks')
    print(f'wrote {a.out}')
    return 0


def cmd_run(a):
    """Roll a batch of episodes in MJX and draw them (today's main job; later stages to come)."""
    _enable_compile_cache()
    import jax  # pylint: disable=import-outside-toplevel
    import jax.numpy as jnp  # pylint: disable=import-outside-toplevel
    import numpy as np  # pylint: disable=import-outside-toplevel
    from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.render import render_maze  # pylint: disable=import-outside-toplevel

    os.makedirs(a.out, exist_ok=True)
    env = envs.make(a.env)
    print(f'{env}\ndevice: {jax.devices()[0]}; {a.envs} environments x {a.steps} control steps (random actions)')
    print('note: data collection, training, keypoints and evaluation are not built yet; this run '
          'exercises the MJX environments only.')
    n_tasks = env.num_tasks
    keys = jax.random.split(jax.random.PRNGKey(a.seed), a.envs)
    task_ids = jnp.arange(a.envs) % n_tasks + 1
    t0 = time.perf_counter()
    reset = jax.jit(jax.vmap(env.reset))
    state = reset(keys, task_ids)
    jax.block_until_ready(state)
    t_reset = time.perf_counter() - t0

    chunk = 10

    @jax.jit
    def rollout(state, key):
        def body(s, k):
            a_ = jax.random.uniform(k, (a.envs, env.action_size), minval=-1, maxval=1)
            s = jax.vmap(env.step)(s, a_)
            return s, s.data.qpos[:, :2]
        return jax.lax.scan(body, state, jax.random.split(key, chunk))

    xys = [np.asarray(state.data.qpos[:, :2])[None]]
    key = jax.random.PRNGKey(a.seed + 1)
    t0 = time.perf_counter()
    t_first = None
    for _ in tqdm(range(max(1, a.steps // chunk)), desc='control steps', unit=f'x{chunk}'):
        key, k = jax.random.split(key)
        state, xy = rollout(state, k)
        xys.append(np.asarray(xy))
        if t_first is None:
            t_first = time.perf_counter() - t0
    total = time.perf_counter() - t0
    xys = np.concatenate(xys)
    n_chunks = max(1, a.steps // chunk)
    rate = (n_chunks - 1) * chunk * a.envs / max(total - t_first, 1e-9) if n_chunks > 1 else float('nan')
    png = os.path.join(a.out, f'{a.env}_rollouts.png')
    render_maze(env.layout, png, start_xy=xys[0], goal_xy=np.asarray(state.goal_xy), agent_xy=xys[-1],
                trajectories=[xys[:, i] for i in range(min(a.envs, 16))],
                title=f'{a.env}: {a.envs} MJX rollouts, random actions')
    summary = dict(env=a.env, envs=a.envs, steps=int(n_chunks * chunk), reset_compile_and_run_s=round(t_reset, 2),
                   first_chunk_s_incl_compile=round(t_first, 2), control_steps_per_s=round(rate, 1),
                   successes=int(np.asarray(state.success).sum()), picture=png)
    with open(os.path.join(a.out, 'summary.json'), 'w') as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary, indent=1))
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(prog='aqm-mjx', description='Adaptive Quasimetric Mapping on MuJoCo MJX.')
    sub = p.add_subparsers(dest='cmd', required=True)
    r = sub.add_parser('run', help='the main job (today: batched MJX rollouts and a picture)')
    r.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    r.add_argument('--envs', type=int, default=16, help='parallel environments')
    r.add_argument('--steps', type=int, default=100, help='control steps per environment')
    r.add_argument('--seed', type=int, default=0, help='random seed')
    r.add_argument('--out', default='runs/default', help='output folder (picture and summary.json)')
    r.set_defaults(fn=cmd_run)
    e = sub.add_parser('envs', help='list the environments and their evaluation tasks')
    e.set_defaults(fn=cmd_envs)
    d = sub.add_parser('render', help='draw a maze with its evaluation tasks (or keypoint maps) as a PNG')
    d.add_argument('--env', default='antmaze-medium')
    d.add_argument('--out', default='maze.png')
    d.add_argument('--deltas', type=float, nargs='*', default=None,
                   help='draw IWE keypoint maps for these delta values (m), with the exact maze distance')
    d.set_defaults(fn=cmd_render)
    a = p.parse_args(argv)
    try:
        return a.fn(a)
    except (ValueError, TypeError) as err:
        print(f'aqm-mjx: error: {err}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    raise SystemExit(main())
