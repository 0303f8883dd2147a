"""Pictures of evaluation results: success per task, the shift heatmap (the paper's Figure 3) and
trajectories over the maze with the keypoint graph, the path taken through it and the pruned edges."""

from __future__ import annotations

import textwrap

from typing import Optional, Sequence

import numpy as np

from aqm_mjx.envs import render


def pretty_label(key: str) -> str:
    """A table key as a legend reads it: ``'qrl:seed_0/aqm'`` -> ``'qrl seed 0: aqm'``."""
    key = key.replace(':seed_', ' seed ')
    return key.replace('/', ': ', 1) if '/' in key else key


def success_bars(summary: dict, variant: str, tasks: Sequence[int], path: Optional[str] = None, title: str = '',
                 episodes: Optional[int] = None):
    """Grouped bars: success rate per task (and the mean) for every agent, on one variant; with
    ``episodes`` (per task) each bar has its 95% Wilson interval (the mean's over every task's)."""
    from aqm_mjx.evaluation.stats import wilson  # pylint: disable=import-outside-toplevel

    plt = render.pyplot()
    agents = list(summary)
    cols = [f'task_{t}' for t in tasks] + ['mean']
    fig, ax = plt.subplots(figsize=(1.2 * len(cols) + 2.5, 3.2), dpi=100)
    width = 0.8 / len(agents)
    for k, a in enumerate(agents):
        vals = [100 * summary[a][variant][c] for c in cols]
        x = np.arange(len(cols)) + (k - (len(agents) - 1) / 2) * width
        bars = ax.bar(x, vals, width, label=pretty_label(a))
        tops = list(vals)
        if episodes:
            ns = [episodes] * len(tasks) + [episodes * len(tasks)]
            ci = np.array([wilson(v / 100 * n, n) for v, n in zip(vals, ns)]) * 100
            ax.errorbar(x, vals, yerr=np.clip([np.array(vals) - ci[:, 0], ci[:, 1] - np.array(vals)], 0, None), fmt='none',
                        ecolor='k', elinewidth=0.7, capsize=2)
            tops = list(ci[:, 1])
        for b, v, top in zip(bars, vals, tops):
            ax.text(b.get_x() + b.get_width() / 2, top + 1, f'{v:.0f}', ha='center', fontsize=7)
    ax.set_xticks(np.arange(len(cols)), [c.replace('_', ' ') for c in cols])
    ax.set_ylim(0, 112)
    ax.set_ylabel('success (%)' + (' [95% Wilson]' if episodes else ''))
    ax.set_title(textwrap.fill(title or f'success per task ({variant})', 90), fontsize=9)
    ax.legend(fontsize=8, frameon=False, loc='upper left', bbox_to_anchor=(1.0, 1.0))
    return render.finish(plt, fig, path)  # pylint: disable=protected-access


def method_bars(rows: dict, variant: str, path: Optional[str] = None, title: str = ''):
    """One bar per method: the mean success over seeds, a whisker for the 95% interval over seeds
    (over pooled episodes where there is one seed) and a dot per seed. ``rows`` as
    :func:`aqm_mjx.compare.aggregate` returns them."""
    plt = render.pyplot()
    names = list(rows)
    fig, ax = plt.subplots(figsize=(0.9 * len(names) + 2.0, 3.2), dpi=100)
    for i, n in enumerate(names):
        r = rows[n][variant]
        ci = r['seed_ci95'] or r['episodes_ci95']
        mean = 100 * r['mean']
        ax.bar(i, mean, 0.7, color=f'C{i % 10}', alpha=0.8)
        ax.errorbar(i, mean, yerr=[[mean - 100 * ci[0]], [100 * ci[1] - mean]], color='k', capsize=4, lw=1)
        seeds = 100 * np.asarray(r['seed_means'])
        ax.plot(np.full(len(seeds), i) + np.linspace(-0.15, 0.15, len(seeds)), seeds, 'o', ms=3, color='k')
        ax.text(i, min(100 * ci[1], 100) + 2, f'{mean:.0f}', ha='center', fontsize=8)
    ax.set_xticks(np.arange(len(names)), names, rotation=30 if len(names) > 6 else 0, ha='right' if len(names) > 6
                  else 'center')
    ax.set_ylim(0, 112)
    ax.set_ylabel('success (%)')
    ax.set_title(title or f'success ({variant})', fontsize=9)
    return render.finish(plt, fig, path)  # pylint: disable=protected-access


def heatmap(rows: Sequence[str], cols: Sequence[str], values: np.ndarray, path: Optional[str] = None,
            title: str = '', xlabel: str = 'evaluation layout', ylabel: str = 'trained on / agent'):
    """Success (%) as a heatmap, rows x columns (the paper's Figure 3 layout)."""
    plt = render.pyplot()
    v = 100 * np.asarray(values, float)
    width = 1.1 * len(cols) + 3.3
    fig, ax = plt.subplots(figsize=(width, 0.55 * len(rows) + 1.6), dpi=100)
    im = ax.imshow(v, cmap='RdYlGn', vmin=0, vmax=100, aspect='auto')
    for i in range(v.shape[0]):
        for j in range(v.shape[1]):
            ax.text(j, i, f'{v[i, j]:.0f}', ha='center', va='center', fontsize=8)
    ax.set_xticks(np.arange(len(cols)), cols, rotation=30, ha='right')
    ax.set_yticks(np.arange(len(rows)), rows)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(textwrap.fill(title, int(6 * width)), fontsize=9)  # a long title wraps, not clipped
    fig.colorbar(im, ax=ax, label='success (%)')
    return render.finish(plt, fig, path)  # pylint: disable=protected-access


def visited_path(node: np.ndarray) -> np.ndarray:
    """The keypoints an episode aimed at, in order, without repeats: ``node [T]`` -> ``[P]``."""
    node = np.asarray(node)
    node = node[node >= 0]
    if len(node) == 0:
        return node
    return node[np.r_[True, node[1:] != node[:-1]]]


def trajectory_panels(base_grid, grids: dict, traces: dict, nodes_xy: np.ndarray, edges: np.ndarray,
                      agent: str, task: int, path: Optional[str] = None):
    """One panel per variant: ``agent``'s first episode of ``task``, with the graph, the keypoints it
    aimed at (bold) and the edges it pruned (dashed red)."""
    panels = []
    for name, grid in grids.items():
        tr = traces.get((agent, name, task))
        if tr is None:
            continue
        xy = np.asarray(tr['xy'])
        visited = visited_path(tr['node'])
        cuts = np.asarray(tr['cuts']).reshape(-1, 2)
        panels.append(dict(grid=grid, base_grid=base_grid, nodes_xy=nodes_xy, edges=edges, pruned_edges=cuts,
                           path_xy=nodes_xy[visited] if len(visited) else None, trajectories=[xy],
                           start_xy=xy[0], goal_xy=np.asarray(tr['goal_xy']),
                           title=f'{name}: {"success" if tr["success"] else "fail"}, {tr["pruned"]} pruned'))
    if not panels:
        raise ValueError(f'no trajectory of agent {agent!r} on task {task} was kept')
    return render.render_panels(base_grid, panels, path)


def read_metrics(path: str) -> list[dict]:
    """The lines of a run's ``metrics.jsonl`` (a missing file: none; a torn last line is skipped)."""
    import json  # pylint: disable=import-outside-toplevel
    import os  # pylint: disable=import-outside-toplevel

    from aqm_mjx import files  # pylint: disable=import-outside-toplevel

    if not os.path.exists(path):
        return []
    out = []
    for line in files.read_lines(path, "a run's metrics, one JSON object a line"):
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def curves(runs: dict, keys: Sequence[str], path: Optional[str] = None, title: str = ''):
    """Learning curves: one panel per training metric in ``keys`` and, where the runs hold learning-curve
    points, a last one of success against updates with its 95% Wilson interval (``eval/success`` of
    ``eval/episodes``). ``runs``: ``{label: [metrics.jsonl path per seed]}``; a colour per label, a
    line per seed."""
    from aqm_mjx.evaluation.stats import wilson  # pylint: disable=import-outside-toplevel

    plt = render.pyplot()
    keys = list(keys)
    lines = {label: [read_metrics(p) for p in paths] for label, paths in runs.items()}
    success = any('eval/success' in ln for seeds in lines.values() for ls in seeds for ln in ls)
    n_panels = max(len(keys) + int(success), 1)
    fig, axes = plt.subplots(1, n_panels, figsize=(3.3 * n_panels, 3.0), dpi=100, squeeze=False)
    axes = axes[0]
    for c, (label, seeds) in enumerate(lines.items()):
        colour = f'C{c % 10}'
        for s, ls in enumerate(seeds):
            name = label if s == 0 else None  # one legend entry per label
            for ax, k in zip(axes, keys):
                pts = [(ln['step'], ln[k]) for ln in ls if k in ln]
                if pts:
                    ax.plot(*zip(*pts), color=colour, lw=1, alpha=0.8, label=name)
            pts = [(ln['step'], ln['eval/success'], ln.get('eval/episodes', 0)) for ln in ls if 'eval/success' in ln]
            if pts:
                x, y, n = (np.asarray(v, float) for v in zip(*pts))
                lo, hi = np.array([wilson(yi * ni, int(ni)) if ni else (yi, yi) for yi, ni in zip(y, n)]).T
                axes[-1].plot(x, 100 * y, 'o-', color=colour, lw=1, ms=3, label=name)
                axes[-1].fill_between(x, 100 * lo, 100 * hi, color=colour, alpha=0.12, lw=0)
    for ax, k in zip(axes, keys):
        ax.set_title(k, fontsize=9)
        ax.set_xlabel('updates')
    if success:
        axes[-1].set_title('success (95% Wilson), development episodes', fontsize=9)
        axes[-1].set_xlabel('updates')
        axes[-1].set_ylabel('success (%)')
        axes[-1].set_ylim(-2, 102)
    if len(runs) > 1 or any(len(p) > 1 for p in runs.values()):
        axes[-1].legend(fontsize=7, frameon=False, loc='best')
    if title:
        fig.suptitle(title, fontsize=10)
    return render.finish(plt, fig, path)  # pylint: disable=protected-access
