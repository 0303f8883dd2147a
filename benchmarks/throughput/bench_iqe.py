"""IQE's interval-union length, the sweep (the package's) against the sort of 2M endpoints (the
reference), and QRL's training updates/s with each, in one run.

    python benchmarks/throughput/bench_iqe.py                       # CPU: about 7 min on 2 cores
    python benchmarks/throughput/bench_iqe.py --presets cpu --calls 5

Part 1 times ``value_and_grad`` of the summed lengths for latents of OGBench's QRL (64 components of
8) at the ``cpu`` and ``paper`` batches (256, 1024), compile apart from the mean of ``--calls`` runs,
and checks that both give the same lengths, and the same gradients except where two endpoints are
equal (there the length has no gradient and each hands the subgradient to a different end).
Part 2 runs QRL's whole update (its IQE, latent dynamics and DDPG+BC actor; bench_train's row)
with the package's sweep and then with ``interval_union_length`` swapped for the sort at trace
time, and prints the ratio.
AQM's own IQE (components of 1) takes neither path; it is one ``relu``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.learn import quasimetric as qm

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402
from bench_train import rate


def _time(f, args, calls):
    """(compile + first call s, mean s of ``calls`` more calls, last output)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(calls):
        out = f(*args)
    jax.block_until_ready(out)
    return first, (time.perf_counter() - t0) / calls, out


def _grad_check(x, y, g_sweep, g_sort) -> dict:
    """Where the two gradients differ, and whether each such component has two equal endpoints.

    Where endpoints tie (two equal ends, say) the length is not differentiable and each way hands
    the subgradient to a different one of them; elsewhere the two must agree exactly.
    """
    neq = [np.asarray(a) != np.asarray(b) for a, b in zip(g_sweep, g_sort)]  # d/dx, d/dy: [..., M] each
    differ = np.any(neq[0] | neq[1], axis=-1)  # components with a differing entry
    ends = np.concatenate([np.asarray(x), np.maximum(np.asarray(x), np.asarray(y))], axis=-1)[differ]  # [n, 2M]
    srt = np.sort(ends, axis=-1)
    tied = np.any(srt[:, 1:] == srt[:, :-1], axis=-1)
    return dict(grad_entries=2 * int(x.size), grad_entries_differ=int(sum(e.sum() for e in neq)),
                differ_only_at_ties=bool(np.all(tied)))


def union_rows(calls):
    rows = []
    for batch in (256, 1024):
        x = jax.random.normal(jax.random.PRNGKey(0), (batch, 64, 8))
        y = jax.random.normal(jax.random.PRNGKey(1), (batch, 64, 8))
        res = {}
        for name, f in (('sweep', qm.interval_union_length), ('sort', qm.interval_union_length_sorted)):
            g = jax.jit(jax.value_and_grad(lambda a, b, f=f: jnp.sum(f(a, b)), argnums=(0, 1)))
            first, dt, out = _time(g, (x, y), calls)
            res[name] = (first, dt, out)
        (_, (gx, gy)), (_, (hx, hy)) = res['sweep'][2], res['sort'][2]
        row = dict(part='union', batch=batch, components=64, size=8,
                   sweep_compile_s=round(res['sweep'][0] - res['sweep'][1], 2), sweep_ms=round(res['sweep'][1] * 1e3, 2),
                   sort_compile_s=round(res['sort'][0] - res['sort'][1], 2), sort_ms=round(res['sort'][1] * 1e3, 2),
                   sort_over_sweep=round(res['sort'][1] / res['sweep'][1], 2),
                   value_rel_diff=float(abs(res['sweep'][2][0] - res['sort'][2][0]) / abs(res['sort'][2][0])),
                   **_grad_check(x, y, (gx, gy), (hx, hy)))
        print(f'union  batch {batch:>5} x 64 x 8: sweep {row["sweep_ms"]:8.2f} ms (compile {row["sweep_compile_s"]:.2f} s)  '
              f'sort {row["sort_ms"]:8.2f} ms (compile {row["sort_compile_s"]:.2f} s)  sort/sweep {row["sort_over_sweep"]:.2f}  '
              f'value rel. diff {row["value_rel_diff"]:.1e}  gradient entries that differ {row["grad_entries_differ"]} '
              f'of {row["grad_entries"]}, all at tied endpoints: {row["differ_only_at_ties"]}', flush=True)
        rows.append(row)
    return rows


def qrl_rows(presets, calls):
    rows = []
    sweep = qm.interval_union_length
    for preset in presets:
        upc = 20 if preset == 'paper' and jax.default_backend() == 'cpu' else None
        got = {}
        for name, f in (('sweep', sweep), ('sort', qm.interval_union_length_sorted)):
            qm.interval_union_length = f  # read when QRL's update is traced, inside rate()
            try:
                got[name] = rate(preset, calls, upc, method='qrl', seeds=1)
            finally:
                qm.interval_union_length = sweep
        row = dict(part='qrl', preset=preset, batch=got['sweep']['batch'], updates_per_call=got['sweep']['updates_per_call'],
                   sweep_updates_per_s=got['sweep']['updates_per_s'], sweep_compile_s=got['sweep']['compile_s'],
                   sort_updates_per_s=got['sort']['updates_per_s'], sort_compile_s=got['sort']['compile_s'],
                   sweep_over_sort=round(got['sweep']['updates_per_s'] / got['sort']['updates_per_s'], 2),
                   sweep_hours_for_preset=got['sweep']['hours_for_preset'], sort_hours_for_preset=got['sort']['hours_for_preset'])
        print(f'qrl    {preset:<6} batch {row["batch"]:>5}: sweep {row["sweep_updates_per_s"]:7.1f} upd/s '
              f'(compile {row["sweep_compile_s"]:.1f} s)  sort {row["sort_updates_per_s"]:7.1f} upd/s '
              f'(compile {row["sort_compile_s"]:.1f} s)  sweep/sort {row["sweep_over_sort"]:.2f}  '
              f'h for the preset {row["sweep_hours_for_preset"]:.2f} against {row["sort_hours_for_preset"]:.2f}', flush=True)
        rows.append(row)
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--presets', nargs='*', default=['cpu', 'paper'], help="QRL's presets for part 2")
    p.add_argument('--calls', type=int, default=3)
    p.add_argument('--out', default=None)
    a = p.parse_args()
    rows = union_rows(a.calls) + qrl_rows(a.presets, a.calls)
    finish(rows, a.out)
    if not all(r['differ_only_at_ties'] for r in rows if r['part'] == 'union'):
        raise SystemExit('the sweep and the sort gave different gradients away from tied endpoints')


if __name__ == '__main__':
    main()
