"""GAS's node construction against its public reference, on the same embeddings.

    git clone https://github.com/qortmdgh4141/GAS /tmp/GAS        # or any checkout of it
    python benchmarks/parity/bench_parity_gas.py --reference /tmp/GAS

The reference's own ``K_utils/keynodes_utils.py`` (temporal-efficiency filtering, TD-aware
clustering) and ``K_utils/keygraph_utils.py`` (edges within ``way_steps``, components joined by
their closest pairs; it needs ``networkx``), imported from ``--reference``, not copied, and
:mod:`aqm_mjx.mapping.gas_nodes` run on the same embeddings: random walks in 8 dimensions,
trajectories of uneven length, at several ``(way_steps, threshold)``. Per case: the states kept
(equal sets), the node count, the largest difference between the node centres, and the edges (the
same set, weights within 1e-4) on the reference's nodes, and each state's waystep subgoal
(``O_utils/datasets.py``'s ``build_waysteps_idx_by_distance``). The control runs ours at a threshold moved
by 0.05 and must disagree (a parity check that cannot fail checks nothing).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
import types

import jax.numpy as jnp
import numpy as np

from aqm_mjx.mapping import gas_nodes

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

CASES = ((10, 0.5), (25, 0.0), (5, 0.9), (50, 0.7))


def _reference(root: str, name: str, folder: str = 'K_utils'):
    path = os.path.join(root, folder, f'{name}.py')
    if not os.path.exists(path):
        raise SystemExit(f'{path} not found: --reference must be a checkout of qortmdgh4141/GAS')
    spec = importlib.util.spec_from_file_location(f'gas_{name}', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _reference_edges(ref_graph, centers: np.ndarray, way_steps: float) -> dict:
    """The reference's edges on ``centers``: ``{(i, j): weight}``."""
    import networkx as nx  # pylint: disable=import-outside-toplevel

    g = nx.DiGraph()
    g.add_nodes_from(range(len(centers)))
    g, pdist = ref_graph.add_distance_based_edges(g, centers, way_steps, 256)
    g = ref_graph.connect_strongly_connected_components(nx.DiGraph(g), pdist)
    return {(u, v): float(np.linalg.norm(centers[u] - centers[v])) for u, v in g.edges}


def _ours(f, ends, way_steps, threshold, max_len, max_nodes):
    keep = gas_nodes.efficient_states(jnp.asarray(f), jnp.asarray(ends), way_steps, threshold, max_len=max_len)
    nodes = gas_nodes.td_aware_clustering(jnp.asarray(f), keep, way_steps, max_nodes=max_nodes)
    return np.nonzero(np.asarray(keep))[0], np.asarray(nodes.centers)[:int(nodes.count)], bool(nodes.overflow)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--reference', required=True, help='a checkout of github.com/qortmdgh4141/GAS')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--out', default=None)
    a = p.parse_args()
    ref = _reference(a.reference, 'keynodes_utils')
    ref_graph = _reference(a.reference, 'keygraph_utils')
    ref_data = _reference(a.reference, 'datasets', 'O_utils')
    rng = np.random.default_rng(a.seed)
    lens = [300, 250, 400, 120, 1000]
    f = np.concatenate([np.cumsum(rng.normal(size=(n, 8)), 0) for n in lens]).astype(np.float32)
    dones = np.zeros(len(f), np.float32)
    dones[np.cumsum(lens) - 1] = 1
    ends = np.concatenate([np.full(n, e) for n, e in zip(lens, np.cumsum(lens) - 1)]).astype(np.int32)
    rows, ok, control_agrees = [], True, True
    print(f'{len(f)} states in {len(lens)} trajectories, 8-d embeddings')
    print(f'{"H":>4} {"thr":>5} {"kept ref":>9} {"kept ours":>9} {"same":>5} {"nodes ref":>9} {"nodes ours":>10} '
          f'{"max |dc|":>9} {"edges ref":>9} {"edges ours":>10} {"same":>5} {"waysteps":>8} {"control":>8} {"ours s":>7}')
    for way_steps, thr in CASES:
        with open(os.devnull, 'w') as null:  # the reference prints tqdm bars
            err, sys.stderr = sys.stderr, null
            try:
                trajs, starts = ref.split_trajectories(f, dones)
                want = np.asarray(ref.collect_efficiency_states(trajs, starts, way_steps, thr))
                centers = ref.td_aware_clustering(f, want, way_steps)
                edges = _reference_edges(ref_graph, centers, way_steps)
                holder = types.SimpleNamespace(dataset=dict(observations=f), terminal_locs=np.nonzero(dones)[0], f_s=f,
                                               config=dict(way_steps=way_steps))
                waysteps = ref_data.GASDataset.build_waysteps_idx_by_distance(holder)
            finally:
                sys.stderr = err
        t0 = time.perf_counter()
        got, ours, overflow = _ours(f, ends, way_steps, thr, max(lens), 4096)
        secs = time.perf_counter() - t0
        same = np.array_equal(want, got) and ours.shape == centers.shape and not overflow
        diff = float(np.abs(ours - centers).max()) if ours.shape == centers.shape else float('inf')
        w = np.asarray(gas_nodes.gas_edges(jnp.asarray(centers), jnp.ones(len(centers), bool), way_steps))
        mine = {(int(i), int(j)): float(w[i, j]) for i, j in zip(*np.nonzero(np.isfinite(w))) if i != j}
        same_edges = mine.keys() == edges.keys() and all(abs(mine[e] - edges[e]) < 1e-4 for e in edges)
        same_waysteps = np.array_equal(np.asarray(gas_nodes.waystep_indices(jnp.asarray(f), jnp.asarray(ends), way_steps,
                                                                             max_len=max(lens))), waysteps)
        c_got, c_centers, _ = _ours(f, ends, way_steps, thr + 0.05, max(lens), 4096)  # CONTROL: another threshold
        control = np.array_equal(want, c_got) and c_centers.shape == centers.shape
        ok &= same and diff < 1e-4 and same_edges and same_waysteps
        control_agrees &= control
        rows.append(dict(way_steps=way_steps, threshold=thr, kept_ref=len(want), kept_ours=len(got), same_kept=same,
                         nodes_ref=len(centers), nodes_ours=len(ours), max_center_diff=diff, edges_ref=len(edges),
                         edges_ours=len(mine), same_edges=same_edges, same_waysteps=same_waysteps, control_agrees=control,
                         seconds_ours=secs))
        print(f'{way_steps:4d} {thr:5.2f} {len(want):9d} {len(got):9d} {str(same):>5} {len(centers):9d} {len(ours):10d} '
              f'{diff:9.1e} {len(edges):9d} {len(mine):10d} {str(same_edges):>5} {str(same_waysteps):>8} {"agrees" if control else "differs":>8} '
              f'{secs:7.2f}')
    print(f'parity: {"PASS" if ok else "FAIL"} (same states kept, same nodes, centres within 1e-4, same edges, same waystep subgoals); '
          f'control: {"FAIL (agreed)" if control_agrees else "differs as it must"}')
    finish(rows, a.out)
    sys.exit(0 if ok and not control_agrees else 1)


if __name__ == '__main__':
    main()
