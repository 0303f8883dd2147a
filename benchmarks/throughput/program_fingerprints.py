"""Fingerprints of every method's training program, to tell a refactor that changes nothing from one
that changes the computation: run it at two commits and compare the hashes.

    python benchmarks/throughput/program_fingerprints.py                         # this checkout
    git worktree add /tmp/old REV && (cd /tmp/old && PYTHONPATH=. python benchmarks/throughput/program_fingerprints.py)

Per method: the StableHLO of one jitted training chunk (5 updates at the ``cpu`` preset's shapes,
antmaze's 29-d observations and 8-d actions, a random dataset of 20,000 states), printed without
source locations, and its SHA-256. Equal hashes mean the same program, so the same updates/s and
the same numbers; ``benchmarks/throughput/bench_train.py`` then has nothing to measure. Lowering only: no
compilation, about a minute on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import sys

import jax
import numpy as np

from aqm_mjx.data import dataset as dsm
from aqm_mjx.learn import fit, methods

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402


def program_text(name: str, ds, updates: int = 5) -> str:
    """The StableHLO of ``updates`` updates of method ``name`` at the ``cpu`` preset, locations removed."""
    m = methods.get(name)
    learner = m.make(m.preset('cpu', env='antmaze-medium'), 29, 8)
    state = learner.init(jax.random.PRNGKey(0))
    txt = jax.jit(fit.chunk_step(learner.update, updates)).lower(state, ds).as_text(debug_info=False)
    return re.sub(r'#loc\d*', '', re.sub(r'loc\([^)]*\)', '', txt))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--methods', nargs='*', default=methods.names(), choices=methods.names())
    p.add_argument('--out', default=None, help='also write the rows as JSON')
    a = p.parse_args()
    rng = np.random.default_rng(0)
    n = 20_000
    term = np.zeros(n, bool)
    term[999::1000] = True
    ds = dsm.to_device(dict(observations=rng.normal(size=(n, 29)).astype(np.float32),
                            actions=rng.uniform(-1, 1, (n, 8)).astype(np.float32), terminals=term))
    rows = []
    for name in a.methods:
        txt = program_text(name, ds)
        rows.append(dict(method=name, sha256=hashlib.sha256(txt.encode()).hexdigest(), chars=len(txt)))
        print(f'{name:8} {rows[-1]["sha256"][:16]}  {len(txt):8d} chars')
    finish(rows, a.out)


if __name__ == '__main__':
    main()
