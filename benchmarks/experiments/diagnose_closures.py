"""Why closed-corridor episodes fail: every episode of the AQM agent and of no pruning on the shift
suite's closures, traced step by step in OGBench's environments, each failure put in one class.

    python benchmarks/experiments/diagnose_closures.py --checkpoint runs/antmaze-medium/train --episodes 10 \
        --split dev --out /tmp/diag

For one checkpoint: the map and the calibration pass as ``aqm-mjx evaluate`` makes them (the run
preset of the checkpoint, ``--set`` on top), then the AQM row and no pruning on the training layout
and the suite's closed corridors, ``--episodes`` per task, on the ``--split`` episodes (``dev`` by
default: this script is for choosing settings). Per episode it keeps the path, the target keypoint,
the steps at which a leg was cut and the final pruned graph, and classes the episodes whose task
route the closure lengthens:

- ``success``;
- ``no cut``: never cut a leg, ended within one cell of the closed cell (the budget never ran out);
- ``stuck at the closure``: cut at least once, ended within one cell of the closed cell;
- ``back to the closure``: left the closed cell's neighbourhood after a cut, came back later, and
  ended elsewhere than the goal;
- ``failed on the detour``: ended away from the closure and from the goal without coming back.

It prints the classes per layout and row, the steps to the first cut, the cuts per episode, and
how many edges into or out of the closed cell the final graphs still hold; ``--out`` keeps it all
as JSON (``episodes.json``) for reading episodes one by one.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.agent.rollout import make_decide
from aqm_mjx.envs import mazes, shifts
from aqm_mjx.envs.ogbench_env import OGBenchEnvs
from aqm_mjx.evaluation import protocol
from aqm_mjx.evaluation.evaluate import calibration_pass
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import trimmed_map
from aqm_mjx.pipeline import stage_keys
from aqm_mjx.assess import prepare_evaluation, read_data

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

CLASSES = ('success', 'no cut', 'stuck at the closure', 'back to the closure', 'failed on the detour')


def trace(env, agent, graph, agent_cfg, eps, inputs, workers: int):
    """Run the table's episodes in OGBench's envs; return per-step xy, target node, pruned count,
    success and the final agent state (numpy)."""
    decide = make_decide(agent, agent_cfg)
    init, act = jax.jit(decide.init), jax.jit(decide.act)
    envs = OGBenchEnvs(env.name, max_episode_steps=eps.steps, workers=workers)
    seeds = np.asarray(jax.vmap(lambda k: jax.random.randint(k, (), 0, jnp.iinfo(jnp.int32).max))(inputs.keys[:, 0]))
    try:
        obs, goal, goal_xy = envs.reset(seeds, np.asarray(inputs.task_ids), np.asarray(inputs.grids),
                                        np.asarray(inputs.cells))
        b = len(seeds)
        goal_d = jnp.asarray(goal)
        agents = init(agent.aux, graph, jnp.asarray(obs), goal_d, inputs)
        xy = np.zeros((eps.steps, b, 2), np.float32)
        node = np.full((eps.steps, b), -1, np.int32)
        pruned = np.zeros((eps.steps, b), np.int32)
        done = np.zeros(b, bool)
        for t in range(eps.steps):
            actions, agents = act(agent.aux, graph, agents, jnp.asarray(obs), goal_d, jnp.asarray(done), jnp.int32(t),
                                  inputs)
            obs, xy[t], success, done = envs.step(np.asarray(actions))
            node[t], pruned[t] = np.asarray(agents.node), np.asarray(agents.pruned)
            if done.all():
                xy[t + 1:], node[t + 1:], pruned[t + 1:] = xy[t], node[t], pruned[t]
                break
    finally:
        envs.close()
    return xy, node, pruned, np.asarray(success, bool), jax.device_get(agents), goal_xy


def classify(xy, pruned, success, cell, goal_xy) -> dict:
    """One episode on a closure at ``cell``: its class and the numbers behind it."""
    ij = np.asarray(mazes.xy_to_ij(xy))
    near = np.abs(ij - np.asarray(cell)).max(-1) <= 1  # within one cell of the closed cell (Chebyshev)
    cut_steps = np.flatnonzero(np.diff(np.concatenate([[0], pruned])) > 0)
    first_cut = int(cut_steps[0]) if len(cut_steps) else -1
    came_back = False
    if first_cut >= 0:
        after = near[first_cut:]
        left = np.flatnonzero(~after)
        came_back = bool(len(left) and after[left[0]:].any())
    if success:
        kind = 'success'
    elif near[-1]:
        kind = 'no cut' if first_cut < 0 else 'stuck at the closure'
    elif came_back:
        kind = 'back to the closure'
    else:
        kind = 'failed on the detour'
    return dict(kind=kind, first_cut=first_cut, cuts=int(pruned[-1]), cut_steps=cut_steps.tolist(),
                steps_near=int(near.sum()), first_near=int(np.argmax(near)) if near.any() else -1,
                end_goal_distance=float(np.linalg.norm(xy[-1] - goal_xy)))


def edges_at(w, kp_ij, cell) -> int:
    """Finite edges of ``w`` from outside into the closed cell (keypoints whose state lies in it)."""
    inside = (kp_ij == np.asarray(cell)).all(-1)
    fin = np.isfinite(w) & ~np.eye(len(w), dtype=bool)
    return int((fin & ~inside[:, None] & inside[None, :]).sum())


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--checkpoint', required=True)
    p.add_argument('--dataset', default=None)
    p.add_argument('--episodes', type=int, default=10, help='episodes per task, row and layout')
    p.add_argument('--seed', type=int, default=0, help='map and episode keys: stage_keys(PRNGKey(seed))')
    p.add_argument('--split', default='dev', choices=protocol.SPLITS)
    p.add_argument('--set', action='append', default=[], help='map/agent/protocol override (section.field=value)')
    p.add_argument('--workers', type=int, default=0, help="processes stepping OGBench's environments")
    p.add_argument('--stall-scale', type=float, default=0.0,
                   help='> 0: the AQM row on the stall rule at patience C x the 90th percentile of the longest '
                        "stall in the calibration pass (instead of the pass's false-alarm quantile)")
    p.add_argument('--out', default=None)
    a = p.parse_args()
    env, _, cfg, path = prepare_evaluation(a.checkpoint, None, a.dataset, 'base', a.set)
    trained = fit.load(a.checkpoint, log=lambda *_: None)
    obs = read_data(path, env)['observations']
    _, k_map, k_eval = stage_keys(jax.random.PRNGKey(a.seed))
    graph, m = trimmed_map(trained.agent, obs, cfg.map, k_map)
    kp_ij = np.asarray(mazes.xy_to_ij(np.asarray(graph.obs)[:, :2]))
    t0 = time.perf_counter()
    cal_proto = dataclasses.replace(cfg.protocol, backend='ogbench', workers=a.workers)
    agent_cfg = cfg.agent
    cal = None
    if protocol.needs_calibration(cfg.protocol):
        cal = calibration_pass(env, trained.agent, graph, cfg.agent, cal_proto, k_eval, progress=False)
        agent_cfg = dataclasses.replace(cfg.agent, kappa=cal['kappa'], patience=cal['patience'])
        if a.stall_scale > 0:  # a multiple of the stall scale (q90: stable across keys), not a tail quantile
            q90 = cal['stall_q'][1]  # calibration.QUANTILES = (0.5, 0.9, 0.95, 0.99)
            agent_cfg = dataclasses.replace(agent_cfg, patience=float(max(1, round(a.stall_scale * q90))))
            print(f'stall scale: q90 of the longest stall {q90:g} -> patience {agent_cfg.patience:g}')
    print(f'{a.checkpoint}: {m["keypoints"]} keypoints; calibration ' +
          ('none' if cal is None else f'{cal["episodes"]} episodes, {cal["legs"]} legs -> kappa {cal["kappa"]:g}, '
                                      f'patience {cal["patience"]:g}, paper kappa {cal["kappa_edges"]:g}') +
          f' ({time.perf_counter() - t0:.0f} s)')
    suite = shifts.suite(env.maze)
    variants = {k: g for k, g in suite.items() if k == 'base' or k.startswith('close')}
    proto = dataclasses.replace(cfg.protocol, episodes=a.episodes, ablations=('no-pruning',), split=a.split)
    eps = protocol.plan_episodes(env, proto, agent_cfg.kappa, variants, patience=agent_cfg.patience,
                                 cut_slack=agent_cfg.cut_slack)
    inputs = protocol.table_inputs(eps, k_eval, budgets=None if cal is None else cal['budgets'])
    t0 = time.perf_counter()
    xy, node, pruned, success, agents, goal_xy = trace(env, trained.agent, graph, agent_cfg, eps, inputs, a.workers)
    print(f'{len(success)} episodes traced in {time.perf_counter() - t0:.0f} s')
    t = eps.table
    names = list(variants)
    base_len = shifts.route_lengths(suite['base'], env.maze)
    episodes, summary = [], {}
    for r in range(len(success)):
        agent_name, layout, task = eps.agents[t.agent[r]], names[t.variant[r]], int(t.task[r])
        row = dict(agent=agent_name, layout=layout, task=task, episode=int(t.episode[r]), success=bool(success[r]),
                   cuts=int(pruned[-1, r]), kept=int(np.asarray(agents.kept)[r]))
        if layout.startswith('close'):
            cell = shifts._cell(layout)  # pylint: disable=protected-access
            affected = bool(shifts.route_lengths(variants[layout], env.maze)[task - 1] > base_len[task - 1])
            row.update(affected=affected, **classify(xy[:, r], pruned[:, r], success[r], cell, goal_xy[r]),
                       edges_into_closure_left=edges_at(np.asarray(agents.w[r]), kp_ij, cell),
                       edges_into_closure_map=edges_at(np.asarray(graph.w), kp_ij, cell))
            if affected:
                s = summary.setdefault((agent_name, layout), dict(n=0, **{c: 0 for c in CLASSES}, first_cut=[],
                                                                  cuts=[], left=[]))
                s['n'] += 1
                s[row['kind']] += 1
                s['cuts'].append(row['cuts'])
                s['left'].append(row['edges_into_closure_left'])
                if row['first_cut'] >= 0:
                    s['first_cut'].append(row['first_cut'])
        episodes.append(row)
    print('\nepisodes whose task route the closure lengthens, by class:')
    print(f'{"row":<12} {"layout":<10} {"n":>3} ' + ' '.join(f'{c[:14]:>14}' for c in CLASSES) +
          '  first cut (median)  cuts/ep  edges into the closed cell left / in the map')
    for (ag, lay), s in summary.items():
        fc = f'{np.median(s["first_cut"]):.0f}' if s['first_cut'] else '-'
        cell = shifts._cell(lay)  # pylint: disable=protected-access
        print(f'{ag:<12} {lay:<10} {s["n"]:>3} ' + ' '.join(f'{s[c]:>14}' for c in CLASSES) +
              f'  {fc:>18}  {np.mean(s["cuts"]):7.2f}  {np.mean(s["left"]):.1f} / {edges_at(np.asarray(graph.w), kp_ij, cell)}')
    for ag in eps.agents:
        for lay in names:
            sel = [e for e in episodes if e['agent'] == ag and e['layout'] == lay]
            print(f'{ag:<12} {lay:<10} success {100 * np.mean([e["success"] for e in sel]):5.1f}% of {len(sel)}, '
                  f'cuts/ep {np.mean([e["cuts"] for e in sel]):.2f}, kept (last route) {np.mean([e["kept"] for e in sel]):.2f}')
    if a.out:
        os.makedirs(a.out, exist_ok=True)
        with open(os.path.join(a.out, 'episodes.json'), 'w') as f:
            json.dump(dict(checkpoint=a.checkpoint, split=a.split, seed=a.seed, calibration=cal,
                           keypoints=m['keypoints'], episodes=episodes), f, indent=1)
        np.savez_compressed(os.path.join(a.out, 'traces.npz'), xy=xy, node=node, pruned=pruned,
                            kp_xy=np.asarray(graph.obs)[:, :2], w=np.asarray(graph.w), w_final=np.asarray(agents.w))
    finish([], None)


if __name__ == '__main__':
    main()
