"""Does a learned policy go where its goal is? The open-arena direction test.

    python benchmarks/experiments/bench_direction.py --checkpoint runs/antmaze-medium/train
    python benchmarks/experiments/bench_direction.py --checkpoint RUN --policy target

16 ants start at the centre of ``antmaze-arena`` (no inner walls) with goals 8 m away in 16
directions, and walk ``--steps`` control steps under the policy's mean action (clipped to [-1, 1])
with the goal observation as its goal. Printed per policy: the progress along the goal direction (m)
of every ant, its mean, and the mean lateral drift. An ant that ignores its goal still walks but
its progress averages near zero; one that follows it gets about 8 m (it then circles the goal).
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import envs
from aqm_mjx.learn import fit

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def direction_test(trained, which: str, n: int = 16, steps: int = 100, radius: float = 8.0, seed: int = 0) -> dict:
    env = envs.make('antmaze-arena')
    ang = jnp.arange(n) * 2 * jnp.pi / n
    start = jnp.tile(jnp.array([[12.0, 12.0]]), (n, 1))
    unit = jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
    goal = start + radius * unit
    s0 = jax.vmap(env.reset_to)(jax.random.split(jax.random.PRNGKey(seed), n), start, goal)
    agent = trained.agent
    aux = {**agent.aux, 'pi': {'main': agent.aux['pi'][which]}}  # the chosen policy as the controller

    def body(s, _):
        a = jnp.clip(jax.vmap(lambda o, g: agent.controller(aux, o, g, 0, None))(s.obs, s.goal), -1, 1)
        return jax.vmap(env.step)(s, a), None

    s, _ = jax.jit(lambda s: jax.lax.scan(body, s, None, length=steps))(s0)
    d = np.asarray(s.data.qpos[:, :2] - start)
    u = np.asarray(unit)
    progress = (d * u).sum(1)
    lateral = np.abs(d[:, 0] * u[:, 1] - d[:, 1] * u[:, 0])
    return dict(policy=which, conditioning=trained.config.conditioning, steps=steps, goal_m=radius,
                progress_m=[round(float(x), 2) for x in progress], mean_progress_m=round(float(progress.mean()), 2),
                mean_lateral_m=round(float(lateral.mean()), 2), distance_walked_m=round(float(np.linalg.norm(d, axis=1).mean()), 2))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--checkpoint', required=True, help='a training run folder')
    p.add_argument('--policy', nargs='+', default=['main', 'target'], choices=['main', 'target'])
    p.add_argument('--steps', type=int, default=100)
    p.add_argument('--out', default=None, help='JSON file for the rows')
    a = p.parse_args(argv)
    trained = fit.load(a.checkpoint, log=lambda *_: None)
    rows = []
    for which in a.policy:
        r = direction_test(trained, which, steps=a.steps)
        print(json.dumps({k: v for k, v in r.items() if k != 'progress_m'}))
        print('  progress per ant (m):', r['progress_m'])
        rows.append(dict(checkpoint=a.checkpoint, step=trained.step, preset=trained.config.preset, **r))
    finish(rows, a.out)


if __name__ == '__main__':
    main()
