"""AQM against its ablations on our own datasets, at CPU scale (RESULTS.md's main table).

    python benchmarks/experiments/bench_ablations.py                                   # medium navigate only
    python benchmarks/experiments/bench_ablations.py --cases medium-navigate medium-stitch large-navigate
    python benchmarks/experiments/bench_ablations.py --data-dir runs/antmaze-medium/data   # reuse collected files

For every case MAZE-STYLE:
1. data: collected in MJX into ``OUT/data/antmaze-MAZE-STYLE.npz`` (navigate: ``--episodes`` x 1001
   states; stitch: 5 x as many episodes of 201 states, the same transition count), or reused from
   ``--data-dir``/OUT when the file is there;
2. training, ``cpu`` preset, one run per low-level objective: ``saw`` (AQM: Q-AWR target policy
   distilled into Q-SAW), ``awr`` (Q-AWR on the goal) and ``bc`` (behaviour cloning); resumed when
   the run folder holds a finished run;
3. maps: IWE (AQM), farthest-point sampling with the same delta, and uniform random keypoints as
   many as IWE chose, all from the same candidates; every map padded to ``--max-keypoints`` so that
   one compiled program evaluates every model and map of a maze;
4. evaluation, OGBench's 5 tasks x ``--episodes-per-task``: rows AQM (saw + IWE), no pruning, flat
   (main policy on the goal, no graph), AQM with the FPS and random maps, AQM with the awr and bc
   policies, flat with the awr and bc policies.

Writes ``OUT/ablations.json`` (every row, keypoint counts, times) and ``OUT/ablations.md`` (the table),
updated after every case.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax

from aqm_mjx import assess, envs, run
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.evaluation import evaluate
from aqm_mjx.evaluation.protocol import ProtocolConfig
from aqm_mjx.learn import fit, methods
from aqm_mjx.mapping import build
from aqm_mjx.mapping import graph as graphs

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _report
from _report import finish  # noqa: E402

OBJECTIVES = ('saw', 'awr', 'bc')
METHOD = {'saw': 'aqm', 'awr': 'aqm-awr', 'bc': 'aqm-bc'}  # registry entries of the objectives


def make_maps(agent, obs, cfg: build.MapConfig, key, selectors=('iwe', 'fps', 'random')) -> dict:
    """{selector: (graph, count, overflow)}, each padded to cfg.max_keypoints; 'random' takes as many
    keypoints as 'iwe' chose (IWE runs first)."""
    out = {}
    for sel in selectors:
        scfg = dataclasses.replace(cfg, selector=sel)
        if sel == 'random':
            scfg = dataclasses.replace(scfg, max_keypoints=max(8, out['iwe'][1]))
        g, info = build.trimmed_map(agent, obs, scfg, key)
        out[sel] = (graphs.pad(g, cfg.max_keypoints), info['keypoints'], info['overflow'] and sel != 'random')
    return out


def run_case(case: str, a, out: str, rows: list) -> None:
    maze, style = case.split('-')
    env_name = f'antmaze-{maze}'
    env = envs.make(env_name)
    t0 = time.perf_counter()
    # ours (antmaze-medium-navigate.npz) or OGBench's own file (antmaze-medium-navigate-v0.npz)
    names = [f'{env_name}-{style}.npz', f'{env_name}-{style}-v0.npz']
    given = next((os.path.join(a.data_dir, n) for n in names if a.data_dir and os.path.exists(os.path.join(a.data_dir, n))),
                 None)
    episodes = a.episodes * (5 if style == 'stitch' else 1)
    path = run.data_stage(env_name, out, given, episodes, a.collect_batch, style=style)
    t_data = time.perf_counter() - t0
    data = assess.read_data(path, env)
    print(f'{case}: {len(data["observations"]):,} transitions from {path} ({t_data:.0f} s)', flush=True)
    models, t_train = {}, {}
    for obj in a.objectives:
        tdir = os.path.join(out, case, obj)
        cfg = methods.get(METHOD[obj]).preset('cpu', env=env_name, seed=a.seed)
        t0 = time.perf_counter()
        # train, resume or skip: the one function that decides
        models[obj] = fit.train(METHOD[obj], cfg, data, tdir, resume='auto', dataset_path=path)
        t_train[obj] = time.perf_counter() - t0
    mcfg = build.MapConfig(delta=a.delta, max_keypoints=a.max_keypoints)
    agent_cfg = AgentConfig()
    proto = ProtocolConfig(episodes=a.episodes_per_task, envs=a.envs, ablations=())
    key = jax.random.PRNGKey(a.seed)
    base = {'base': env.layout}
    program = None
    results = {}

    def run_one(name, model, graph, protocol):
        nonlocal program
        agent = model.agent
        if program is None:
            program = evaluate.make_program(env, agent, agent_cfg, protocol.horizon or env.max_episode_steps)
        res = evaluate.evaluate(env, agent, graph, agent_cfg, protocol, base, key=key, program=program, progress=False)
        for who in res.agents:
            label = name if who == 'aqm' else f'{name} [{who}]'
            results[label] = res.summary[who]['base']
            print(f'  {label:<28} {100 * res.summary[who]["base"]["mean"]:5.1f}%', flush=True)

    t0 = time.perf_counter()
    counts = {}
    if 'saw' in models:
        maps = make_maps(models['saw'].agent, data['observations'], mcfg, key)
        counts = {k: v[1] for k, v in maps.items()}
        overflow = [k for k, v in maps.items() if v[2]]
        if overflow:
            print(f'  warning: {overflow} filled all {a.max_keypoints} slots; raise --max-keypoints or --delta')
        run_one('AQM (IWE, Q-SAW)', models['saw'], maps['iwe'][0],
                dataclasses.replace(proto, ablations=('no-pruning', 'flat')))
        run_one('AQM, FPS keypoints', models['saw'], maps['fps'][0], proto)
        run_one('AQM, random keypoints', models['saw'], maps['random'][0], proto)
    for obj, label in (('awr', 'Q-AWR low policy'), ('bc', 'BC low policy')):
        if obj in models:
            g = make_maps(models[obj].agent, data['observations'], mcfg, key, ('iwe',))['iwe'][0]
            run_one(f'AQM, {label}', models[obj], g, dataclasses.replace(proto, ablations=('flat',)))
    t_eval = time.perf_counter() - t0
    rows.append(dict(case=case, transitions=int(len(data['observations'])), keypoints=counts,
                     episodes_per_task=a.episodes_per_task, results=results,
                     seconds=dict(data=round(t_data), train={k: round(v) for k, v in t_train.items()}, eval=round(t_eval))))


def markdown(rows: list) -> str:
    labels = []
    for r in rows:
        for k in r['results']:
            if k not in labels:
                labels.append(k)
    cases = [r['case'] for r in rows]
    lines = ['| agent | ' + ' | '.join(cases) + ' |', '|---|' + '---|' * len(cases)]
    for lab in labels:
        cells = [f"{100 * r['results'][lab]['mean']:.0f}%" if lab in r['results'] else 'not run' for r in rows]
        lines.append(f'| {lab} | ' + ' | '.join(cells) + ' |')
    lines.append('| keypoints IWE / FPS / random | ' + ' | '.join(
        '/'.join(str(r['keypoints'].get(k, '-')) for k in ('iwe', 'fps', 'random')) for r in rows) + ' |')
    return '\n'.join(lines) + '\n'


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--cases', nargs='+', default=['medium-navigate'],
                   help='MAZE-STYLE: medium/large/giant x navigate/stitch')
    p.add_argument('--objectives', nargs='+', default=list(OBJECTIVES), choices=OBJECTIVES)
    p.add_argument('--episodes', type=int, default=100, help='navigate episodes collected (stitch: 5x, shorter)')
    p.add_argument('--collect-batch', type=int, default=110)
    p.add_argument('--data-dir', default=None,
                   help='folder with antmaze-MAZE-STYLE.npz (ours) or antmaze-MAZE-STYLE-v0.npz (OGBench) files to use')
    p.add_argument('--episodes-per-task', type=int, default=4)
    p.add_argument('--envs', type=int, default=20,
                   help='environments per call; 20 (one task x 4 episodes x 5 tasks) keeps one compiled shape')
    p.add_argument('--delta', type=float, default=build.MapConfig.delta)
    p.add_argument('--max-keypoints', type=int, default=160)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--out', default='benchmarks/results/ablations_cpu')
    a = p.parse_args(argv)
    for c in a.cases:
        maze, _, style = c.partition('-')
        if style not in ('navigate', 'stitch'):
            p.error(f'case {c!r}: expected MAZE-navigate or MAZE-stitch')
        envs.parse_name(f'antmaze-{maze}')
    os.makedirs(a.out, exist_ok=True)
    rows = []
    for case in a.cases:
        run_case(case, a, a.out, rows)
        with open(os.path.join(a.out, 'ablations.json'), 'w') as f:
            json.dump(dict(args=vars(a), rows=rows), f, indent=1)
        with open(os.path.join(a.out, 'ablations.md'), 'w') as f:
            f.write(markdown(rows))
    print(markdown(rows))
    finish(rows, None)


if __name__ == '__main__':
    main()
