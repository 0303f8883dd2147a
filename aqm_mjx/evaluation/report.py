"""What an evaluation shows a person: the summary table, ``results.json`` and the pictures."""

from __future__ import annotations

import os
from typing import Optional, Sequence

import jax
import numpy as np

from aqm_mjx.files import provenance, write_json
from aqm_mjx.evaluation import calibration, plots
from aqm_mjx.evaluation.evaluate import Results
from aqm_mjx.mapping.graph import Graph, edge_list


def print_summary(res: Results, log=print, false_alarm: float = 0.005) -> None:
    """One line per agent and layout: success per task, the mean, and mean edges pruned; then, per
    layout, the no-pruning row's legs and the budgets that would cut ``false_alarm`` of them (pass
    ``ProtocolConfig.false_alarm``; the default is its default)."""
    cols = [f'task_{t}' for t in res.tasks] + ['mean', 'pruned_mean']
    width = max(len(a) for a in res.agents) + max(len(v) for v in res.variants) + 3
    log(f'{"agent / layout":<{width}}' + ''.join(f'{c.replace("_mean", ""):>9}' for c in cols))
    for a in res.agents:
        for v in res.variants:
            row = res.summary[a][v]
            cells = [f'{100 * row[c]:8.0f}%' for c in cols[:-1]] + [f'{row["pruned_mean"]:9.2f}']
            log(f'{a + " / " + v:<{width}}' + ''.join(cells))
    legs = calibration.report(res, false_alarm)
    for v, row in legs.get(calibration.NO_PRUNING, {}).items():
        c = row['calibrated']
        log(f'legs of no-pruning / {v}: {row["legs"]} completed, steps/d median {row["steps_per_d"]["q50"]:.2f}, '
            f'q95 {row["steps_per_d"]["q95"]:.2f}; longest stall q95 {row["longest_stall"]["q95"]:.0f}. Budgets that '
            f'cut {100 * c["false_alarm"]:g}% of them: agent.kappa={c["kappa"]:.2f} (fixed rule) or '
            f'agent.patience={c["patience"]:.0f} (stall rule)')


MAX_DRAWN = 5000  # the most edges of a dense map a picture draws (its shortest)


def drawn_edges(graph: Graph, limit: int = MAX_DRAWN) -> np.ndarray:
    """``[E, 2]`` the edges a report counts and draws: every finite one of a keypoint graph; of a dense
    map (more than half the pairs joined: TTGS's, where every pair is, weighted past ``tau``) or of any
    map with more than ``limit`` edges, those within ``tau``, at most ``limit`` of them, the shortest
    first: a map of 4,000 nodes is not 16 million lines in a picture, nor the millions within ``tau``
    of a value that reads every pair near (GCIVL's drawn so held 22 GB for half an hour; HIQL's TTGS
    map of giant stitch, 5.7 million finite edges where its value reads some pairs unreachable, 20 GB)."""
    w, mask = np.asarray(graph.w), np.asarray(graph.mask)
    k = int(mask.sum())
    sub = np.isfinite(w[mask][:, mask])
    joined = int(sub.sum() - np.trace(sub))  # off the diagonal (TTGS's is inf, a keypoint graph's 0)
    if joined > 0.5 * k * (k - 1) or joined > limit:
        edges = edge_list(np.where(w <= float(graph.tau), w, np.inf), mask)
        if len(edges) > limit:
            edges = edges[np.argsort(w[edges[:, 0], edges[:, 1]], kind='stable')[:limit]]
        return edges
    return edge_list(w, mask)


def write(res: Results, graph: Optional[Graph], layout, variants: dict, out: str, env_name: str, episodes: int,
          info: dict, name: Optional[str] = None, false_alarm: float = 0.005) -> dict:
    """Write ``out/results.json``, ``success.png``, ``trajectories.png`` and, with several layouts,
    ``heatmap.png``. ``info`` is merged into the JSON (config, checkpoint, keypoints, ...); ``legs``
    holds the leg log, with the no-pruning rows' budgets at ``false_alarm``. Returns the report written."""
    os.makedirs(out, exist_ok=True)
    if not isinstance(graph, Graph):  # a method without a map, or a map that is no graph (HILP's states)
        nodes_xy, edges = np.zeros((0, 2)), np.zeros((0, 2), int)
    else:
        nodes_xy = np.asarray(graph.obs)[:, :2]
        edges = drawn_edges(graph)
    report = dict(env=env_name, **info, edges=int(len(edges)), agents=res.agents, variants=res.variants,
                  tasks=res.tasks, summary=res.summary, legs=calibration.report(res, false_alarm), timing=res.timing,
                  backend=jax.default_backend(), provenance=provenance(),
                  device=str(jax.devices()[0]), device_count=jax.device_count())
    write_json(os.path.join(out, 'results.json'), report)
    write_episodes(res, os.path.join(out, 'episodes.npz'))
    first = res.variants[0]
    plots.success_bars(res.summary, first, res.tasks, os.path.join(out, 'success.png'),
                       title=f'{env_name} ({first}): success per task, {episodes} episodes each', episodes=episodes)
    plots.trajectory_panels(layout, variants, res.traces, nodes_xy, edges, res.agents[0], res.tasks[0],
                            os.path.join(out, 'trajectories.png'))
    if len(variants) > 1:
        vals = np.array([[res.summary[a][v]['mean'] for v in res.variants] for a in res.agents])
        plots.heatmap([f'{name}: {a}' if name else a for a in res.agents], res.variants, vals,
                      os.path.join(out, 'heatmap.png'),
                      title=f'{env_name}: trained on base, evaluated on each layout (mean success)')
    return report


def write_episodes(res: Results, path: str) -> None:
    """``episodes.npz`` beside ``results.json``: one row per episode of the table, for recomputing any
    rate or interval (``np.load(path)``, no pickle): ``agent``, ``layout`` (names), ``task``,
    ``episode`` (its number within its layout and task), ``success``, ``pruned`` (overruns),
    ``removed`` (edges cut), ``legs`` (legs completed). Written whole or not at all."""
    t = res.table
    arrays = dict(agent=np.asarray(res.agents)[np.asarray(t.agent)], layout=np.asarray(res.variants)[np.asarray(t.variant)],
                  task=np.asarray(t.task, np.int32), episode=np.asarray(t.episode, np.int32),
                  success=np.asarray(res.success, bool), pruned=np.asarray(res.pruned, np.int32),
                  removed=np.asarray(res.removed, np.int32), legs=np.asarray(res.n_legs, np.int32))
    tmp = path + '.tmp.npz'
    try:
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _pct(x: float) -> str:
    return f'{100 * x:.0f}'


def _span(ci) -> str:
    return '-' if ci is None else f'{_pct(ci[0])}-{_pct(ci[1])}'


def comparison_markdown(rows: dict, variant: str, tasks: Sequence[int], seeds: Sequence[int], episodes: int) -> str:
    """A comparison (``aqm-mjx compare``'s aggregated rows) as a Markdown table of one layout."""
    head = ('| method | ' + ' | '.join(f'task {t}' for t in tasks) + ' | mean | 95% over seeds | '
            '95% over episodes | per seed |')
    lines = [head, '|' + '---|' * (len(tasks) + 5)]
    for name, row in rows.items():
        r = row[variant]
        lines.append(f'| {name} | ' + ' | '.join(_pct(r[f'task_{t}']) for t in tasks)
                     + f' | **{_pct(r["mean"])}** | {_span(r["seed_ci95"])} | {_span(r["episodes_ci95"])} | '
                     + ', '.join(_pct(x) for x in r['seed_means']) + ' |')
    lines.append(f'\nSuccess (%) on layout {variant}; seeds {", ".join(map(str, seeds))}; {len(tasks)} tasks x '
                 f'{episodes} episodes per seed; the same episodes for every method.')
    return '\n'.join(lines) + '\n'
