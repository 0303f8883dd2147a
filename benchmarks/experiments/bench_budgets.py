"""Budgets in the learned controller's own time: calibrate, then compare the rules.

    python benchmarks/experiments/bench_budgets.py --checkpoint RUN/train/aqm/seed_0 --checkpoint RUN/train/aqm/seed_1 \
        --episodes 20 --out benchmarks/results/budgets_cpu

For every checkpoint (a seed), with one map (``stage_keys(PRNGKey(--seed))``, as ``aqm-mjx evaluate``):

1. **Calibration pass**: the agent without pruning (kappa = inf) on the *training* layout,
   ``--calibration-episodes`` episodes between start and goal cells that no evaluation task uses, on
   their own key (:func:`aqm_mjx.evaluation.protocol.calibration_episodes`). Every leg it completes is
   traversable; :func:`aqm_mjx.evaluation.calibration.calibrate` turns their (d, steps, longest
   stall, kind) into the fixed rule's ``kappa``, the paper's rule's ``kappa_edges`` (keypoint edges
   alone) and the stall rule's ``patience`` that would have cut a fraction ``--false-alarm`` of them.
   (The same pass as ``protocol.calibrate`` runs before any evaluation; this script keeps its own
   to put several rates and both rules side by side.)
2. **Evaluation** on the same episodes (``--split``: ``report`` by default) for every row: the
   fixed rule on every leg at the preset's kappa (``aqm``), the paper's rule (keypoint edges alone,
   one cut) at the preset's kappa and at its calibrated kappa, the fixed rule at the calibrated
   kappa, the stall rule at the calibrated patience, no pruning and the flat policy (unless
   ``--no-flat``); layouts: the training layout and the closed-corridor layouts of the shift suite
   (``--shift all`` adds the opened walls).
3. With ``--cut-slack S``: the calibrated rows again with parallel cuts at slack S (an overrun of
   z_i -> z_j also cuts the edges from within S w(i, j) of z_i to within S w(i, j) of z_j,
   ``AgentConfig.cut_slack``).

The rows of steps 1-2 use the paper's single cut (``cut_slack`` 0) whatever the preset says (the
``cpu`` preset's AQM row cuts in parallel at 0.6: ``--cut-slack 0.6`` gives that row).
``--short`` keeps only the paper's rule (at the preset's kappa and calibrated), no pruning (and
flat), and the calibrated stall rule with each ``--cut-slack`` (with the single cut when none is
given): the default's comparison rows.

Prints per row and layout: success pooled over seeds with its 95% Wilson interval, the per-seed
means, the legs cut per episode (overruns) and the keypoint edges removed per episode (more than the
overruns with ``--cut-slack``: an overrun also cuts the edges parallel to it); writes ``rows.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import jax
import numpy as np

from aqm_mjx import files
from aqm_mjx.envs import shifts
from aqm_mjx.evaluation import calibration, evaluate, stats
from aqm_mjx.evaluation import protocol
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import trimmed_map
from aqm_mjx.pipeline import stage_keys
from aqm_mjx.assess import prepare_evaluation, read_data

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def cell(success, pruned, removed) -> dict:
    """One row x layout of one seed: its episodes' outcomes, legs cut (overruns, goal and start legs
    included) and keypoint edges removed (more than the overruns with parallel cuts), kept per
    episode so that seeds pool by concatenation."""
    success, pruned, removed = np.asarray(success, bool), np.asarray(pruned, int), np.asarray(removed, int)
    return dict(success=int(success.sum()), n=int(success.size), pruned=float(pruned.mean()),
                removed=float(removed.mean()), episodes_success=success.tolist(), episodes_pruned=pruned.tolist(),
                episodes_removed=removed.tolist())


def one_seed(ckpt, a, log=print, train_layout: str = 'base', layouts=None) -> dict:
    """Calibrate one checkpoint on its training layout, then evaluate every rule on the same episodes.

    ``a``: this script's options (episodes, calibration episodes, false-alarm rates, shift, seed,
    overrides, flat, progress). ``layouts``: the evaluation layouts by name (default: from
    ``a.shift``); ``train_layout``: the layout the model's data were collected on, where the
    calibration pass runs."""
    env, _, cfg, path = prepare_evaluation(ckpt, None, a.dataset, 'base', a.set)
    trained = fit.load(ckpt, log=log)
    obs = read_data(path, env)['observations']
    _, k_map, k_eval = stage_keys(jax.random.PRNGKey(a.seed))
    graph, m = trimmed_map(trained.agent, obs, cfg.map, k_map)
    if layouts is None:
        suite = shifts.suite(env.maze)
        variants = {k: g for k, g in suite.items()
                    if k == 'base' or (a.shift == 'closed' and k.startswith('close')) or a.shift == 'all'}
    else:
        variants = {k: shifts.variant(env.maze, k) for k in layouts}
    # 1. calibration: no pruning, training layout, cells no task uses, its own key (protocol.calibrate's pass)
    t0 = time.perf_counter()
    base_proto = dataclasses.replace(cfg.protocol, calibration_episodes=a.calibration_episodes)
    cal_proto = protocol.calibration_protocol(base_proto)
    cal_eps = protocol.calibration_episodes(env, base_proto, shifts.variant(env.maze, train_layout))
    cal = evaluate.evaluate(env, trained.agent, graph, dataclasses.replace(cfg.agent, kappa=float('inf'), patience=0.0),
                            cal_proto, key=jax.random.fold_in(k_eval, protocol.CALIBRATION_FOLD), progress=a.progress,
                            episodes=cal_eps)
    legs = calibration.legs_of(cal, 'aqm')
    cals = [{k: np.asarray(v).tolist() for k, v in calibration.calibrate(legs, q).items()} for q in a.false_alarm]
    if not cals[0]['legs']:
        raise SystemExit(f'{ckpt}: the calibration pass completed no leg on {train_layout} ({cal_proto.episodes} '
                         'episodes per task): nothing to calibrate from; give more --calibration-episodes or a '
                         'model that reaches its keypoints')
    settings = [(round(float(c['kappa']), 2), float(round(c['patience']))) for c in cals]
    paper_kappas = [round(float(c['kappa_edges']), 2) for c in cals]
    c = cals[0]
    log(f'{ckpt}: {m["keypoints"]} keypoints; calibration pass {cal_proto.episodes} episodes, {c["legs"]} legs, '
        f'steps/d q50 {c["ratio_q"][0]:.2f} q95 {c["ratio_q"][2]:.2f}, longest stall q95 {c["stall_q"][2]:.0f} -> '
        + ', '.join(f'kappa {k}, patience {p:.0f}, paper kappa {pk} at {q:.1%} false alarms'
                    for q, (k, p), pk in zip(a.false_alarm, settings, paper_kappas))
        + f' ({time.perf_counter() - t0:.0f} s)')
    # 2. evaluation: every rule on the same episodes
    several = len(a.false_alarm) > 1
    ablations, names = [], {'aqm': f'fixed on every leg, preset kappa {cfg.agent.kappa:g}'}
    paper_fixed = f'paper={cfg.agent.kappa:g}'
    ablations.append(paper_fixed)
    names[paper_fixed] = f"paper's rule, preset kappa {cfg.agent.kappa:g}"
    for q, (kappa_c, patience_c), pk in zip(a.false_alarm, settings, paper_kappas):
        # rows are named by rule (and rate), not by the calibrated value, which differs from seed to seed
        at = f' at {q:.1%}' if several else ''
        if f'paper={pk:g}' not in ablations:
            ablations.append(f'paper={pk:g}')
            names[ablations[-1]] = f"paper's rule, calibrated kappa{at}"
        if a.short:  # the stall rule alone, and only when no parallel-cut pass gives it below
            if not a.cut_slack:
                ablations.append(f'stall={patience_c:g}')
                names[ablations[-1]] = f'stall, calibrated patience{at}'
            continue
        ablations += [f'kappa={kappa_c}', f'stall={patience_c:g}']
        names[ablations[-2]], names[ablations[-1]] = f'fixed, calibrated kappa{at}', f'stall, calibrated patience{at}'
    ablations += ['no-pruning'] + (['flat'] if a.flat else [])
    names.update({'no-pruning': 'no pruning', 'flat': 'flat'})
    proto = dataclasses.replace(cfg.protocol, episodes=a.episodes, ablations=tuple(dict.fromkeys(ablations)),
                                split=a.split)
    single = dataclasses.replace(cfg.agent, patience=0.0, cut_slack=0.0)  # the paper's rule: one cut per overrun
    res = evaluate.evaluate(env, trained.agent, graph, single, proto, variants, key=k_eval, progress=a.progress)
    rows = {}

    def collect(res, names):
        for i, ag in enumerate(res.agents):
            for j, v in enumerate(res.variants):
                sel = (res.table.agent == i) & (res.table.variant == j)
                rows[(names[ag], v)] = cell(res.success[sel], res.pruned[sel], res.removed[sel])

    collect(res, names)
    # 3. parallel cuts: the calibrated rules again, on the same episodes, an overrun also cutting the
    # edges parallel to it (AgentConfig.cut_slack); the AQM row of this pass is the calibrated fixed rule
    for slack in a.cut_slack:
        for q, (kappa_c, patience_c) in zip(a.false_alarm, settings):
            at = f' at {q:.1%}' if several else ''
            stall_name = f'stall, calibrated patience{at}, parallel cuts {slack:g}'
            if a.short:  # the stall rule as the AQM row, alone
                agent_cfg = dataclasses.replace(cfg.agent, kappa=kappa_c, patience=patience_c, cut_slack=slack)
                proto_s, names_s = dataclasses.replace(proto, ablations=()), {'aqm': stall_name}
            else:  # the calibrated fixed rule as the AQM row, the stall rule beside it
                agent_cfg = dataclasses.replace(cfg.agent, kappa=kappa_c, patience=0.0, cut_slack=slack)
                proto_s = dataclasses.replace(proto, ablations=(f'stall={patience_c:g}',))
                names_s = {'aqm': f'fixed, calibrated kappa{at}, parallel cuts {slack:g}',
                           f'stall={patience_c:g}': stall_name}
            res_s = evaluate.evaluate(env, trained.agent, graph, agent_cfg, proto_s, variants, key=k_eval,
                                      progress=a.progress)
            collect(res_s, names_s)
    kappa_c, patience_c = settings[0]
    return dict(checkpoint=ckpt, keypoints=m['keypoints'], calibration=c, kappa=kappa_c, patience=patience_c,
                calibrations=[dict(false_alarm=q, kappa=k, patience=p, paper_kappa=pk)
                              for q, (k, p), pk in zip(a.false_alarm, settings, paper_kappas)],
                rows=rows, variants=res.variants, timing=res.timing)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--checkpoint', action='append', required=True, help='a run folder (repeat: one per seed)')
    p.add_argument('--dataset', help="default: the dataset recorded in each run's config.json")
    p.add_argument('--episodes', type=int, default=20, help='evaluation episodes per task, row and layout')
    p.add_argument('--calibration-episodes', type=int, default=100,
                   help='calibration episodes (between cells no evaluation task uses)')
    p.add_argument('--split', default='report', choices=protocol.SPLITS,
                   help="evaluation episodes: 'report' (tables) or 'dev' (choosing settings)")
    p.add_argument('--false-alarm', type=float, nargs='+', default=[0.02],
                   help='fraction of traversable legs cut; several rates add a calibrated pair of rows each')
    p.add_argument('--shift', choices=('base', 'closed', 'all'), default='closed',
                   help="layouts: the training layout alone, with the closed corridors (default), or the whole suite")
    p.add_argument('--seed', type=int, default=0, help='map and episode keys: stage_keys(PRNGKey(seed))')
    p.add_argument('--set', action='append', default=[], help='map/agent/protocol override, e.g. protocol.tasks=1,2')
    p.add_argument('--cut-slack', type=float, nargs='*', default=[],
                   help='add the calibrated rows again with parallel cuts at each slack in (0, 1) '
                        '(AgentConfig.cut_slack: an overrun also cuts the edges parallel to it)')
    p.add_argument('--no-flat', dest='flat', action='store_false',
                   help='leave out the flat row (its episodes mostly run to the step limit: the costliest row)')
    p.add_argument('--short', action='store_true',
                   help="only the acceptance's rows: the paper's fixed rule, no pruning (and flat) and the calibrated "
                        'stall rule with each --cut-slack')
    p.add_argument('--no-progress', dest='progress', action='store_false')
    p.add_argument('--out', help='folder for rows.json')
    a = p.parse_args()
    bad_slack = [x for x in a.cut_slack if not 0 < x < 1]
    if bad_slack:
        p.error(f'--cut-slack values must be in (0, 1); got {bad_slack}')
    bad = [q for q in a.false_alarm if not 0 < q < 1]
    if bad:  # before any map or episode (calibrate() would refuse them only after the calibration pass)
        p.error(f'--false-alarm rates must be in (0, 1); got {bad}')
    if a.out:
        files.check_writable(a.out, what='the benchmark')
    seeds = []
    for c in a.checkpoint:
        seeds.append(one_seed(c, a))
        if a.out:  # each seed is kept as it ends: a late failure loses nothing measured
            os.makedirs(a.out, exist_ok=True)
            s = seeds[-1]
            files.write_json(os.path.join(a.out, f'seed_{len(seeds) - 1}.json'),
                             dict(s, rows=[dict(rule=r, layout=v, **x) for (r, v), x in s['rows'].items()]))
    variants = seeds[0]['variants']
    print(f'\n{len(seeds)} seed(s) x {a.episodes} episodes per task; success pooled over seeds [95% Wilson], '
          'per-seed means, legs cut per episode')
    out_rows = []
    for name in dict.fromkeys(k[0] for k in seeds[0]['rows']):
        for v in variants:
            cells = [s['rows'][(name, v)] for s in seeds]
            k, n = sum(c['success'] for c in cells), sum(c['n'] for c in cells)
            lo, hi = stats.wilson(k, n)
            per = ', '.join(f'{100 * c["success"] / c["n"]:.0f}' for c in cells)
            cut = stats.cuts_by_outcome(sum((c['episodes_success'] for c in cells), []),
                                        sum((c['episodes_pruned'] for c in cells), []))
            removed = float(np.mean(sum((c['episodes_removed'] for c in cells), [])))
            print(f'{name:<50} {v:<10} {100 * k / n:5.1f}% [{100 * lo:4.1f}-{100 * hi:5.1f}]  seeds {per:<10} '
                  f'cut/ep {cut["all"]:5.2f} (succeeded {cut["succeeded"]:5.2f}, failed {cut["failed"]:5.2f}), '
                  f'edges removed/ep {removed:5.2f}')
            out_rows.append(dict(rule=name, layout=v, success=k, n=n, wilson=[lo, hi], per_seed=per,
                                 cut_per_episode=cut['all'], cut_per_succeeded=cut['succeeded'],
                                 cut_per_failed=cut['failed'], removed_per_episode=removed))
    for s in seeds:
        print(f"{s['checkpoint']}: calibrated " + ', '.join(f"kappa {c['kappa']}, patience {c['patience']:g} at "
                                                             f"{c['false_alarm']:.1%}" for c in s['calibrations']) + " "
              f"({s['calibration']['legs']} legs); evaluation {s['timing']['total_s']:.0f} s")
    if a.out:
        os.makedirs(a.out, exist_ok=True)
        meta = [dict(checkpoint=s['checkpoint'], kappa=s['kappa'], patience=s['patience'], calibrations=s['calibrations'],
                     calibration=s['calibration'], keypoints=s['keypoints']) for s in seeds]
        finish([dict(seeds=meta, rows=out_rows, episodes=a.episodes, false_alarm=a.false_alarm, split=a.split,
                     command=' '.join(sys.argv))],
               os.path.join(a.out, 'rows.json'))
    else:
        finish([], None)


if __name__ == '__main__':
    main()
