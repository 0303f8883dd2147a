"""How stable the calibrated budgets are: the calibration pass of one checkpoint on several keys.

    python benchmarks/experiments/bench_calibration.py --checkpoint runs/antmaze-medium/train --keys 5 \
        --episodes 20 100 200 --false-alarm 0.005 0.01 0.02 --set protocol.backend=ogbench

For each number of calibration episodes and each of ``--keys`` keys (the calibration key of
``stage_keys(PRNGKey(k))``, k = 0..keys-1; the map is seed 0's, as ``aqm-mjx evaluate`` builds it),
the pass that ``protocol.calibrate`` runs before an evaluation: the agent without pruning on the
training layout, between start and goal cells that no evaluation task uses. From its legs, at each
``--false-alarm`` rate: the stall rule's patience, the fixed rule's kappa and the paper's rule's
kappa (keypoint edges alone); at each ``--stall-scale`` C, the stall rule's patience as
``protocol.stall_scale`` sets it (C x the 90th percentile of the longest stall, rounded to a step).
Prints min / median / max over the keys and the spread (max / min - 1; a stable rule moves by at
most 20%); ``--out`` writes the rows as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import jax
import numpy as np

from aqm_mjx.evaluation import calibration, evaluate, protocol
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import trimmed_map
from aqm_mjx.pipeline import stage_keys
from aqm_mjx.assess import prepare_evaluation, read_data

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--checkpoint', required=True)
    p.add_argument('--dataset', default=None)
    p.add_argument('--keys', type=int, default=5, help='calibration keys (those of seeds 0 .. keys - 1)')
    p.add_argument('--episodes', type=int, nargs='+', default=[100], help='calibration episodes per pass')
    p.add_argument('--false-alarm', type=float, nargs='+', default=[0.005, 0.01, 0.02])
    p.add_argument('--stall-scale', type=float, nargs='*', default=[6.0],
                   help='patience = C x the 90th percentile of the longest stall (protocol.stall_scale), per C')
    p.add_argument('--set', action='append', default=[], help='map/agent/protocol override (section.field=value)')
    p.add_argument('--out', default=None)
    a = p.parse_args()
    if a.keys < 2:
        p.error('--keys must be >= 2: a spread needs two calibrations')
    env, _, cfg, path = prepare_evaluation(a.checkpoint, None, a.dataset, 'base', a.set)
    trained = fit.load(a.checkpoint, log=lambda *_: None)
    _, k_map, _ = stage_keys(jax.random.PRNGKey(0))
    graph, m = trimmed_map(trained.agent, read_data(path, env)['observations'], cfg.map, k_map)
    print(f'{a.checkpoint}: {m["keypoints"]} keypoints; backend {cfg.protocol.backend}')
    rows = []
    for n in a.episodes:
        proto = dataclasses.replace(cfg.protocol, calibration_episodes=n)
        eps = protocol.calibration_episodes(env, proto)
        per_key = []
        t0 = time.perf_counter()
        for k in range(a.keys):
            k_eval = stage_keys(jax.random.PRNGKey(k))[2]
            res = evaluate.evaluate(env, trained.agent, graph, dataclasses.replace(cfg.agent, kappa=float('inf'),
                                                                                 patience=0.0),
                                    protocol.calibration_protocol(proto), progress=False, episodes=eps,
                                    key=jax.random.fold_in(k_eval, protocol.CALIBRATION_FOLD))
            per_key.append([{x: float(v) for x, v in calibration.calibrate(res.legs, q).items()
                             if x in ('kappa', 'kappa_edges', 'patience', 'legs')} for q in a.false_alarm]
                           + [dict(patience=float(calibration.budget(calibration.calibrate(res.legs, 0.005, stall_scale=c),
                                                                     'stall', 1.0, 0.0)[1]))
                              for c in a.stall_scale])
        secs = (time.perf_counter() - t0) / a.keys
        for ci, c in enumerate(a.stall_scale):
            v = np.array([k[len(a.false_alarm) + ci]['patience'] for k in per_key])
            spread = float(v.max() / v.min() - 1)
            rows.append(dict(episodes=n, stall_scale=c, patience=dict(values=v.tolist(), min=float(v.min()),
                             median=float(np.median(v)), max=float(v.max()), spread=spread)))
            print(f'{n:4d} episodes, patience {c:g} x q90 of the longest stall: {v.min():.4g} / {np.median(v):.4g} / '
                  f'{v.max():.4g} (+{100 * spread:.0f}%)')
        for qi, q in enumerate(a.false_alarm):
            cells = [c[qi] for c in per_key]
            row = dict(episodes=n, false_alarm=q, legs=[int(c['legs']) for c in cells], seconds_per_pass=round(secs, 1))
            line = f'{n:4d} episodes, {q:.1%}: legs {int(np.median(row["legs"]))} (median); '
            for name in ('patience', 'kappa', 'kappa_edges'):
                v = np.array([c[name] for c in cells])
                spread = float(v.max() / v.min() - 1) if v.min() > 0 else float('inf')
                row[name] = dict(values=v.round(3).tolist(), min=float(v.min()), median=float(np.median(v)),
                                 max=float(v.max()), spread=spread)
                line += f'{name} {v.min():.4g} / {np.median(v):.4g} / {v.max():.4g} (+{100 * spread:.0f}%); '
            print(line + f'{secs:.0f} s per pass')
            rows.append(row)
    finish([dict(rows=rows, checkpoint=a.checkpoint, command=' '.join(sys.argv))], a.out)


if __name__ == '__main__':
    main()
