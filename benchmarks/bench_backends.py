"""The two backends on the same episodes: speed and agreement (issue 18).

    python benchmarks/bench_backends.py --checkpoint RUN/train --episodes 50 --out benchmarks/results/backends_cpu.json

One checkpoint, one map (``stage_keys(PRNGKey(--seed))``, as ``aqm-mjx evaluate``) and one episode
table (AQM, no pruning and the flat policy x every task x ``--episodes``, the same episode keys)
run on

- ``mjx``: our MJX copy of the maze, the whole chunk one jitted program (compiled ahead of time and
  timed apart);
- ``ogbench``: OGBench's own environments (plain MuJoCo) stepped on the host, the agent one jitted,
  batched call per control step (its calls compiled apart, by a warm-up without physics);
  ``--workers`` processes step the environments;
- OGBench's serial loop: one ``antmaze`` environment of OGBench, the same networks' flat controller
  called (jitted, batch 1) once per control step, as OGBench's evaluation runs (``--serial-steps``).

Speed: wall time of the same table on each backend (compile apart) and their ratio; environment
steps/s (for the host backends only steps of unfinished episodes count). Agreement: per row, each
backend's success with its 95% Wilson interval, and whether each mean lies inside the other's
interval; the difference with Newcombe's 95% interval.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
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
from aqm_mjx.run import prepare_evaluation, read_data

from _report import finish  # benchmarks/_report.py (the script's folder is on sys.path)
from bench_evaluate import ogbench_loop_rate


def newcombe(k1: int, n1: int, k2: int, n2: int) -> tuple[float, float]:
    """95% interval of p1 - p2 from the two Wilson intervals (Newcombe's method 10)."""
    p1, p2 = k1 / n1, k2 / n2
    l1, u1 = stats.wilson(k1, n1)
    l2, u2 = stats.wilson(k2, n2)
    d = p1 - p2
    return d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2), d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)


def run_backend(backend, workers, env, trained, graph, cfg, eps, k_eval, progress):
    """Compile apart, then the whole table in one chunk; returns (Results, compile_s, run_s, env_steps)."""
    protocol = dataclasses.replace(cfg.protocol, backend=backend, workers=workers, envs=len(eps.table.task))
    mesh = ev.device_mesh()
    program = ev.make_program(env, trained.agent, cfg.agent, eps.steps, mesh, backend, workers)
    n = len(eps.table.task)
    chunk = -(-n // mesh.devices.size) * mesh.devices.size
    rows = np.arange(chunk) % n
    shard, rep = NamedSharding(mesh, PartitionSpec('env')), NamedSharding(mesh, PartitionSpec())
    inputs = jax.tree.map(lambda x: ev.put_global(x, shard), proto.table_inputs(eps, k_eval, rows))
    aux, g = jax.device_put((trained.agent.aux, graph), rep)
    t0 = time.perf_counter()
    if backend == 'mjx':
        program = program.lower(aux, g, inputs).compile()
    else:
        program.run.warm(aux, g, inputs)
    compile_s = time.perf_counter() - t0
    try:
        res = ev.evaluate(env, trained.agent, graph, cfg.agent, protocol, eps.variants, key=k_eval, program=program,
                          progress=progress)
        env_steps = program.envs.live_steps if backend != 'mjx' else n * eps.steps
    finally:
        if hasattr(program, 'close'):
            program.close()
    return res, compile_s, res.timing['total_s'], env_steps


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--checkpoint', required=True, help='a run folder (RUN/train of `aqm-mjx run`)')
    p.add_argument('--dataset', help="default: the dataset recorded in the run's config.json")
    p.add_argument('--episodes', type=int, default=50, help='episodes per task and row on each backend')
    p.add_argument('--tasks', default='', help='task ids, e.g. 1,2 (default: all)')
    p.add_argument('--workers', type=int, default=0, help='processes stepping the OGBench environments')
    p.add_argument('--serial-steps', type=int, default=3000, help="control steps of OGBench's serial loop")
    p.add_argument('--backends', nargs='+', default=['mjx', 'ogbench'], choices=proto.BACKENDS)
    p.add_argument('--seed', type=int, default=0, help='map and episode keys: stage_keys(PRNGKey(seed))')
    p.add_argument('--no-progress', dest='progress', action='store_false')
    p.add_argument('--out', help='JSON file for the rows')
    a = p.parse_args()
    overrides = [f'protocol.episodes={a.episodes}', 'protocol.ablations=no-pruning,flat']
    if a.tasks:
        overrides.append(f'protocol.tasks={a.tasks}')
    env, variants, cfg, path = prepare_evaluation(a.checkpoint, None, a.dataset, 'base', overrides)
    trained = fit.load(a.checkpoint)
    obs = read_data(path, env)['observations']
    _, k_map, k_eval = stage_keys(jax.random.PRNGKey(a.seed))
    graph, m = trimmed_map(trained.agent, obs, cfg.map, k_map) if trained.agent.plans else (None, {'keypoints': 0})
    eps = proto.plan_episodes(env, cfg.protocol, cfg.agent.kappa, variants, plans=trained.agent.plans,
                              patience=cfg.agent.patience)
    n = len(eps.table.task)
    print(f'{a.checkpoint}: {m["keypoints"]} keypoints; {len(eps.agents)} rows x {len(eps.task_ids)} tasks x '
          f'{a.episodes} episodes = {n} episodes of {eps.steps} steps per backend', flush=True)
    rows, results = [], {}
    serial = ogbench_loop_rate(trained, a.serial_steps)
    print(serial, flush=True)
    rows.append(serial)
    for b in a.backends:
        res, compile_s, run_s, env_steps = run_backend(b, a.workers if b == 'ogbench' else 0, env, trained, graph,
                                                      cfg, eps, k_eval, a.progress)
        results[b] = res
        row = dict(row=f'backend {b}', workers=a.workers if b == 'ogbench' else 0, episodes=n,
                   compile_s=round(compile_s, 1), run_s=round(run_s, 1), episodes_per_s=round(n / run_s, 2),
                   env_steps=int(env_steps), env_steps_per_s=round(env_steps / run_s, 1))
        print(row, flush=True)
        rows.append(row)
    if len(results) == 2:
        rm, ro = rows[-2], rows[-1]
        speed = dict(row='speed', ogbench_vs_mjx=round(rm['run_s'] / ro['run_s'], 2),
                     ogbench_vs_serial_loop=round(ro['env_steps_per_s'] / serial['control_steps_per_s'], 2))
        print(speed)
        rows.append(speed)
        mjx, ogb = results['mjx'], results['ogbench']
        print(f'\nagreement, {a.episodes} episodes x {len(eps.task_ids)} tasks per row and backend '
              '[95% Wilson]; difference ogbench - mjx [95% Newcombe]')
        for i, name in enumerate(mjx.agents):
            sel = mjx.table.agent == i
            k_m, k_o, n_r = int(mjx.success[sel].sum()), int(ogb.success[sel].sum()), int(sel.sum())
            (lm, um), (lo, uo) = stats.wilson(k_m, n_r), stats.wilson(k_o, n_r)
            dl, du = newcombe(k_o, n_r, k_m, n_r)
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
