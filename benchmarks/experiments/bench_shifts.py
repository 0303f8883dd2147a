"""The shift suite without learning: replanning across every test-time layout of a maze.

    python benchmarks/experiments/bench_shifts.py                        # CPU: antmaze-medium, 2 episodes, ~10 minutes
    python benchmarks/experiments/bench_shifts.py --episodes 50 --envs 4096   # on a GPU: the full protocol

The quasimetric is the exact maze distance of the *training* layout (``oracle.maze_graph``, IWE at
``--delta`` m, a time-to-reach at 0.12 m per control step); the controller is the scripted trot
steered by the training layout's BFS toward the current target. So on a shifted layout the agent's
map and controller are both out of date, as a learned agent's would be. Rows: AQM (kappa 0.25), no
pruning (kappa = inf) and the flat agent (always aimed at the goal); columns: the layouts of
:func:`aqm_mjx.envs.shifts.suite`. Every agent x layout x task x episode runs as one episode table
(:func:`aqm_mjx.evaluation.evaluate.evaluate`). Writes a heatmap PNG and the JSON summary.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from aqm_mjx import envs
from aqm_mjx.agent import oracle
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.envs import shifts
from aqm_mjx.evaluation import evaluate, plots, report
from aqm_mjx.evaluation.protocol import ProtocolConfig
from aqm_mjx.mapping import graph as graphs

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

SPEED = 0.12  # m per control step of the scripted trot at noise 0 (about 1.2 m/s)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--env', default='antmaze-medium')
    p.add_argument('--episodes', type=int, default=2)
    p.add_argument('--envs', type=int, default=192)
    p.add_argument('--delta', type=float, default=4.0, help='IWE repel radius (m)')
    p.add_argument('--out', default='benchmarks/results/shifts_cpu')
    a = p.parse_args()
    env = envs.make(a.env)
    base = env.layout
    agent, graph, match = oracle.oracle_agent(env, base, delta=a.delta, speed=SPEED)
    protocol = ProtocolConfig(episodes=a.episodes, envs=a.envs, ablations=('no-pruning', 'flat'))
    variants = shifts.suite(env.maze)
    res = evaluate.evaluate(env, agent, graph, AgentConfig(**match), protocol, variants)
    report.print_summary(res)
    os.makedirs(a.out, exist_ok=True)
    vals = np.array([[res.summary[ag][v]['mean'] for v in res.variants] for ag in res.agents])
    plots.heatmap(res.agents, res.variants, vals, os.path.join(a.out, 'heatmap.png'), ylabel='agent',
                  title=f'{a.env}: exact-distance map and scripted trot of the base layout, {a.episodes} ep/task')
    plots.trajectory_panels(base, variants, res.traces, np.asarray(graph.obs)[:, :2],
                            graphs.edge_list(graph.w, graph.mask),
                            'aqm', res.tasks[0], os.path.join(a.out, 'trajectories.png'))
    with open(os.path.join(a.out, 'summary.json'), 'w') as f:
        json.dump(dict(summary=res.summary, timing=res.timing, keypoints=int(graph.mask.sum())), f, indent=1)
    finish([dict(summary=res.summary, timing=res.timing)], os.path.join(a.out, 'rows.json'))


if __name__ == '__main__':
    main()
