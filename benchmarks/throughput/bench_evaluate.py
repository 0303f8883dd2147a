"""Evaluation throughput: the full AQM agent against physics alone, and against an OGBench-style loop.

    python benchmarks/throughput/bench_evaluate.py                              # CPU: about 15 minutes
    python benchmarks/throughput/bench_evaluate.py --batches 1024 4096 16384 65536 --steps 100   # on a GPU
    python benchmarks/throughput/bench_evaluate.py --physics-preset fast --batches 16384 --steps 3   # 16k on a CPU

Rows, control steps/s summed over the batch (compile printed apart; the first call compiles and
runs, the second, with new keys, is timed alone):

- 'physics B': ``lax.scan`` over ``vmap(env.step)`` in antmaze-medium from the same resets,
  replaying the agent's recorded actions: the same states and contacts, nothing else (the final
  x-y are checked against the agent's).
- 'agent B': :func:`aqm_mjx.evaluation.evaluate.make_program`, the whole evaluation program: per step, encode
  the state (IQE encoder), switch / time / prune on the keypoint graph, replan the environments that
  pruned (Floyd-Warshall), the main policy's action, the physics. Its networks have the ``cpu``
  preset's shapes (3x256 MLPs, 256 IQE components; random weights unless ``--checkpoint``) and
  ``--keypoints`` keypoints on a fully connected graph, kappa 0. With the default switch radius
  agents rarely reach a keypoint in a short call (few prunes: the typical step). ``--switch-quantile
  0.5`` is the stress case: the switch radius is the median start-to-keypoint distance and every
  edge weight is scaled by 1e-3, so budgets are ~0 steps and agents prune and replan whenever they
  fail to be at their next keypoint at once. Prunes and target changes are printed.
- 'ogbench loop': OGBench's gymnasium ``antmaze-medium-v0`` (plain MuJoCo), one environment, one
  jitted policy call (the same network, batch 1) per control step: how OGBench's evaluation runs.
The ratio ``overhead`` is physics / agent at the same batch; ``vs_ogbench`` is agent / loop.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx import envs
from aqm_mjx.envs import physics
from aqm_mjx.agent import oracle, rollout
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.learn import fit, methods
from aqm_mjx.mapping import graph as graphs

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def timed_twice(fn, make_args):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*make_args(0)))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*make_args(1)))
    return first, time.perf_counter() - t0, out


def physics_replay_rate(env, batch, steps, keys, task_ids, actions):
    """Physics alone: the same resets, then the agent's recorded actions replayed (same contacts)."""

    def run(keys, task_ids, actions):
        states = jax.vmap(env.reset)(keys[:, 0], task_ids)
        s, _ = jax.lax.scan(lambda s, a: (jax.vmap(env.step)(s, a), None), states, actions)
        return s.data.qpos[:, :2]

    fn = jax.jit(run)
    first, second, xy = timed_twice(fn, lambda i: (keys, task_ids, actions))
    return dict(row=f'physics {batch}', batch=batch, steps=steps, compile_s=round(first - second, 1),
                run_s=round(second, 2), control_steps_per_s=round(batch * steps / second, 1)), np.asarray(xy)


def make_agent(env, checkpoint, n_keypoints, seed=0):
    if checkpoint:
        trained = fit.load(checkpoint)
    else:
        cfg = methods.get('aqm').preset('cpu', env=env.name)
        learner = methods.get('aqm').make(cfg, env.obs_size, env.action_size)
        trained = fit.Trained('aqm', cfg, learner, learner.init(jax.random.PRNGKey(seed)), 0, {})
    agent = trained.agent
    # keypoint observations: IWE keypoints of the exact maze distance (positions over the free space)
    _, g = oracle.maze_graph(env.layout, delta=3.0, obs_size=env.obs_size, max_keypoints=512)
    obs = np.array(g.obs[:n_keypoints])
    obs[:, 2] = 0.75  # torso height of a standing ant; the rest of the pose zero
    obs = jnp.asarray(obs)
    z = jax.vmap(lambda o: agent.encode(agent.aux, o))(obs)
    d = lambda x, y: agent.dist(agent.aux, x, y)  # noqa: E731
    w = graphs.build_graph(d, z, jnp.ones(len(obs), bool), 0.0, tau=jnp.inf)  # fully connected
    # attachment radius 1e9: starts and goals attach to every keypoint
    return agent, graphs.Graph(z=z, obs=obs, mask=jnp.ones(len(obs), bool), w=w, tau=jnp.float32(1e9)), trained


def agent_rate(env, agent, graph, batch, steps, kappa, switch_radius):
    cfg = AgentConfig(kappa=kappa, switch_radius=switch_radius)
    program = jax.jit(rollout.make_rollout(env, agent, cfg, steps, record_actions=True))
    ids = np.arange(batch, dtype=np.int32) % 5 + 1
    inputs = [rollout.episode_inputs(rollout.episode_keys(jax.random.PRNGKey(i), np.arange(batch)), ids, env.layout,
                                     kappa, True) for i in range(2)]
    first, second, out = timed_twice(lambda x: program(agent.aux, graph, x), lambda i: (inputs[i],))
    node = np.asarray(out['node'])
    pruned = np.asarray(out['pruned'])
    return dict(row=f'agent {batch}', batch=batch, switch_radius=round(switch_radius, 4), steps=steps, keypoints=int(graph.mask.shape[0]),
                compile_s=round(first - second, 1), run_s=round(second, 2),
                control_steps_per_s=round(batch * steps / second, 1), prunes=int(pruned.sum()),
                node_changes=int((node[1:] != node[:-1]).sum())), (inputs[1].keys, inputs[1].task_ids, out['actions'],
                                                             out['xy'][-1])


def ogbench_loop_rate(trained, n_steps, seed=0):
    import gymnasium  # pylint: disable=import-outside-toplevel
    import ogbench.locomaze  # noqa: F401  pylint: disable=import-outside-toplevel,unused-import

    env = gymnasium.make('antmaze-medium-v0', max_episode_steps=1000)
    agent = trained.agent
    act = jax.jit(lambda aux, o, g: agent.controller(aux, o, g, 0, None))
    params = agent.aux
    obs, info = env.reset(seed=seed, options=dict(task_id=1))
    goal = info['goal']
    np.asarray(act(params, obs, goal))  # compile
    t0 = time.perf_counter()
    for _ in range(n_steps):
        a = np.clip(np.asarray(act(params, obs, goal)), -1, 1)
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            obs, info = env.reset(options=dict(task_id=1))
            goal = info['goal']
    dt = time.perf_counter() - t0
    return dict(row='ogbench loop (1 env, jitted policy per step)', steps=n_steps, run_s=round(dt, 2),
                control_steps_per_s=round(n_steps / dt, 1))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--env', default='antmaze-medium')
    p.add_argument('--batches', type=int, nargs='*', default=[64, 256, 1024])
    p.add_argument('--steps', type=int, default=20, help='control steps per timed call')
    p.add_argument('--keypoints', type=int, default=64)
    p.add_argument('--kappa', type=float, default=0.0)
    p.add_argument('--switch-quantile', type=float, default=0.0,
                   help='stress: the switch radius is this quantile of start-to-keypoint distances and edge '
                        'weights are scaled by 1e-3, so agents prune and replan often; 0: radius 1.0 (typical)')
    p.add_argument('--checkpoint', default=None, help='a trained run folder (default: random cpu-preset weights)')
    p.add_argument('--ogbench-steps', type=int, default=2000)
    p.add_argument('--impl', default='jax', choices=['jax', 'warp'], help="MJX implementation ('warp': MuJoCo Warp, NVIDIA)")
    p.add_argument('--physics-preset', default='ogbench', choices=list(physics.NAMES),
                   help="named physics (aqm_mjx.envs.physics): 'ogbench' (RK4, Newton 100/50) or 'fast', ...")
    p.add_argument('--iterations', type=int, default=None, help="solver iterations (default: the preset's)")
    p.add_argument('--ls-iterations', type=int, default=None, help="line-search iterations (default: the preset's)")
    p.add_argument('--out', default=None, help='JSON file for the rows')
    a = p.parse_args()
    solver = {k: v for k, v in (('iterations', a.iterations), ('ls_iterations', a.ls_iterations)) if v is not None}
    env = envs.make(a.env, physics=a.physics_preset, impl=a.impl, **solver)
    print(f'{a.env}: physics {physics.describe(env.physics)}', flush=True)
    agent, graph, trained = make_agent(env, a.checkpoint, a.keypoints)
    radius = 1.0
    if a.switch_quantile > 0:
        # STRESS: start states within the switch radius of some keypoints, and budgets of ~0 steps
        states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(9), 64), jnp.arange(64) % 5 + 1)
        s0 = jax.vmap(lambda o: agent.encode(agent.aux, o))(states.obs)
        d0 = jax.vmap(lambda x: jax.vmap(lambda z: agent.dist(agent.aux, x, z))(graph.z))(s0)
        radius = float(np.quantile(np.asarray(d0), a.switch_quantile))
        graph = graph.replace(w=graph.w * 1e-3)
    rows = []
    loop = ogbench_loop_rate(trained, a.ogbench_steps)
    print(loop, flush=True)
    rows.append(loop)
    for b in a.batches:
        ag, (keys, ids, actions, xy_end) = agent_rate(env, agent, graph, b, a.steps, a.kappa, radius)
        ph, xy_replay = physics_replay_rate(env, b, a.steps, keys, ids, actions)
        ph['same_final_xy_as_agent'] = bool(np.allclose(xy_replay, np.asarray(xy_end), atol=1e-4))
        print(ph, flush=True)
        ag['overhead_vs_physics'] = round(ph['control_steps_per_s'] / ag['control_steps_per_s'], 2)
        ag['vs_ogbench_loop'] = round(ag['control_steps_per_s'] / loop['control_steps_per_s'], 2)
        print(ag, flush=True)
        rows += [ph, ag]
    print(f'{"batch":>6} {"physics/s":>10} {"agent/s":>9} {"overhead":>8} {"vs ogbench loop":>15} {"prunes":>7}')
    for ph, ag in zip(rows[1::2], rows[2::2]):
        print(f'{ph["batch"]:>6} {ph["control_steps_per_s"]:>10} {ag["control_steps_per_s"]:>9} '
              f'{ag["overhead_vs_physics"]:>8} {ag["vs_ogbench_loop"]:>15} {ag["prunes"]:>7}')
    finish(rows, a.out)


if __name__ == '__main__':
    main()
