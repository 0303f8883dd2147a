"""``aqm-mjx compare``: several methods on the same data and the same episodes, with seeds.

    aqm-mjx compare --env antmaze-medium --methods aqm gcbc gcivl gciql qrl crl hiql saw --seeds 2

One folder holds the whole comparison::

    OUT/compare.json                    what was asked and the data's SHA-256 (both checked on every re-run)
    OUT/data/ENV-STYLE.npz              collected once (or --dataset)
    OUT/train/METHOD/seed_S/            an ordinary run folder per method and seed
    OUT/eval/METHOD/                    `aqm-mjx evaluate` of that method's seeds
    OUT/results.json, table.md, success.png   the comparison

:func:`merge` (``aqm-mjx merge A B --out C``) puts finished comparisons on the same data
(by SHA-256) and episodes into one table.

Each method's seeds train as one vmapped program (:func:`aqm_mjx.learn.fit.train_seeds`); a seed's
run key is ``PRNGKey(seed)`` split by :func:`~aqm_mjx.pipeline.stage_keys`, as in ``aqm-mjx run
--seed S``. Every checkpoint is evaluated with the episode keys of ``PRNGKey(eval_seed)``, so all
methods meet the same tasks, layouts and initial noise. A re-run after an interrupt skips methods
that are trained and evaluated, resumes one that was training, and redoes only the tables.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
from typing import Optional, Sequence

import jax
import jax.numpy as jnp

from aqm_mjx import envs, files, memory, presets, processes
from aqm_mjx.agent import planners
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.evaluation import plots, report, stats
from aqm_mjx.evaluation.protocol import plan_episodes
from aqm_mjx.learn import fit, methods
from aqm_mjx.pipeline import RunConfig, stage_keys
from aqm_mjx import assess, run

DEFAULT_METHODS = ('aqm', 'gcbc', 'gcivl', 'gciql', 'qrl', 'crl', 'hiql', 'saw')


def _scope(pair: str) -> Optional[str]:
    """The method an override is for (``'gciql:alpha=0.1'`` -> ``'gciql'``), None for a shared one."""
    head = pair.split('=', 1)[0]
    return head.split(':', 1)[0] if ':' in head else None


def method_configs(env_name: str, names: Sequence[str], preset: str, overrides: Sequence[str] = (),
                   style: Optional[str] = None) -> dict[str, RunConfig]:
    """``{method: RunConfig}`` for a comparison, every override checked before any work.

    ``overrides`` are ``section.field=value`` pairs (``field=value`` where the field is unique), given
    to every method; ``METHOD:section.field=value`` goes to that method alone (a setting of
    one method, for instance: ``gciql:alpha=0.1``). A shared override that a method's
    config lacks is an error naming the method; scope it instead.
    """
    names = list(names)
    if not names:
        raise ValueError('give at least one method')
    for n in names:
        methods.get(n)
    if len(set(names)) != len(names):
        raise ValueError(f'methods repeat: {names}')
    shared, scoped = [], {n: [] for n in names}
    for pair in overrides:
        m = _scope(pair)
        if m is not None:
            rest = pair.split(':', 1)[1]
            if m not in scoped:
                raise ValueError(f'override {pair!r} is for method {m!r}, which is not compared '
                                 f'(methods: {", ".join(names)})')
            scoped[m].append(rest)
        else:
            shared.append(pair)
    out = {}
    for n in names:
        # the methods alone by default (AQM's ablations triple its evaluation): protocol.ablations=... adds them
        cfg = RunConfig.preset(preset, method=n, env=env_name, style=style).with_overrides(['protocol.ablations='])
        try:
            cfg = cfg.with_overrides(shared)
        except ValueError as e:
            # a field this method lacks: scope it; a bad value: the message says what is wrong with it
            lacks = 'no section has a field' in str(e) or ' field ' in str(e) and str(e).startswith('unknown')
            raise ValueError(f'{n}: {e}' + (f'; give an override one method has as {n}:FIELD=VALUE' if lacks
                                             else '')) from None
        try:
            out[n] = cfg.with_overrides(scoped[n])
        except ValueError as e:
            raise ValueError(f'{n}: {e} (in {", ".join(f"{n}:{o}" for o in scoped[n])})') from None
    return out


def _spec(env_name, style, preset, seeds, first_seed, eval_seed, shift, overrides, dataset) -> dict:
    return dict(env=env_name, style=style, preset=preset, seeds=[first_seed + i for i in range(seeds)],
                eval_seed=eval_seed, shift=shift, overrides=list(overrides),
                dataset=os.path.abspath(dataset) if dataset else None)


PLANNERS = tuple(p for p in planners.CHOICES if p != 'own')  # what --planners may name


def planner_rows(name: str, cfg, planners: Sequence[str], obs_size: int, action_size: int, log=print) -> dict:
    """``{'METHOD+PLANNER': RunConfig}``: the rows ``compare --planners`` adds for method ``name`` (its
    checkpoints evaluated again with ``agent.planner`` set), leaving out what would repeat its own row
    (``flat`` for a method that runs flat, ``aqm`` for one that plans on AQM's map already) and what it
    cannot run (``aqm``, ``ttgs`` without a value, said in one line)."""
    learner = methods.get(name).make(cfg.train, obs_size, action_size)
    own = learner.agent()
    out = {}
    for p in planners:
        if p not in PLANNERS:
            raise ValueError(f'--planners: unknown planner {p!r}; choose from {", ".join(PLANNERS)}')
        if (p == 'flat' and not own.plans) or (p == 'aqm' and own.prunes):
            continue  # its own row already
        if p != 'flat' and learner.distance is None:
            log(f'{name}: no value to plan with, so no {name}+{p} row')
            continue
        out[f'{name}+{p}'] = dataclasses.replace(cfg, agent=dataclasses.replace(cfg.agent, planner=p))
    return out


def _check_spec(out: str, spec: dict, names: list[str]) -> tuple[list[str], Optional[str]]:
    """The methods of ``OUT/compare.json`` and these, and the data's SHA-256 recorded there (None
    before the first data stage), after checking that the rest of the request is the same (a folder
    holds one comparison)."""
    path = os.path.join(out, 'compare.json')
    if not os.path.exists(path):
        return names, None
    saved = files.read_json(path, 'a comparison folder written by aqm-mjx compare')
    diff = [k for k in spec if saved.get(k) != spec[k]]
    if diff:
        raise ValueError(f'{out} holds a comparison with other settings ('
                         + '; '.join(f'{k}: {saved.get(k)!r} there, {spec[k]!r} now' for k in diff)
                         + '); choose another --out')
    return list(dict.fromkeys(saved.get('methods', []) + names)), saved.get('data_sha256')


def seed_folders(out: str, method: str, seeds: Sequence[int]) -> list[str]:
    return [os.path.join(out, 'train', method, f'seed_{s}') for s in seeds]


def _evaluation(ev: str, folders: list[str], steps: int) -> Optional[dict]:
    """``ev/results.json`` if it covers these run folders at ``steps``, else None."""
    path = os.path.join(ev, 'results.json')
    if not os.path.exists(path):
        return None
    res = files.read_json(path, 'an evaluation written by aqm-mjx evaluate')
    have = {os.path.normpath(c['checkpoint']): c['step'] for c in res.get('checkpoints', {}).values()}
    return res if all(have.get(os.path.normpath(os.path.abspath(f))) == steps for f in folders) else None


def aggregate(per_method: dict[str, dict], seeds: Sequence[int]) -> dict:
    """The comparison's rows from each method's ``evaluate_checkpoints`` table.

    ``per_method[m]`` is that table (``summary: {LABEL/agent: {layout: {task_T, mean}}}``, labels
    ``m:seed_S``). A row is a method (its own agent: AQM's planner or a flat controller), or
    ``method/agent`` for an ablation; ``m`` may be ``method+planner`` (its checkpoints evaluated under
    another planner, ``compare --planners``). Per layout it holds the per-task means over seeds, the
    per-seed means, their mean, the 95% t interval over seeds and the Wilson interval of the pooled
    episodes (seeds x tasks x episodes)."""
    rows = {}
    for m, res in per_method.items():
        episodes, tasks = int(res['episodes']), list(res['tasks'])
        method = m.split('+', 1)[0]  # 'gcivl+aqm': GCIVL's checkpoints under a planner (compare --planners)
        labels = assess.checkpoint_labels([f'seed_{s}' for s in seeds], [method] * len(seeds))  # as evaluate names them
        agents = []
        for key in res['summary']:
            label, agent = key.split('/', 1)
            if label == labels[0]:
                agents.append(agent)
        for k, agent in enumerate(agents):
            name = m if k == 0 else f'{m}/{agent}'
            row = {}
            for v in res['variants']:
                cells = [res['summary'][f'{lab}/{agent}'][v] for lab in labels]
                row[v] = _cell([c['mean'] for c in cells],
                               {t: sum(c[f'task_{t}'] for c in cells) / len(cells) for t in tasks}, episodes)
            rows[name] = row
    return rows


def _cell(seed_means: Sequence[float], task_means: dict, episodes: int) -> dict:
    """One row's numbers on one layout: ``seed_means`` (one success rate a seed, each over ``len(task_means)``
    tasks x ``episodes``), ``task_means`` ({task: mean over those seeds}); the mean, the 95% t interval
    over seeds and the Wilson interval of the pooled episodes."""
    seed_means = [float(x) for x in seed_means]
    n = len(seed_means) * len(task_means) * episodes
    wins = round(sum(seed_means) * len(task_means) * episodes)
    lo, hi = stats.seed_interval(seed_means)
    return dict(mean=sum(seed_means) / len(seed_means), seed_means=seed_means,
                seed_ci95=None if math.isnan(lo) else [lo, hi], episodes_ci95=list(stats.wilson(wins, n)),
                episodes=n, **{f'task_{t}': m for t, m in task_means.items()})


def _write_tables(out, spec, per_method, seed_ids, cfgs, log, write: bool = True) -> dict:
    """``OUT/results.json``, ``table.md`` and ``success.png`` of the methods evaluated so far (with
    ``write`` False, the comparison alone: another process writes it)."""
    names = list(per_method)
    first = per_method[names[0]]
    rows = aggregate(per_method, seed_ids)
    tasks, episodes = first['tasks'], int(first['episodes'])
    # each row's own config: the one its evaluation recorded (a method evaluated by an earlier run of this
    # folder keeps what it ran with), the current one for evaluations that predate the record
    configs = {n: per_method[n].get('config') or cfgs[n].to_dict() for n in names}
    result = dict(spec, methods=names, tasks=tasks, episodes=episodes, variants=first['variants'], rows=rows,
                  configs=configs, split=first.get('split'))
    if write:
        _write(out, result, log)
    return result


def _write(out: str, result: dict, log) -> None:
    """``result`` (a comparison as ``results.json`` holds it) to ``OUT/results.json``, ``table.md`` and
    ``success.png``."""
    rows, variant, seed_ids = result['rows'], result['variants'][0], result['seeds']
    result['provenance'] = files.provenance()  # what wrote this table (version, commit, command)
    files.write_json(os.path.join(out, 'results.json'), result, makedirs=True)
    table = report.comparison_markdown(rows, variant, result['tasks'], seed_ids, int(result['episodes']))
    files.write_text(os.path.join(out, 'table.md'), table)
    plots.method_bars(rows, variant, os.path.join(out, 'success.png'),
                      title=f'{result["env"]} {result["style"]} ({variant}), {result["preset"]} preset: mean of '
                            f'{len(seed_ids)} seed(s), 95% interval')
    log(table)
    log(f'wrote {out}/results.json, {out}/table.md and {out}/success.png')


# what two comparison folders must share for their rows to sit in one table: the data (by SHA-256),
# the request, and the episodes (the seeds are checked per method: every row of a table over the same seeds)
_SHARED = ('data_sha256', 'env', 'style', 'preset', 'eval_seed', 'split', 'shift', 'tasks', 'episodes',
           'variants')


# shared overrides that choose how a comparison runs, not what it computes: the OGBench backend's worker
# processes step the same seeded environments whatever their number (the policy sees the whole batch)
_EXECUTION = ('protocol.workers',)


def _settings(overrides: Sequence[str]) -> list[str]:
    """The shared overrides (no ``METHOD:``) that change results: all but :data:`_EXECUTION`'s, sorted."""
    return sorted(o for o in overrides if _scope(o) is None and o.split('=', 1)[0] not in _EXECUTION)


def _draw_curves(out: str, folders: dict, env_name: str, preset: str) -> None:
    """``out/curves.png``: success against updates of every method so far, a line per seed (the
    learning-curve points in each seed folder's ``metrics.jsonl``); nothing without them."""
    paths = {m: [os.path.join(f, 'metrics.jsonl') for f in fs] for m, fs in folders.items()}
    if any('eval/success' in ln for ps in paths.values() for p in ps for ln in plots.read_metrics(p)):
        plots.curves(paths, [], os.path.join(out, 'curves.png'), title=f'{env_name}, {preset} preset')


def _row_faults(r: dict) -> list[str]:
    """What in ``r['rows']`` the table could not print: per row and layout, a mean, task rates and
    seed means that are success rates (numbers in [0, 1]), and intervals that are ordered pairs of
    rates (or none)."""
    num = lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and 0.0 <= x <= 1.0  # noqa: E731
    pair = lambda x: x is None or (isinstance(x, list) and len(x) == 2 and all(map(num, x))  # noqa: E731
                                   and x[0] <= x[1])
    faults = []
    for name, row in r['rows'].items():
        for v in r.get('variants') or []:
            cell = row.get(v) if isinstance(row, dict) else None
            if not isinstance(cell, dict):
                faults.append(f'row {name!r} has no layout {v!r}')
                continue
            bad = [k for k in ['mean'] + [f'task_{t}' for t in r.get('tasks') or []] if not num(cell.get(k))]
            if not (isinstance(cell.get('seed_means'), list) and all(map(num, cell['seed_means']))):
                bad.append('seed_means')
            bad += [k for k in ('seed_ci95', 'episodes_ci95') if not pair(cell.get(k))]
            if bad:
                faults.append(f'row {name!r}, layout {v!r}: {", ".join(bad)} not success rates in [0, 1] '
                              '(intervals: ordered pairs of them)')
    return faults


def _read_comparison(folder: str) -> dict:
    """``FOLDER/results.json`` of a finished comparison, its parts that :func:`merge` reads checked
    (types and the rows and configs of every method), the file named on any fault."""
    path = os.path.join(folder, 'results.json')
    r = files.read_json(path, 'a folder written by aqm-mjx compare')
    faults = []
    methods_ = r.get('methods')
    if not (isinstance(methods_, list) and methods_ and all(isinstance(m, str) for m in methods_)):
        faults.append(f"'methods' is {methods_!r}, not a list of method names")
        methods_ = []
    for key in ('rows', 'configs'):
        if not isinstance(r.get(key), dict):
            faults.append(f"{key!r} is {'missing' if key not in r else type(r[key]).__name__}, not an object")
        else:
            lost = [m for m in methods_ if m not in r[key]]
            if lost:
                faults.append(f"{key!r} lacks method(s) {lost}")
    if not isinstance(r.get('overrides', []), list):
        faults.append(f"'overrides' is {type(r['overrides']).__name__}, not a list")
    paths = lambda v: isinstance(v, str) or (isinstance(v, list) and all(isinstance(x, str) for x in v))  # noqa: E731
    origin = r.get('merged_from', {})  # a table merge wrote: each method's folder(s)
    if not (isinstance(origin, dict) and all(map(paths, origin.values()))):
        faults.append("'merged_from' is not an object of folders (a path or a list of paths per method)")
    if not faults:  # every number the table prints is a number
        faults += _row_faults(r)
    if faults:
        raise files.BadFileError(f'{path} is not a finished comparison: ' + '; '.join(faults))
    return r


def merge(folders: Sequence[str], out: str, log=print) -> dict:
    """One table from several finished ``aqm-mjx compare`` folders: their methods' rows side by side.

    For rows that several sessions (or machines) computed on the same data and episodes. Every folder's
    ``results.json`` must agree on the data's SHA-256, the environment, style, preset, episode key
    (``eval_seed``), layout, tasks and episodes, and on the overrides given to every method (a
    ``METHOD:`` override travels with its method; ``protocol.workers``, how many processes stepped
    OGBench's environments, may differ). A method may appear in several folders when each holds other
    seeds of it, trained and evaluated alike (the same config but its first seed, the same ``METHOD:``
    overrides and rows): its rows are pooled over their seeds (:func:`_pooled`). Every method must end
    with the same seeds. Writes ``OUT/results.json`` (with ``merged_from``: a method's folder, or the
    list of its folders where its seeds were pooled; an input that ``merge`` wrote passes on the folders
    its own ``merged_from`` names), ``OUT/table.md`` and ``OUT/success.png`` holding
    ``OUT``'s lock (:func:`aqm_mjx.files.run_lock`); the inputs are only read: an ``OUT`` that is,
    lies inside or links into an input (or holds one) is refused before anything is written. Returns
    the merged comparison.
    """
    folders = [os.path.normpath(f) for f in folders]
    if len(folders) < 2:
        raise ValueError(f'give at least two comparison folders to merge; got {len(folders)}')
    real = [os.path.realpath(f) for f in folders]  # one folder however it is spelled
    if len(set(real)) != len(real):
        raise ValueError(f'folders repeat: {folders}')
    for f in folders:  # the inputs are only read: no output in, at or linked into one, and no input in the output
        into = files.inside(out, f)
        if into or files.inside(f, out):
            raise ValueError(f'--out {out} ' + ('is or lies inside' if into else 'holds')
                             + f' the input {f} (resolved: {os.path.realpath(out)} and {os.path.realpath(f)}); '
                             'merge only reads its inputs: write the merged table to a folder outside every input')
    if os.path.exists(os.path.join(out, 'compare.json')):
        raise ValueError(f'{out} is a comparison folder; write the merged table to another --out (its own '
                         'files would be replaced)')
    parts = [_read_comparison(f) for f in folders]
    first = parts[0]
    shared = [o for o in first.get('overrides', []) if _scope(o) is None]  # the first folder's, workers too
    settings = _settings(shared)
    for f, r in zip(folders, parts):
        if not r.get('data_sha256'):
            raise ValueError(f'{f}/results.json records no data SHA-256 (written before aqm-mjx recorded it): '
                             'its data cannot be shown to be the others\'')
        diff = [k for k in _SHARED if r.get(k) != first.get(k)]
        if _settings(r.get('overrides', [])) != settings:
            diff.append('overrides')
        if diff:
            raise ValueError(f'{f} and {folders[0]} differ in ' + '; '.join(
                f'{k} ({r.get(k)!r} against {first.get(k)!r})' for k in diff) + ': their rows would not share data '
                'and episodes')
    held = {}  # method -> [(folder, its results)]: one folder, or several holding other seeds of it
    for f, r in zip(folders, parts):
        for m in r['methods']:
            held.setdefault(m, []).append((f, r))
    for m, hs in held.items():
        _check_seeds_of_one_method(m, hs)
    names = list(held)
    union = {m: sorted(s for _, r in hs for s in r['seeds']) for m, hs in held.items()}
    seeds = union[names[0]]
    if any(union[m] != seeds for m in names):
        raise ValueError('the methods cover different seeds (' + '; '.join(f'{m}: {union[m]}' for m in names)
                         + '): a table holds one set of seeds; train the missing ones into another folder with '
                         'the same command and --seeds N --seed FIRST, then merge that folder too')
    rows, configs, scoped = {}, {}, []
    for m, hs in held.items():
        r0 = hs[0][1]
        configs[m] = r0['configs'][m]
        scoped += [o for o in r0.get('overrides', []) if _scope(o) == m]
        for k in _rows_of(r0, m):
            rows[k] = r0['rows'][k] if len(hs) == 1 else {
                v: _pooled([(r['seeds'], r['rows'][k][v]) for _, r in hs], r0['tasks'], int(r0['episodes']))
                for v in r0['variants']}
    origin = {m: _origin(m, hs) for m, hs in held.items()}
    result = dict(first, methods=names, rows=rows, configs=configs, seeds=seeds, overrides=shared + scoped,
                  merged_from=origin)
    with files.run_lock(out):  # one writer per folder, as compare
        _write(out, result, log)
    return result


def _origin(m: str, hs: list) -> str | list[str]:
    """The folder(s) where method ``m``'s rows were computed, from ``hs`` ([(folder, results)]): each
    folder, or, for a table ``merge`` wrote, the folder(s) its ``merged_from`` names for ``m``; one path,
    or the list where its seeds come from several."""
    got = []
    for f, r in hs:
        o = r.get('merged_from', {}).get(m, os.path.abspath(f))
        got += [o] if isinstance(o, str) else list(o)
    return got[0] if len(got) == 1 else got


def _rows_of(r: dict, m: str) -> list[str]:
    """The names of method ``m``'s rows in comparison ``r``: its own, then its ablations' (``m/AGENT``;
    results.json may hold the rows in another order)."""
    return [k for k in sorted(r['rows'], key=lambda k: k != m) if k.split('/', 1)[0] == m]


# what may differ between two folders' configs of one method whose seeds merge joins: the first seed, and
# how many processes stepped OGBench's environments
_PER_FOLDER = ('train.seed', 'protocol.workers')


def _flat(d: dict, prefix: str = '') -> dict:
    """``{'a': {'b': 1}}`` as ``{'a.b': 1}``."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f'{prefix}{k}.'))
        else:
            out[f'{prefix}{k}'] = v
    return out


def _check_seeds_of_one_method(m: str, hs: list) -> None:
    """A method in several folders ``hs`` ([(folder, results)]) must hold other seeds in each, with the
    same config (but :data:`_PER_FOLDER`), ``METHOD:`` overrides and rows; the fault named otherwise."""
    if len(hs) == 1:
        return
    seen = {}
    for f, r in hs:
        bad = [k for k in _rows_of(r, m) for v in r['variants']
               if len(r['rows'][k][v]['seed_means']) != len(r['seeds'])]
        if bad:
            raise ValueError(f'{f}/results.json: rows {bad} hold another number of seed means than its '
                             f'{len(r["seeds"])} seeds')
        for s in r['seeds']:
            if s in seen:
                raise ValueError(f'method {m!r} has seed {s} in both {seen[s]} and {f}: keep one (merge takes each '
                                 'seed of a method from one folder)')
            seen[s] = f
    f0, r0 = hs[0]
    c0 = {k: v for k, v in _flat(r0['configs'][m]).items() if k not in _PER_FOLDER}
    o0 = sorted(o for o in r0.get('overrides', []) if _scope(o) == m)
    k0 = sorted(_rows_of(r0, m))
    for f, r in hs[1:]:
        c = {k: v for k, v in _flat(r['configs'][m]).items() if k not in _PER_FOLDER}
        diff = sorted(k for k in set(c0) | set(c) if c0.get(k, '(absent)') != c.get(k, '(absent)'))
        o = sorted(o for o in r.get('overrides', []) if _scope(o) == m)
        if o != o0:
            diff.append(f'its overrides ({o} against {o0})')
        k = sorted(_rows_of(r, m))
        if k != k0:
            diff.append(f'its rows ({k} against {k0})')
        if diff:
            raise ValueError(f'method {m!r} in {f} and {f0} differs in ' + ', '.join(diff[:8])
                             + (f' and {len(diff) - 8} more' if len(diff) > 8 else '')
                             + ': seeds of one method merge only when trained and evaluated alike')


def _pooled(cells: list, tasks: Sequence[int], episodes: int) -> dict:
    """One cell from one method's cells in several folders, ``[(seeds, cell)]``: seed means in seed order,
    task means weighted by each folder's seeds, the intervals of all of them (:func:`_cell`)."""
    by_seed = sorted((s, x) for seeds, c in cells for s, x in zip(seeds, c['seed_means']))
    count = sum(len(seeds) for seeds, _ in cells)
    return _cell([x for _, x in by_seed],
                 {t: sum(len(seeds) * c[f'task_{t}'] for seeds, c in cells) / count for t in tasks}, episodes)


def compare(env_name: str, method_names: Sequence[str], seeds: int, out: str, preset: str = presets.DEFAULT,
            dataset: Optional[str] = None, style: str = 'navigate', collect_episodes: int = 100,
            collect_batch: int = 55, overrides: Sequence[str] = (), shift: str = 'base', first_seed: int = 0,
            eval_seed: int = 0, log=print, collect_physics: str = 'mjx', collect_preset: str = 'ogbench',
            planners: Sequence[str] = ()) -> dict:
    """``aqm-mjx compare``: data, then for each method in turn its seeds trained (vmapped) and evaluated
    on the shared episodes; ``OUT/results.json``, ``OUT/table.md`` and ``OUT/success.png`` are
    rewritten after each method, so an interrupted comparison leaves the table of those done.
    ``planners`` (``flat``, ``aqm``, ``ttgs``): each method's checkpoints evaluated again under each
    planner on the same episodes, as rows ``METHOD+PLANNER`` (:func:`planner_rows`).

    Everything (methods, overrides, layouts, tasks, the folder's earlier request) is checked before
    data are collected. Returns the comparison written to ``results.json``.
    """
    envs.parse_name(env_name)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f'--seeds must be an integer >= 1; got {seeds!r}')
    if dataset is not None:
        if not os.path.exists(dataset):
            raise FileNotFoundError(f'dataset {dataset!r} not found')
        ds_io.check_env_name(dataset, env_name)
        try:
            style = ds_io.infer_env(dataset)[1] or style
        except ValueError:
            pass  # not an OGBench name: --style stands
    names = list(method_names)
    cfgs = method_configs(env_name, names, preset, overrides, style=style)
    env = envs.make(env_name)
    variants = assess.variants_for(env.maze, shift)
    for c in cfgs.values():
        plan_episodes(env, c.protocol, c.agent.kappa, variants)  # bad task ids fail before any work
        memory.check_training(methods.get(c.method), c.train, env.obs_size, env.action_size, seeds)
    several, writer = jax.process_count() > 1, processes.writer()
    if seeds < jax.process_count():
        raise ValueError(f'--seeds {seeds} over {jax.process_count()} processes: every process trains at least one '
                         'seed; give more seeds or fewer processes')
    for c in cfgs.values():
        processes.check_backend(c.protocol.backend)
    seed_ids = [first_seed + i for i in range(seeds)]
    spec = _spec(env_name, style, preset, seeds, first_seed, eval_seed, shift, overrides, dataset)
    extra = {n: planner_rows(n, c, planners, env.obs_size, env.action_size, log) for n, c in cfgs.items()}
    given = assess.read_data(dataset, env) if dataset else None  # a damaged file is named before anything is written
    # several processes (aqm_mjx.processes): process 0 holds the folder's lock and writes the comparison's files,
    # process p trains seeds p, p + N, ... into their own folders; all of them evaluate every checkpoint together
    with files.run_lock(out) if writer else contextlib.nullcontext():
        all_names, recorded = _check_spec(out, spec, names)
        processes.barrier('compare: request checked')  # every process read compare.json before it changes
        cpath = os.path.join(out, 'compare.json')
        kept = {} if recorded is None else dict(data_sha256=recorded)
        if writer:
            files.write_json(cpath, dict(spec, methods=all_names, **kept), makedirs=True)
        path = run.data_stage(env_name, out, dataset, collect_episodes, collect_batch, log, style=style,
                              physics=collect_physics, physics_preset=collect_preset)
        data = given if given is not None else assess.read_data(path, env)
        digest = ds_io.fingerprint(data)
        if recorded is not None and recorded != digest:
            raise ValueError(f'{path}: the data changed since this comparison began (sha256 {digest[:16]}... now, '
                             f'{recorded[:16]}... in {cpath}): its methods would not share their data; restore '
                             'the file or choose another --out')
        if recorded is None and writer:  # the first data stage of this folder: record what its methods share
            files.write_json(cpath, dict(spec, methods=all_names, data_sha256=digest))
        spec = dict(spec, data_sha256=digest)  # into results.json beside the request
        log(f'data: {path} ({len(data["observations"])} states, sha256 {digest[:16]}...)')
        log(f'{len(names)} method(s) x {seeds} seed(s) ({preset} preset), one method at a time: its seeds trained '
            f'as one vmapped program, then evaluated on the episodes of PRNGKey({eval_seed}); the table grows as each '
            'ends')
        if several:  # (fit.train_seeds splits them: seed i on process i mod N)
            log(f'process {jax.process_index()} of {jax.process_count()} trains seed(s) '
                f'{[seed_ids[i] for i in processes.share(seeds)]}; the '
                'learning curve is not drawn across processes')
        per_method, result = {}, None
        for i, (n, c) in enumerate(cfgs.items()):
            folders, ev = seed_folders(out, n, seed_ids), os.path.join(out, 'eval', n)
            log(f'[{i + 1}/{len(cfgs)} {n}] train and evaluate')
            keys = jnp.stack([stage_keys(jax.random.PRNGKey(s))[0] for s in seed_ids])
            fit.train_seeds(n, [dataclasses.replace(c.train, seed=s) for s in seed_ids], data, folders, keys,
                            dataset_path=os.path.abspath(path), log=log,
                            curve=None if several else assess.learning_curve(
                                env, data, c, stage_keys(jax.random.PRNGKey(eval_seed))[2], n))
            processes.barrier(f'compare: {n} trained')  # every seed's checkpoint is on disk
            res = _evaluation(ev, folders, c.train.steps)
            if res is not None:
                log(f'{n}: evaluated already ({ev}/results.json)')
            else:
                assess.evaluate_checkpoints(folders, ev, cfg=c, dataset=path, shift=shift, seed=eval_seed, log=log)
                processes.barrier(f'compare: {n} evaluated')  # process 0 wrote its results.json
                res = files.read_json(os.path.join(ev, 'results.json'))  # as a re-run reads it (JSON types)
            per_method[n] = res
            for row, rc in extra[n].items():  # the same checkpoints under another planner (--planners)
                ev_p = os.path.join(out, 'eval', row)
                res_p = _evaluation(ev_p, folders, c.train.steps)
                if res_p is None:
                    log(f'[{i + 1}/{len(cfgs)} {n}] evaluate under planner {rc.agent.planner} ({row})')
                    assess.evaluate_checkpoints(folders, ev_p, cfg=rc, dataset=path, shift=shift, seed=eval_seed,
                                                log=log)
                    processes.barrier(f'compare: {row} evaluated')
                    res_p = files.read_json(os.path.join(ev_p, 'results.json'))
                per_method[row] = res_p
            if writer:
                _draw_curves(out, {m: seed_folders(out, m, seed_ids) for m in per_method}, env_name, preset)
            result = _write_tables(out, spec, per_method, seed_ids, {m: cfgs.get(m) or extra[n][m] for m in per_method},
                                   log if i + 1 == len(cfgs) else (lambda *_: None), write=writer)
            if i + 1 < len(cfgs):
                log(f'{n}: done; {out}/table.md now holds {", ".join(per_method)}')
        return result
