"""A method's distance along the data: the quantiles of ``d(s_t, s_{t+k})`` in control steps for several
offsets ``k``, on states drawn from the dataset's own trajectories, for each checkpoint given. What a
planner (``--planner aqm|ttgs``) builds its map on, read over the whole range the map uses: AQM's
keypoints at delta 8 and TTGS's tau 24 need the short range (k of 1-25) to grow, its budgets and
searches the long range. ``mapping.build.distance_check`` tests two of these offsets (1 and 25)
before a map is built; this prints the profile behind that test.

    python benchmarks/experiments/distance_profile.py --dataset runs/antmaze-medium/data/antmaze-medium-navigate.npz \
        --checkpoint runs/nav_crl/train/crl/seed_1 --checkpoint runs/nav_qrl/train/qrl/seed_1 \
        --out benchmarks/results/planners_medium_navigate/distance_profile.json

Each row: the checkpoint, its method, and per offset k the 10%, 50% and 90% quantiles of d and the
share of pairs where d(s_t, s_{t+k}) <= d(s_t, s_t) (a distance that does not tell s_{t+k} from s_t).

``--coverage K [K ...]`` adds how many keypoints AQM's map needs on the distance: IWE at ``--delta``
over the candidates an evaluation draws (``--candidates``, the map key ``aqm-mjx evaluate --seed S``
uses; one run with the most slots, read at each K), and how many candidates K slots left outside
every keypoint's delta (0: the map covers the data). When an evaluation warns that its keypoints did not cover the candidates,
this says whether more slots would, and how many:

    python benchmarks/experiments/distance_profile.py --dataset runs/giant/data400/antmaze-giant-navigate.npz \
        --checkpoint runs/map67/giant_nav_gcivl/train/gcivl/seed_0 --offsets 1 25 --coverage 512 1024 2048 --delta 12
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

from aqm_mjx.agent import planners
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import MapConfig, distances_along, select_keypoints
from aqm_mjx.pipeline import stage_keys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

OFFSETS = (0, 1, 2, 5, 10, 25, 50, 100, 200)


def profile(trained: fit.Trained, obs: np.ndarray, terminals: np.ndarray, offsets, pairs: int,
            seed: int) -> tuple[dict, int] | None:
    """``({k: {'q10', 'q50', 'q90', 'not_above_d0'}}, P)``: the method's ``d(s_t, s_{t+k})`` over the ``P``
    pairs :func:`aqm_mjx.mapping.build.distances_along` draws with ``PRNGKey(seed)`` (the same for every
    checkpoint); None when the data hold no trajectory long enough."""
    if trained.learner.distance is None:
        raise ValueError(f'{trained.method} has no distance in steps (it runs flat): nothing to profile')
    agent = planners.around(trained.agent, trained.learner.distance, 'aqm', trained.method)
    d = distances_along(agent, obs, terminals, jax.random.PRNGKey(seed), sorted({0, *offsets}), pairs)
    if d is None:
        return None
    out = {}
    for k in offsets:
        q10, q50, q90 = (float(x) for x in np.quantile(d[k], [0.1, 0.5, 0.9]))
        out[int(k)] = dict(q10=q10, q50=q50, q90=q90, not_above_d0=float(np.mean(d[k] <= d[0])))
    return out, len(d[0])


def coverage(trained: fit.Trained, obs: np.ndarray, slots, delta: float, candidates: int, seed: int) -> list[dict]:
    """Per slot count K: IWE's keypoints at ``delta`` on the method's distance (planner ``aqm``) over the
    candidates an evaluation with ``--seed seed`` draws, whether K slots overflowed and how many candidates
    they left uncovered. One IWE run with the most slots: its first K keypoints are the K-slot run's
    (the greedy order does not depend on K), so ``Keypoints.left`` gives every K."""
    agent = planners.around(trained.agent, trained.learner.distance, 'aqm', trained.method)
    cfg = MapConfig(delta=delta, max_keypoints=max(slots), candidates=candidates)
    t0 = time.perf_counter()
    cand, _, kp = jax.jit(lambda o, k: select_keypoints(agent, o, cfg, k))(obs, stage_keys(jax.random.PRNGKey(seed))[1])
    count, left = int(kp.count), np.asarray(kp.left)
    seconds = round(time.perf_counter() - t0, 1)
    return [dict(slots=int(k), keypoints=min(count, int(k)), overflow=bool(left[min(count, k) - 1] > 0),
                 uncovered=int(left[min(count, k) - 1]), candidates=int(cand.shape[0]), seconds=seconds)
            for k in slots]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--checkpoint', action='append', required=True, help='a trained run folder (repeat for several)')
    p.add_argument('--dataset', required=True, help='the .npz whose trajectories the pairs come from')
    p.add_argument('--offsets', type=int, nargs='+', default=list(OFFSETS))
    p.add_argument('--pairs', type=int, default=256)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--coverage', type=int, nargs='+', default=[], metavar='K',
                   help="IWE's keypoints at --delta with K slots each, and the candidates K slots left uncovered")
    p.add_argument('--delta', type=float, default=12.0, help="IWE's repel radius for --coverage (cpu-giant's: 12)")
    p.add_argument('--candidates', type=int, default=MapConfig.candidates,
                   help='dataset states IWE selects from for --coverage (the map default)')
    p.add_argument('--out')
    a = p.parse_args()
    if min(a.offsets) < 0:
        p.error('--offsets must be >= 0')
    if a.coverage and (min(a.coverage) < 1 or not a.delta > 0 or a.candidates < 1):
        p.error('--coverage slot counts, --delta and --candidates must be positive')
    data = ds_io.read_ogbench(a.dataset)
    obs = np.asarray(data['observations'], np.float32)
    rows = []
    print(f'{a.dataset}; d(s_t, s_t+k) in steps: 10% / median / 90%, and the share with d <= d(s_t, s_t)')
    print(f'{"checkpoint":44s} {"method":6s} ' + ' '.join(f'{"k=" + str(k):>18s}' for k in a.offsets))
    for ck in a.checkpoint:
        trained = fit.load(ck, log=lambda *_: None)
        t0 = time.perf_counter()
        try:
            found = profile(trained, obs, data['terminals'], a.offsets, a.pairs, a.seed)
        except ValueError as e:
            sys.exit(f'distance_profile: {ck}: {e}')
        if found is None:
            sys.exit(f'distance_profile: the data hold no trajectory of {max(a.offsets) + 1} states: lower --offsets')
        prof, n = found
        cells = ' '.join(f'{r["q10"]:5.0f}/{r["q50"]:5.0f}/{r["q90"]:5.0f}'.rjust(18) for r in prof.values())
        shares = ' '.join(f'{r["not_above_d0"]:18.2f}' for r in prof.values())
        print(f'{ck[-44:]:44s} {trained.method:6s} {cells}\n{"":44s} {"<=d0":6s} {shares}')
        row = dict(checkpoint=ck, method=trained.method, step=trained.step, pairs=n,
                   seconds=round(time.perf_counter() - t0, 2), offsets={str(k): v for k, v in prof.items()})
        if a.coverage:
            row.update(delta=a.delta, coverage=coverage(trained, obs, a.coverage, a.delta, a.candidates, a.seed))
            for c in row['coverage']:
                print(f'{"":44s} IWE at delta {a.delta:g} with {c["slots"]} slots: {c["keypoints"]} keypoints, '
                      f'{c["uncovered"]:,} of {c["candidates"]:,} candidates left uncovered')
            print(f'{"":44s} ({row["coverage"][0]["seconds"]} s for IWE with {max(a.coverage)} slots)')
        rows.append(row)
    finish(rows, a.out)


if __name__ == '__main__':
    main()
