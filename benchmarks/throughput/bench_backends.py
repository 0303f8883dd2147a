"""The two backends on the same episodes: speed and agreement.

    python benchmarks/throughput/bench_backends.py --checkpoint RUN/train --episodes 50 --out benchmarks/results/backends_cpu.json

One checkpoint, one map (``stage_keys(PRNGKey(--seed))``, as ``aqm-mjx evaluate``) and one episode
table (AQM, no pruning and the flat policy x every task x ``--episodes``, the same episode keys)
run on

- ``mjx``: our MJX copy of the maze, a chunk of ``--envs`` environments one jitted program (its
  compile time taken out of the first chunk using the later chunks' rate);
- ``ogbench``: OGBench's own environments (plain MuJoCo) stepped on the host, the agent one jitted,
  batched call per control step (its calls compiled apart, by a warm-up without physics);
  ``--workers`` processes step the environments;
- OGBench's serial loop: one OGBench environment, the agent called (jitted, batch 1) once per control
  step, as OGBench's evaluation runs (``--serial-steps`` steps): with the whole AQM agent (encoder,
  switching, budgets, pruning, replanning, controller: what the backend runs), and with the flat
  controller alone (one network: a lighter agent than the backend's).

Speed: wall time of the same table on each backend (compile apart) and their ratio; environment
steps/s (for the host backends only steps of unfinished episodes count). Agreement: per row, each
backend's success with its 95% Wilson interval, and whether each mean lies inside the other's
interval; the difference with Newcombe's 95% interval.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import jax
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from aqm_mjx.evaluation import evaluate as ev
from aqm_mjx.evaluation import protocol as proto
from aqm_mjx.evaluation import stats
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import trimmed_map
from aqm_mjx.pipeline import stage_keys
from aqm_mjx.assess import prepare_evaluation, read_data

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402
from bench_evaluate import ogbench_loop_rate


def serial_agent_rate(env, trained, graph, cfg, eps, k_eval, n_steps: int) -> dict:
    """OGBench's serial loop with the whole agent: one OGBench environment, the agent's jitted step
    (:func:`~aqm_mjx.agent.rollout.make_decide`, batch 1) once per control step, the AQM row's
    episodes one after another until ``n_steps`` environment steps."""
    from aqm_mjx.agent.rollout import make_host_rollout  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs.ogbench_env import OGBenchEnvs  # pylint: disable=import-outside-toplevel

    rows = np.flatnonzero(eps.table.agent == 0)
    with OGBenchEnvs(env.name, max_episode_steps=eps.steps) as one:
        run = make_host_rollout(one, trained.agent, cfg.agent, eps.steps)
        run.warm(trained.agent.aux, graph, proto.table_inputs(eps, k_eval, rows[:1]))
        t0, i = time.perf_counter(), 0
        while one.live_steps < n_steps:
            run(trained.agent.aux, graph, proto.table_inputs(eps, k_eval, rows[i % len(rows):][:1]))
            i += 1
        dt = time.perf_counter() - t0
    return dict(row='ogbench loop, whole AQM agent (1 env, jitted agent step per control step)',
                steps=one.live_steps, episodes=i, run_s=round(dt, 2), control_steps_per_s=round(one.live_steps / dt, 1))


def run_backend(backend, workers, env, trained, graph, cfg, eps, k_eval, envs_per_chunk, progress):
    """The table in chunks of ``envs_per_chunk``; returns (Results, compile_s, run_s, env_steps).

    mjx: the jitted program compiles inside the first chunk; compile = first chunk - the time the
    later chunks' rate gives it, run = total - compile. (Ahead-of-time compilation is not used: a
    compiled executable called directly runs on the calling thread, and the progress callback of a
    large batch then waits for the interpreter lock that thread holds.) ogbench: the agent's calls
    are compiled by a warm-up without physics, timed apart."""
    protocol = dataclasses.replace(cfg.protocol, backend=backend, workers=workers, envs=envs_per_chunk)
    mesh = ev.device_mesh()
    program = ev.make_program(env, trained.agent, cfg.agent, eps.steps, mesh, backend, workers)
    compile_s = 0.0
    if backend != 'mjx':
        n = len(eps.table.task)
        chunk, _ = ev.chunking(n, envs_per_chunk, mesh.devices.size)  # the shape evaluate will call with
        shard, rep = NamedSharding(mesh, PartitionSpec('env')), NamedSharding(mesh, PartitionSpec())
        inputs = jax.tree.map(lambda x: ev.put_global(x, shard), proto.table_inputs(eps, k_eval, np.arange(chunk) % n))
        t0 = time.perf_counter()
        program.run.warm(*jax.device_put((trained.agent.aux, graph), rep), inputs)
        compile_s = time.perf_counter() - t0
    try:
        res = ev.evaluate(env, trained.agent, graph, cfg.agent, protocol, eps.variants, key=k_eval, program=program,
                          progress=progress)
        env_steps = program.envs.live_steps if backend != 'mjx' else res.timing['chunks'] * res.timing['envs_per_chunk'] * eps.steps
    finally:
        if hasattr(program, 'close'):
            program.close()
    run_s = res.timing['total_s']
    if backend == 'mjx':
        rate = res.timing['env_steps_per_s_after_first_chunk']
        if rate is None:
            raise ValueError('the mjx timing needs at least two chunks: lower --envs')
        compile_s = res.timing['first_chunk_s'] - res.timing['envs_per_chunk'] * eps.steps / rate
        run_s -= compile_s
    return res, compile_s, run_s, env_steps


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--checkpoint', required=True, help='a run folder (RUN/train of `aqm-mjx run`)')
    p.add_argument('--dataset', help="default: the dataset recorded in the run's config.json")
    p.add_argument('--episodes', type=int, default=50, help='episodes per task and row on each backend')
    p.add_argument('--tasks', default='', help='task ids, e.g. 1,2 (default: all)')
    p.add_argument('--envs', type=int, default=250, help='environments per chunk on both backends (mjx: >= 2 chunks)')
    p.add_argument('--workers', type=int, default=0, help='processes stepping the OGBench environments')
    p.add_argument('--serial-steps', type=int, default=3000, help="control steps of OGBench's serial loop")
    p.add_argument('--backends', nargs='+', default=['mjx', 'ogbench'], choices=proto.BACKENDS)
    p.add_argument('--seed', type=int, default=0, help='map and episode keys: stage_keys(PRNGKey(seed))')
    p.add_argument('--set', action='append', default=[],
                   help='agent/protocol override after the defaults, e.g. agent.kappa=3.57 or protocol.ablations=')
    p.add_argument('--no-progress', dest='progress', action='store_false')
    p.add_argument('--out', help='JSON file for the rows')
    a = p.parse_args()
    overrides = [f'protocol.episodes={a.episodes}', 'protocol.ablations=no-pruning,flat']
    if a.tasks:
        overrides.append(f'protocol.tasks={a.tasks}')
    overrides += a.set
    env, variants, cfg, path = prepare_evaluation(a.checkpoint, None, a.dataset, 'base', overrides)
    trained = fit.load(a.checkpoint)
    obs = read_data(path, env)['observations']
    _, k_map, k_eval = stage_keys(jax.random.PRNGKey(a.seed))
    graph, m = trimmed_map(trained.agent, obs, cfg.map, k_map) if trained.agent.plans else (None, {'keypoints': 0})
    eps = proto.plan_episodes(env, cfg.protocol, cfg.agent.kappa, variants, plans=trained.agent.plans,
                              patience=cfg.agent.patience)
    n = len(eps.table.task)
    print(f'{a.checkpoint}: kappa {cfg.agent.kappa}, patience {cfg.agent.patience}; {m["keypoints"]} keypoints; {len(eps.agents)} rows x {len(eps.task_ids)} tasks x '
          f'{a.episodes} episodes = {n} episodes of {eps.steps} steps per backend', flush=True)
    n_dev = ev.device_mesh().devices.size
    chunk, n_chunks = ev.chunking(n, a.envs, n_dev)
    if 'mjx' in a.backends and n_chunks < 2:  # checked before any episode runs, not after MJX's
        most = (n - 1) // n_dev * n_dev  # the largest --envs whose chunk is smaller than n
        p.error(f'the mjx timing needs at least two chunks: {n} episodes in chunks of {chunk} make one; '
                + (f'use --envs {most} or less' if most else f'more episodes than {n_dev} devices x 1 are needed'))
    rows, results = [], {}
    serial = ogbench_loop_rate(trained, a.serial_steps)
    print(serial, flush=True)
    rows.append(serial)
    if trained.agent.plans:
        serial_agent = serial_agent_rate(env, trained, graph, cfg, eps, k_eval, a.serial_steps)
        print(serial_agent, flush=True)
        rows.append(serial_agent)
    else:
        serial_agent = serial
    for b in a.backends:
        res, compile_s, run_s, env_steps = run_backend(b, a.workers if b == 'ogbench' else 0, env, trained, graph,
                                                      cfg, eps, k_eval, a.envs, a.progress)
        results[b] = res
        row = dict(row=f'backend {b}', workers=a.workers if b == 'ogbench' else 0, episodes=n,
                   compile_s=round(compile_s, 1), run_s=round(run_s, 1), episodes_per_s=round(n / run_s, 2),
                   env_steps=int(env_steps), env_steps_per_s=round(env_steps / run_s, 1))
        print(row, flush=True)
        rows.append(row)
    if 'ogbench' in results:
        ro = rows[-1]
        speed = dict(row='speed', ogbench_vs_serial_loop_same_agent=round(
            ro['env_steps_per_s'] / serial_agent['control_steps_per_s'], 2),
            ogbench_vs_serial_loop_flat_policy=round(ro['env_steps_per_s'] / serial['control_steps_per_s'], 2))
        if len(results) == 2:
            speed['ogbench_vs_mjx'] = round(rows[-2]['run_s'] / ro['run_s'], 2)
        print(speed)
        rows.append(speed)
    if len(results) == 2:
        mjx, ogb = results['mjx'], results['ogbench']
        print(f'\nagreement, {a.episodes} episodes x {len(eps.task_ids)} tasks per row and backend '
              '[95% Wilson]; difference ogbench - mjx [95% Newcombe]')
        for i, name in enumerate(mjx.agents):
            sel = mjx.table.agent == i
            k_m, k_o, n_r = int(mjx.success[sel].sum()), int(ogb.success[sel].sum()), int(sel.sum())
            (lm, um), (lo, uo) = stats.wilson(k_m, n_r), stats.wilson(k_o, n_r)
            dl, du = stats.newcombe(k_o, n_r, k_m, n_r)
            inside = bool(lo <= k_m / n_r <= uo and lm <= k_o / n_r <= um)
            row = dict(row=f'agreement {name}', n=n_r, mjx=k_m / n_r, mjx_ci=[lm, um], ogbench=k_o / n_r,
                       ogbench_ci=[lo, uo], diff=(k_o - k_m) / n_r, diff_ci=[dl, du], each_inside_other=inside,
                       per_task={f'task_{t}': [float(mjx.success[sel & (mjx.table.task == t)].mean()),
                                               float(ogb.success[sel & (ogb.table.task == t)].mean())]
                                 for t in eps.task_ids},
                       pruned_per_episode=[float(mjx.pruned[sel].mean()), float(ogb.pruned[sel].mean())])
            rows.append(row)
            print(f'{name:<11} mjx {100 * k_m / n_r:5.1f}% [{100 * lm:4.1f}-{100 * um:5.1f}]  ogbench '
                  f'{100 * k_o / n_r:5.1f}% [{100 * lo:4.1f}-{100 * uo:5.1f}]  diff {100 * (k_o - k_m) / n_r:+5.1f} '
                  f'[{100 * dl:+5.1f}, {100 * du:+5.1f}]  each inside the other: {inside}  '
                  f'cut/ep {row["pruned_per_episode"][0]:.2f} / {row["pruned_per_episode"][1]:.2f}')
            print('            per task (mjx, ogbench): ' + ', '.join(
                f'{k[5:]}: {100 * v[0]:.0f}/{100 * v[1]:.0f}' for k, v in row['per_task'].items()))
    finish(rows, a.out)


if __name__ == '__main__':
    main()
