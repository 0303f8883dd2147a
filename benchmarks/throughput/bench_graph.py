"""Floyd-Warshall throughput against SciPy, and IWE time on large candidate sets, in one run.

    python benchmarks/throughput/bench_graph.py                    # CPU defaults
    python benchmarks/throughput/bench_graph.py --batches 1 16 256 1024 4096 --iwe-sizes 100000 1000000

Floyd-Warshall: ``jit(plan.floyd_warshall_batch)`` on B random directed graphs of K nodes with
infinite entries, against ``scipy.sparse.csgraph.floyd_warshall`` called once per graph on the
same graphs (SciPy has no batched form). The ratio is graphs/s of JAX over graphs/s of SciPy.

IWE: ``keypoints.iwe`` over N candidates in a 2-D latent space with a cheap asymmetric quasimetric
(d(x, y) = |y - x| + 0.5 relu(y_0 - x_0)), delta chosen so K lands near 50 to 200. The cost per
iteration is one pass over the N encoded candidates; a learned encoder's latent distance costs
more per pair but scales the same way.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.sparse.csgraph import floyd_warshall as scipy_fw

from aqm_mjx.agent import plan
from aqm_mjx.mapping import keypoints


def graphs(rng, b, k):
    w = rng.uniform(0.5, 10.0, (b, k, k)).astype(np.float32)
    w[rng.random((b, k, k)) > 6.0 / k] = np.inf
    return w


def bench_fw(k, b, reps, rng, with_next):
    w = graphs(rng, b, k)
    f = jax.jit(lambda x: plan.floyd_warshall_batch(x, with_next=with_next))  # chunk: 8 on CPU, whole batch on GPU
    wj = jnp.asarray(w)
    t0 = time.perf_counter()
    jax.block_until_ready(f(wj))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(reps):
        out = f(wj)
    jax.block_until_ready(out)
    jax_rate = b * reps / (time.perf_counter() - t0)
    n_sp = min(b, 64)  # SciPy per graph is constant; time up to 64 graphs
    dense = np.where(np.isfinite(w[:n_sp]), w[:n_sp], 0.0).astype(np.float64)
    t0 = time.perf_counter()
    for g in range(n_sp):
        ref = scipy_fw(dense[g], directed=True, return_predecessors=with_next)
    sp_rate = n_sp / (time.perf_counter() - t0)
    ref_d = ref[0] if with_next else ref
    np.testing.assert_allclose(np.asarray(out[0][n_sp - 1]), ref_d, rtol=1e-4)
    return compile_s, jax_rate, sp_rate


def bench_iwe(n, delta, kmax, chunk):
    rng = np.random.default_rng(0)
    pts = jnp.asarray(rng.random((n, 2)), jnp.float32)

    def d(x, y):
        return jnp.linalg.norm(y - x) + 0.5 * jnp.maximum(y[0] - x[0], 0.0)

    # The candidates are an argument: captured as a constant, XLA would constant-fold the distance
    # pass at compile time (minutes at 10^7 candidates).
    f = jax.jit(lambda p, key, dl: keypoints.iwe(d, p, key, dl, kmax, chunk=chunk))
    t0 = time.perf_counter()
    kp = f(pts, jax.random.PRNGKey(0), delta)
    jax.block_until_ready(kp)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    kp = f(pts, jax.random.PRNGKey(1), delta)
    jax.block_until_ready(kp)
    run = time.perf_counter() - t0
    return first - run, run, int(kp.count), bool(kp.overflow)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--ks', type=int, nargs='*', default=[64, 160, 256], help='graph sizes K (none: skip Floyd-Warshall)')
    p.add_argument('--batches', type=int, nargs='+', default=[1, 16, 256, 1024], help='graphs per batch')
    p.add_argument('--max-elements', type=float, default=1.2e8, help='skip B*K*K above this (memory/time)')
    p.add_argument('--reps', type=int, default=3)
    p.add_argument('--iwe-sizes', type=int, nargs='*', default=[100_000, 1_000_000], help='candidate counts (none: skip IWE)')
    p.add_argument('--iwe-deltas', type=float, nargs='+', default=[0.12, 0.07], help='delta values (K ~ 60, 180)')
    p.add_argument('--chunk', type=int, default=65536)
    a = p.parse_args(argv)
    dev = jax.devices()[0]
    print(f'# bench_graph: {dev.platform} {dev.device_kind}, {os.cpu_count()} CPU cores, {platform.processor() or platform.machine()}')
    rng = np.random.default_rng(0)
    print('# Floyd-Warshall; "dist" = distances only (SciPy default), "+next" = with the next-hop '
          'matrix (SciPy return_predecessors=True)')
    print(f'{"K":>5}{"batch":>7}{"output":>8}{"compile s":>11}{"jax graphs/s":>14}{"scipy graphs/s":>16}{"ratio":>8}')
    for k in a.ks:
        for b in a.batches:
            if b * k * k > a.max_elements:
                continue
            for with_next in (False, True):
                c, jr, sr = bench_fw(k, b, a.reps, rng, with_next)
                out = '+next' if with_next else 'dist'
                print(f'{k:>5}{b:>7}{out:>8}{c:>11.2f}{jr:>14.1f}{sr:>16.1f}{jr / sr:>8.2f}', flush=True)
    print(f'{"N":>9}{"delta":>7}{"compile s":>11}{"run s":>8}{"keypoints":>11}{"overflow":>10}')
    for n in a.iwe_sizes:
        for delta in a.iwe_deltas:
            c, r, cnt, of = bench_iwe(n, delta, 400, a.chunk)
            print(f'{n:>9}{delta:>7}{c:>11.2f}{r:>8.2f}{cnt:>11}{str(of):>10}', flush=True)


if __name__ == '__main__':
    main()
