"""What the moving progress bar costs: the evaluation program with its host hook against the same
program without it, on the same episodes, in one run.

    python benchmarks/throughput/bench_progress.py                    # CPU: antmaze-medium, 64 envs x 500 steps, ~5 minutes
    python benchmarks/throughput/bench_progress.py --batch 4096 --steps 1000      # on a GPU

Both programs are :func:`aqm_mjx.agent.rollout.make_rollout` of the full AQM agent (``cpu``-preset
shapes, random weights, as ``bench_evaluate.py``); one is built with ``progress=`` a
:class:`aqm_mjx.progress.ChunkBar` (a host callback every 50 control steps), the other without. Each
is compiled and run once first (compile printed apart), then they are timed alternately
``--repeats`` times on the same inputs; the overhead is the ratio of the median times minus one.
The final positions of both are checked equal (the hook changes nothing).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import numpy as np

from aqm_mjx import envs
from aqm_mjx.agent import rollout
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.progress import ChunkBar

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402
from bench_evaluate import make_agent


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--env', default='antmaze-medium')
    p.add_argument('--batch', type=int, default=64)
    p.add_argument('--steps', type=int, default=500)
    p.add_argument('--keypoints', type=int, default=64)
    p.add_argument('--repeats', type=int, default=3)
    p.add_argument('--out', default=None, help='JSON file for the rows')
    a = p.parse_args()
    env = envs.make(a.env)
    agent, graph, _ = make_agent(env, None, a.keypoints)
    cfg = AgentConfig(kappa=1.0, switch_radius=1.0)
    ids = np.arange(a.batch, dtype=np.int32) % 5 + 1
    inputs = rollout.episode_inputs(rollout.episode_keys(jax.random.PRNGKey(1), np.arange(a.batch)), ids, env.layout,
                                    1.0, True)
    ticks = ChunkBar(None)
    programs = {'without the hook': jax.jit(rollout.make_rollout(env, agent, cfg, a.steps)),
                'with the hook': jax.jit(rollout.make_rollout(env, agent, cfg, a.steps, progress=ticks))}
    rows, times, xy = [], {k: [] for k in programs}, {}
    for name, prog in programs.items():
        t0 = time.perf_counter()
        out = jax.block_until_ready(prog(agent.aux, graph, inputs))
        xy[name] = np.asarray(out['xy'][-1])
        print(f'{name}: compile and first call {time.perf_counter() - t0:.1f} s')
    calls_before = ticks.calls
    for _ in range(a.repeats):
        for name, prog in programs.items():
            ticks.start(a.batch, a.steps)
            t0 = time.perf_counter()
            jax.block_until_ready(prog(agent.aux, graph, inputs))
            times[name].append(time.perf_counter() - t0)
    calls = (ticks.calls - calls_before) // a.repeats
    same = bool(np.array_equal(xy['without the hook'], xy['with the hook']))
    base = float(np.median(times['without the hook']))
    for name, ts in times.items():
        med = float(np.median(ts))
        rows.append(dict(row=name, batch=a.batch, steps=a.steps, median_s=round(med, 3), runs_s=[round(t, 3) for t in ts],
                         control_steps_per_s=round(a.batch * a.steps / med, 1), ratio=round(med / base, 4)))
        print(f'{name:<17} median {med:7.3f} s  ({", ".join(f"{t:.3f}" for t in ts)})  '
              f'{a.batch * a.steps / med:9.1f} control steps/s  ratio {med / base:.4f}')
    print(f'host callbacks per call: {calls} (every 50 of {a.steps} steps); overhead '
          f'{100 * (rows[1]["median_s"] / rows[0]["median_s"] - 1):+.2f}%; same final positions: {same}')
    finish(rows + [dict(row='check', callbacks_per_call=calls, same_positions=same)], a.out)


if __name__ == '__main__':
    main()
