"""The scripted ant expert re-measured in MJX: flat-ground speed and flips, then waypoint following.

    python benchmarks/experiments/bench_expert.py                       # CPU: about 10 minutes
    python benchmarks/experiments/bench_expert.py --mazes medium --episodes 4 --flat-dirs 8   # quick look

Flat ground: ``--flat-dirs`` commanded directions x 200 control steps from OGBench's reset, random
start phase, at action noise 0, 0.2 and 0.5: mean speed along the command, slowest episode, flips
(torso up-axis pointing below the horizon at the end). Waypoint following: OGBench's 5 evaluation
tasks of each maze, ``--episodes`` per task, 1000 steps, action noise 0.2, command = centre of the
next BFS cell (the goal inside the goal cell): success rate per task.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import envs
from aqm_mjx.data import expert
from aqm_mjx._mjx import mjx


def flat_ground(env, n_dirs, noise, steps=200, seed=0):
    # The ant alone on an unbounded floor: the wall proxies stay parked (env.physics_step would treat
    # cells outside the grid as walls).
    def free_step(data, a):
        data = data.replace(ctrl=jnp.clip(a, -1, 1))
        return jax.lax.scan(lambda d, _: (mjx.step(env.mjx_model, d), None), data, None, length=env.frame_skip)[0]
    angles = jnp.linspace(0, 2 * jnp.pi, n_dirs, endpoint=False)
    cmds = jnp.stack([jnp.cos(angles), jnp.sin(angles)], -1)
    keys = jax.random.split(jax.random.PRNGKey(seed), n_dirs)

    @jax.jit
    def run(keys):
        def one(key, cmd):
            k0, k1, k2 = jax.random.split(key, 3)
            s = env.reset_to(k0, jnp.zeros(2), jnp.zeros(2) + 100.0)
            phase = jax.random.uniform(k1, (), maxval=2 * jnp.pi)

            def body(c, t):
                data, k = c
                k, kn = jax.random.split(k)
                a = expert.gait_action(data.qpos, data.qvel, cmd, t, phase)
                a = a + noise * jax.random.normal(kn, a.shape)
                return (free_step(data, a), k), None

            (data, _), _ = jax.lax.scan(body, (s.data, k2), jnp.arange(steps))
            speed = jnp.dot(data.qpos[:2] - s.data.qpos[:2], cmd) / (steps * 0.1)
            q = data.qpos[3:7]
            up_z = 1 - 2 * (q[1] ** 2 + q[2] ** 2)  # z component of the torso's up axis
            return speed, up_z < 0
        return jax.vmap(one)(keys, cmds)

    speed, flipped = run(keys)
    return np.asarray(speed), np.asarray(flipped)


def waypoints(env, episodes, noise=0.2, seed=0):
    table = jnp.asarray(expert.bfs_next_cell(env.layout))
    n = env.num_tasks * episodes
    task_ids = jnp.arange(n) % env.num_tasks + 1
    keys = jax.random.split(jax.random.PRNGKey(seed), n)

    @jax.jit
    def run(keys, task_ids):
        def one(key, tid):
            k0, k1, k2 = jax.random.split(key, 3)
            s = env.reset(k0, tid)
            phase = jax.random.uniform(k1, (), maxval=2 * jnp.pi)

            def body(c, t):
                s, k = c
                k, kn = jax.random.split(k)
                cmd = expert.waypoint_command(s.data.qpos[:2], s.goal_xy, table, env.layout.shape)
                a = expert.gait_action(s.data.qpos, s.data.qvel, cmd, t, phase)
                s = env.step(s, a + noise * jax.random.normal(kn, a.shape))
                return (s, k), None

            (s, _), _ = jax.lax.scan(body, (s, k2), jnp.arange(env.max_episode_steps))
            return s.success, s.steps
        return jax.vmap(one)(keys, task_ids)

    success, steps = run(keys, task_ids)
    return np.asarray(success), np.asarray(steps), np.asarray(task_ids)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--mazes', nargs='*', default=['medium', 'large'])
    p.add_argument('--episodes', type=int, default=20, help='episodes per task')
    p.add_argument('--flat-dirs', type=int, default=32)
    p.add_argument('--noises', type=float, nargs='*', default=[0.0, 0.2, 0.5])
    a = p.parse_args(argv)
    print(f'# bench_expert: {jax.devices()[0].platform}, OGBench physics (RK4, Newton 100/50)')
    env = envs.make('antmaze-arena')
    for noise in a.noises:
        t0 = time.perf_counter()
        speed, flipped = flat_ground(env, a.flat_dirs, noise)
        print(f'flat ground, noise {noise}: speed along command {speed.mean():.2f} m/s (slowest {speed.min():.2f}), '
              f'flips {int(flipped.sum())}/{len(flipped)}  [{time.perf_counter() - t0:.0f} s]', flush=True)
    for maze in a.mazes:
        env = envs.make(f'antmaze-{maze}')
        t0 = time.perf_counter()
        success, steps, tids = waypoints(env, a.episodes)
        per_task = [success[tids == k].mean() for k in range(1, env.num_tasks + 1)]
        print(f'antmaze-{maze} waypoint follower, noise 0.2, {a.episodes} episodes x {env.num_tasks} tasks: success '
              f'{100 * success.mean():.1f}% (per task {", ".join(f"{100 * x:.0f}" for x in per_task)}), mean steps '
              f'of successes {steps[success > 0].mean() if success.any() else float("nan"):.0f}  '
              f'[{time.perf_counter() - t0:.0f} s]', flush=True)


if __name__ == '__main__':
    main()
