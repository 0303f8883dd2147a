"""Physical sanity checks of the MJX environments that are also run as benchmarks on a GPU.

    python -m aqm_mjx.envs.checks --env antmaze-large --envs 64 --steps 1000
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.envs import mazes


def wall_check(env, n_envs: int, n_steps: int, seed: int = 0, speed: float = 4.0):
    """Random-action rollouts thrown at walls; how close does any torso centre get to a wall block?

    Each of ``n_envs`` ants starts at a random point of a free cell (0.6 to 3.4 m from that cell's
    walls) with its torso moving at ``speed`` m/s towards the nearest wall block, then takes
    ``n_steps`` uniform random actions.

    Returns:
        (torso-to-wall distances ``[n_steps + 1, n_envs]``, largest torso displacement in one
        control step).
    """
    grid = env.layout
    rng = np.random.default_rng(seed)
    free = np.argwhere(grid == 0)
    xy = mazes.ij_to_xy(free[rng.integers(len(free), size=n_envs)]) + rng.uniform(-1.4, 1.4, (n_envs, 2))
    keys = jax.random.split(jax.random.PRNGKey(seed), n_envs)
    xy_j = jnp.asarray(xy, jnp.float32)
    s = jax.jit(jax.vmap(env.reset_to))(keys, xy_j, xy_j)
    walls = mazes.ij_to_xy(np.argwhere(grid == 1))
    nearest = walls[np.argmin(np.linalg.norm(xy[:, None] - walls, axis=-1), axis=-1)]
    v = speed * (nearest - xy) / np.linalg.norm(nearest - xy, axis=-1, keepdims=True)
    data = s.data.replace(qvel=s.data.qvel.at[:, :2].set(jnp.asarray(v, jnp.float32)))
    grids = jnp.broadcast_to(jnp.asarray(grid), (n_envs,) + grid.shape)
    pstep = jax.vmap(env.physics_step)

    @jax.jit
    def roll(data, key):
        def body(d, k):
            d = pstep(d, jax.random.uniform(k, (n_envs, env.action_size), minval=-1, maxval=1), grids)
            return d, d.qpos[:, :2]
        return jax.lax.scan(body, data, jax.random.split(key, n_steps))

    _, xys = roll(data, jax.random.PRNGKey(seed + 1))
    xys = np.concatenate([xy[None], np.asarray(xys)])
    return mazes.wall_distance(xys, grid), float(np.max(np.linalg.norm(np.diff(xys, axis=0), axis=-1)))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--env', default='antmaze-large')
    p.add_argument('--envs', type=int, default=64)
    p.add_argument('--steps', type=int, default=1000)
    p.add_argument('--seed', type=int, default=1)
    a = p.parse_args(argv)
    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel

    env = envs.make(a.env)
    t0 = time.perf_counter()
    dist, moved = wall_check(env, a.envs, a.steps, a.seed)
    print(f'{a.env}: {a.envs} envs x {a.steps} random-action steps in {time.perf_counter() - t0:.1f} s '
          f'({jax.devices()[0].platform}); min torso-wall distance {dist.min():.3f} m '
          f'(torso sphere radius 0.25), {int((dist < 0.5).sum())} env-steps within 0.5 m of a wall, '
          f'max torso displacement in one control step {moved:.3f} m')
    ok = dist.min() >= 0.25 - 0.03
    print('PASS' if ok else 'FAIL')
    return 0 if ok else 1


if __name__ == '__main__':
    raise SystemExit(main())
