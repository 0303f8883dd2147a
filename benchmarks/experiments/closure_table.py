"""The closed-corridor table of several models from one ``aqm-mjx evaluate`` folder.

    aqm-mjx evaluate --checkpoint A --checkpoint B ... --shift closures --episodes 20 \
        --ablations no-pruning paper=1 paper=cal --backend ogbench --out OUT
    python benchmarks/experiments/closure_table.py OUT [--rows aqm no-pruning paper=1 paper=cal]

    python benchmarks/experiments/closure_table.py --pool S1 S2 S3 [--rows aqm no-pruning flat] [--json OUT.json]

``OUT`` is the folder of several checkpoints (one sub-folder each) or of one (its ``results.json`` alone;
the model is labelled ``--label``, default the checkpoint folder's name).

Per model (checkpoint) and row: success on the unchanged maze and on the mean of the closed
corridors (95% Wilson intervals over the pooled episodes), the closure gain over no pruning, and
the closure share (closure success / unchanged-maze success). The gain's and the share's 95%
intervals come from a parametric bootstrap over the episodes: every (layout, task) cell redrawn
binomially at its observed rate (10,000 draws; the rows' episodes are drawn apart, so for the gain
the interval is wider than a paired one would be). Prints Markdown; ``--json`` writes the numbers.

``--pool`` reads one model per seed (each ``Si`` an evaluation's ``results.json``, or its folder; a folder of
several checkpoints gives each) and pools them into one row per ``--rows`` entry: the mean of each layout
over the seeds, the mean of the closed corridors with its 95% Wilson interval over the pooled episodes,
each seed's mean; then the first row minus each other: the mean difference with Student's t interval over
the per-seed differences (paired: the rows ran on the same episodes) and Newcombe's over the pooled
episodes (unpaired). The seeds must share layouts, tasks and episodes and be different checkpoints.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from aqm_mjx.evaluation import stats  # noqa: E402  (run as a script from the repository)

DRAWS = 10_000


def _counts(summary: dict, layouts, tasks, n: int) -> np.ndarray:
    """``[layouts, tasks]`` successes (rate x episodes, rounded) of one row."""
    return np.array([[round(summary[v][f'task_{t}'] * n) for t in tasks] for v in layouts])


def model_rows(res: dict, rows, n: int, rng) -> list[dict]:
    layouts, tasks = res['variants'], res['tasks']
    closed = [i for i, v in enumerate(layouts) if v.startswith('close')]
    base = layouts.index('base')
    counts = {r: _counts(res['summary'][r], layouts, tasks, n) for r in rows}
    draws = {r: rng.binomial(n, c / n, size=(DRAWS,) + c.shape) for r, c in counts.items()}
    out = []
    for r in rows:
        c, d = counts[r], draws[r]
        nb, nc = len(tasks) * n, len(closed) * len(tasks) * n
        b_rate, c_rate = c[base].sum() / nb, c[closed].sum() / nc
        b_draw, c_draw = d[:, base].sum(-1) / nb, d[:, closed].sum((-1, -2)) / nc
        share_draw = c_draw / np.maximum(b_draw, 1e-9)
        row = dict(row=r, base=b_rate, base_ci=list(stats.wilson(c[base].sum(), nb)), closures=c_rate,
                   closures_ci=list(stats.wilson(c[closed].sum(), nc)),
                   per_closure=[c[i].sum() / (len(tasks) * n) for i in closed],
                   share=c_rate / b_rate if b_rate else float('nan'),
                   share_ci=np.percentile(share_draw, [2.5, 97.5]).tolist())
        if r != 'no-pruning' and 'no-pruning' in counts:
            cn, dn = counts['no-pruning'], draws['no-pruning']
            row['gain'] = c_rate - cn[closed].sum() / nc
            row['gain_ci'] = np.percentile(c_draw - dn[:, closed].sum((-1, -2)) / nc, [2.5, 97.5]).tolist()
            row['base_diff'] = b_rate - cn[base].sum() / nb
            row['base_diff_ci'] = np.percentile(b_draw - dn[:, base].sum(-1) / nb, [2.5, 97.5]).tolist()
        out.append(row)
    return out


def _checkpoint_results(folder: str, label: str) -> dict:
    """The ``results.json`` of checkpoint ``label`` in a several-checkpoint evaluation ``folder`` (its
    sub-folder is named ``label``, or with ':' written '_')."""
    sub = next(d for d in (label, label.replace(':', '_')) if os.path.isdir(os.path.join(folder, d)))
    return json.load(open(os.path.join(folder, sub, 'results.json')))


def _read_models(paths) -> list[dict]:
    """One ``results.json`` per model from files or evaluation folders (a folder of several checkpoints
    gives each sub-folder's)."""
    out = []
    for path in paths:
        file = os.path.join(path, 'results.json') if os.path.isdir(path) else path
        if not os.path.isfile(file):
            raise SystemExit(f'closure_table: {path}: no results.json there')
        res = json.load(open(file))
        if 'checkpoints' in res:  # several checkpoints: one sub-folder each
            out += [_checkpoint_results(path, k) for k in res['checkpoints']]
        else:
            out.append(res)
    return out


def pool_seeds(models: list[dict], rows) -> dict:
    """Pool one model per seed into one row per ``rows`` entry, and the first row against each other.

    Args:
        models: ``aqm-mjx evaluate`` results (one checkpoint each) on the same layouts, tasks and episodes.
        rows: summary rows to pool (e.g. ``['aqm', 'no-pruning', 'flat']``); the first is compared
            against the others.
    Returns:
        ``{'layouts', 'closed', 'episodes', 'seeds', 'rows': {row: {...}}, 'differences': {row: {...}}}``:
        per row ``per_layout`` (mean over seeds), ``closures`` with ``closures_ci`` (Wilson over the
        pooled closed-corridor episodes) and ``per_seed``; per other row the first row minus it:
        ``mean``, ``per_seed``, ``paired_ci`` (t over seeds) and ``newcombe_ci`` (pooled episodes).
    """
    if len(models) < 1:
        raise SystemExit('closure_table: --pool needs at least one evaluation')
    first = models[0]
    layouts, tasks = list(first['variants']), list(first['tasks'])
    n = int(first['config']['protocol']['episodes'])
    closed = [v for v in layouts if v.startswith('close')]
    if not closed:
        raise SystemExit(f'closure_table: {first["checkpoint"]}: no closed corridor among its layouts {layouts}')
    for m in models:
        got = (list(m['variants']), list(m['tasks']), int(m['config']['protocol']['episodes']))
        if got != (layouts, tasks, n):
            raise SystemExit(f'closure_table: {m["checkpoint"]} has layouts, tasks and episodes {got}; '
                             f'{first["checkpoint"]} has {(layouts, tasks, n)}: they do not pool')
        missing = [r for r in rows if r not in m['summary']]
        if missing:
            raise SystemExit(f'closure_table: {m["checkpoint"]} has no row {missing} (rows: {sorted(m["summary"])})')
    names = [m['checkpoint'] for m in models]
    if len(set(names)) < len(names):
        raise SystemExit(f'closure_table: a checkpoint appears twice among {names}: pool different seeds')
    cells = len(closed) * len(tasks) * n  # closed-corridor episodes per seed and row
    shut = [layouts.index(v) for v in closed]
    # successes per row: [seeds, layouts, tasks]
    grid = {r: np.stack([_counts(m['summary'][r], layouts, tasks, n) for m in models]) for r in rows}
    counts = {r: g[:, shut].sum((1, 2)) for r, g in grid.items()}  # [seeds] on the closed corridors
    out = dict(layouts=layouts, closed=closed, episodes=n, seeds=names, rows={}, differences={})
    for r in rows:
        k = counts[r]
        per_layout = grid[r].sum((0, 2)) / (len(models) * len(tasks) * n)
        out['rows'][r] = dict(
            per_layout={v: float(x) for v, x in zip(layouts, per_layout)},
            closures=float(k.sum() / (cells * len(models))),
            closures_ci=list(stats.wilson(int(k.sum()), cells * len(models))),
            per_seed=(k / cells).tolist())
    for r in rows[1:]:
        d = (counts[rows[0]] - counts[r]) / cells
        out['differences'][r] = dict(
            mean=float(d.mean()), per_seed=d.tolist(), paired_ci=list(stats.paired_interval(d)),
            newcombe_ci=list(stats.newcombe(int(counts[rows[0]].sum()), cells * len(models),
                                            int(counts[r].sum()), cells * len(models))))
    return out


def pooled_markdown(p: dict) -> str:
    lines = ['| row | ' + ' | '.join(p['layouts']) + ' | closures (mean) [95% Wilson] | per seed |',
             '|' + '---|' * (len(p['layouts']) + 3)]
    for r, v in p['rows'].items():
        lines.append(f'| {r} | ' + ' | '.join(f'{100 * v["per_layout"][x]:.1f}' for x in p['layouts'])
                     + f' | {100 * v["closures"]:.1f} {span(v["closures_ci"])} | '
                     + ', '.join(f'{100 * x:.1f}' for x in v['per_seed']) + ' |')
    first = next(iter(p['rows']))
    for r, d in p['differences'].items():
        lo, hi = d['paired_ci']
        paired = 'no t interval with one seed' if math.isnan(lo) else f'paired t [{100 * lo:+.1f}, {100 * hi:+.1f}]'
        lines.append(f'\n{first} - {r}: {100 * d["mean"]:+.1f} ({paired}; pooled episodes, Newcombe '
                     f'[{100 * d["newcombe_ci"][0]:+.1f}, {100 * d["newcombe_ci"][1]:+.1f}]); per seed '
                     + ', '.join(f'{100 * x:+.1f}' for x in d['per_seed']))
    lines.append(f'\n{len(p["seeds"])} seeds x {p["episodes"]} episodes per task and layout: '
                 f'{len(p["closed"])} closed corridors.')
    return '\n'.join(lines)


def pct(x) -> str:
    return f'{100 * x:.0f}'


def span(ci) -> str:
    return f'[{100 * ci[0]:.0f}, {100 * ci[1]:.0f}]'


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('folder', nargs='?', help='an `aqm-mjx evaluate` output folder with one sub-folder per checkpoint')
    p.add_argument('--pool', nargs='+', default=None, metavar='S',
                   help="one evaluation per seed (results.json or its folder): pool them into one row per --rows")
    p.add_argument('--rows', nargs='+', default=None,
                   help="rows to report (default aqm no-pruning paper=1 paper=cal; with --pool aqm no-pruning flat)")
    p.add_argument('--json', default=None)
    p.add_argument('--label', default=None, help="the model's name when OUT holds one checkpoint's evaluation")
    a = p.parse_args()
    if (a.folder is None) == (a.pool is None):
        p.error('give either an evaluation folder or --pool S1 S2 ...')
    if a.pool:
        pooled = pool_seeds(_read_models(a.pool), a.rows or ['aqm', 'no-pruning', 'flat'])
        print(pooled_markdown(pooled))
        if a.json:
            with open(a.json, 'w') as f:
                json.dump(pooled, f, indent=1)
        return
    a.rows = a.rows or ['aqm', 'no-pruning', 'paper=1', 'paper=cal']
    top = json.load(open(os.path.join(a.folder, 'results.json')))
    single = None if 'checkpoints' in top else top  # one checkpoint: its results.json is the whole folder
    if single:
        label = a.label or os.path.basename(os.path.normpath(top['checkpoint']))
        top = dict(top, checkpoints=[label], episodes=top['config']['protocol']['episodes'],
                   split=top['config']['protocol'].get('split'))
    n = int(top['episodes'])
    rng = np.random.default_rng(0)
    table, lines = {}, []
    closed = [v for v in top['variants'] if v.startswith('close')]
    lines.append('| model | row | calibrated | base | ' + ' | '.join(closed) + ' | closures (mean) | base - no pruning '
                 '| gain over no pruning | share (closures / base) |')
    lines.append('|' + '---|' * (8 + len(closed)))
    for label in sorted(top['checkpoints'], key=lambda k: (not k.endswith(':train'), k)):  # README's model first
        if single:
            res = single  # already read
        else:
            res = _checkpoint_results(a.folder, label)
        cal = res.get('calibration') or {}
        table[label] = dict(calibration=cal, rows=model_rows(res, a.rows, n, rng))
        for r in table[label]['rows']:
            how = ('patience ' + f'{cal.get("patience", float("nan")):g}' if r['row'] == 'aqm'
                   else f'kappa {cal.get("kappa_edges", float("nan")):g}' if r['row'] == 'paper=cal' else '-')
            diff = (f'{100 * r["base_diff"]:+.0f} {span(r["base_diff_ci"])}' if 'base_diff' in r else '-')
            gain = (f'**{100 * r["gain"]:+.1f}** {span(r["gain_ci"])}' if 'gain' in r else '-')
            lines.append(f'| {label} | {r["row"]} | {how} | {pct(r["base"])} {span(r["base_ci"])} | '
                         + ' | '.join(pct(x) for x in r['per_closure'])
                         + f' | {pct(r["closures"])} {span(r["closures_ci"])} | {diff} | {gain} | '
                           f'{pct(r["share"])} {span(r["share_ci"])} |')
    lines.append(f'\n{n} episodes per task and layout ({len(top["tasks"])} tasks): {len(top["tasks"]) * n} per '
                 f'layout and row, {len(closed) * len(top["tasks"]) * n} on the closures; split '
                 f'{top.get("split")}; seed {top.get("seed")}.')
    print('\n'.join(lines))
    if a.json:
        with open(a.json, 'w') as f:
            json.dump(dict(folder=a.folder, episodes=n, models=table), f, indent=1)


if __name__ == '__main__':
    main()
