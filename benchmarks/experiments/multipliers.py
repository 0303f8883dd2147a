"""How a quasimetric's Lagrange multiplier and its local constraint move over training, read from
runs' ``metrics.jsonl``: AQM's ``qrl/lambda`` (lambda itself trained) and QRL's ``value/lambda``
(OGBench's ``exp(log_lambda)``), beside the constraint's mean squared excess relu(d(s, s') - 1)^2,
whose bound is epsilon^2 = 0.05.

    python benchmarks/experiments/multipliers.py runs/antmaze-medium-cpu/train \
        runs/nav_report/train/qrl/seed_1 --out benchmarks/results/multipliers/multipliers.json

AQM logs the constraint as ``lambda/violation`` = mean relu(d - 1)^2 - epsilon^2; QRL as
``value/d_pos_loss`` = mean relu(d - 1)^2.
"""

from __future__ import annotations

import argparse
import os
import sys

from aqm_mjx.evaluation import plots

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

EPS2 = 0.05
STEPS = (500, 2_000, 4_000, 8_000, 12_000, 16_000, 18_000, 20_000)


def read(run: str, steps=STEPS) -> dict:
    """One run's multiplier, squared excess and mean d(s, s') at ``steps`` (the nearest logged step
    at or before each)."""
    path = os.path.join(run, 'metrics.jsonl')
    if not os.path.exists(path):
        raise FileNotFoundError(f'{run}: no metrics.jsonl (a run folder of aqm-mjx train, run or compare)')
    rows = [r for r in plots.read_metrics(path) if 'step' in r]
    if any('qrl/lambda' in r for r in rows):
        lam, excess, d_pos = 'qrl/lambda', lambda r: r['lambda/violation'] + EPS2, 'qrl/d_pos_mean'
    elif any('value/lambda' in r for r in rows):
        lam, excess, d_pos = 'value/lambda', lambda r: r['value/d_pos_loss'], 'value/d_pos_mean'
    else:
        raise ValueError(f'{run}: metrics.jsonl logs no multiplier (qrl/lambda or value/lambda)')
    logged = sorted((r for r in rows if lam in r), key=lambda r: r['step'])
    out = []
    for s in steps:
        before = [r for r in logged if r['step'] <= s]
        if before:
            r = before[-1]
            out.append(dict(step=r['step'], lam=float(r[lam]), excess=float(excess(r)), d_pos=float(r[d_pos])))
    return dict(run=run, multiplier=lam, points=out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('runs', nargs='+', help='run folders with a metrics.jsonl')
    p.add_argument('--out', help='write the rows as JSON here')
    a = p.parse_args(argv)
    rows = [read(r) for r in a.runs]
    for row in rows:
        print(f'{row["run"]} ({row["multiplier"]})')
        print('  update     ' + ' '.join(f'{q["step"]:>8,}' for q in row['points']))
        print('  lambda     ' + ' '.join(f'{q["lam"]:>8.1f}' for q in row['points']))
        print('  excess^2   ' + ' '.join(f'{q["excess"]:>8.4f}' for q in row['points']))
        print('  d(s, s\')   ' + ' '.join(f'{q["d_pos"]:>8.3f}' for q in row['points']))
    finish(rows, a.out)
    return 0


if __name__ == '__main__':
    sys.exit(main())
