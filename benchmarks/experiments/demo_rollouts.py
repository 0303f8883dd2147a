"""Random-action MJX rollouts of a maze environment and a picture of them: the environments alone,
no agent (a quick look that the physics and the rendering work on this machine).

    python benchmarks/experiments/demo_rollouts.py --env antmaze-medium --envs 16 --steps 100 --out runs/rollouts

Writes OUT/ENV_rollouts.png and OUT/summary.json (reset and first-chunk times with compilation, then
control steps per second). bench_env.py measures throughput against plain MuJoCo.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault('TF_CPP_MIN_LOG_LEVEL', '3')
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from aqm_mjx import envs, memory  # noqa: E402
from aqm_mjx.envs.render import render_maze  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    p.add_argument('--envs', type=int, default=16, help='parallel environments')
    p.add_argument('--steps', type=int, default=100, help='control steps per environment')
    p.add_argument('--seed', type=int, default=0, help='random seed')
    p.add_argument('--out', default='runs/rollouts', help='output folder (picture and summary.json)')
    a = p.parse_args(argv)
    for name in ('envs', 'steps'):
        if getattr(a, name) < 1:
            raise SystemExit(f'--{name} must be >= 1; got {getattr(a, name)}')
    env = envs.make(a.env)
    memory.check(a.envs * (memory.env_state_bytes(env) * memory.FACTOR + 8 * a.steps),
                 f'{a.envs:,} environments x {a.steps:,} steps', '--envs (or --steps)')
    os.makedirs(a.out, exist_ok=True)
    print(f'{env}\ndevice: {jax.devices()[0]}; {a.envs} environments x {a.steps} control steps (random actions)')
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


if __name__ == '__main__':
    raise SystemExit(main())
