"""Regression: per-episode success, prunes and keypoint counts of the three ways to run AQM, and of
the test-time agent on a case that reaches its goals.

Recorded at a small fixed configuration (the ci preset at 100 updates, 2 tasks x 2 episodes,
kappa 0 so that budgets are overrun) before the package was split into stage packages; the same
seeds give the same values afterwards (on the ``dev`` episodes, which were the only ones then).
``tests/regression_values.json`` holds them. One change was
intended and recorded: ``aqm-mjx evaluate`` now splits its seed into map and episode keys with
``stage_keys`` as ``aqm-mjx run`` does (it used ``PRNGKey(seed)`` for both), so its values now
equal the step-by-step run's. When AQM's defaults became SAW's subgoal cap and OGBench's
initialiser, the test kept the values by asking for the old ones (``subgoal_cap=end``,
``initializer=lecun``): it checks that the three paths agree and that refactors change nothing,
not the defaults.

The learned cases reach no goal at that scale, so a change that broke reaching goals would pass
them; ``oracle_case`` adds one that does: the exact maze distance and a BFS point controller
(:func:`aqm_mjx.agent.oracle.oracle_agent`) on pointmaze-medium, the unchanged maze and two closed
corridors, with the AQM row (fixed budget, parallel cuts), no pruning, the paper's rule and the
stall rule; recorded when the paper's rule and the leg kinds joined the agent. The same on
antmaze-medium (the scripted trot in OGBench's MuJoCo, 40 s) was recorded before the agent's
refactor, so that it keeps reaching goals with the ant too.
"""

import json
import os

import jax
import numpy as np
import pytest

from aqm_mjx import cli, envs, pipeline, run
from aqm_mjx.agent import oracle
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.data import synthetic
from aqm_mjx.envs import mazes, shifts
from aqm_mjx.evaluation import evaluate as evaluation
from aqm_mjx.evaluation import protocol

SEED = 3
RECORDED = json.load(open(os.path.join(os.path.dirname(__file__), 'regression_values.json')))


def ant_walks(n_traj=30, t_len=40, seed=0):
    """Point walks dressed as 29-d ant observations (upright torso), random 8-d actions."""
    p = synthetic.point_walks('medium', n_traj=n_traj, t_len=t_len, seed=seed)
    n = len(p['terminals'])
    rng = np.random.default_rng(seed)
    obs = np.zeros((n, 29), np.float32)
    obs[:, :2] = p['observations']
    obs[:, 2], obs[:, 3] = 0.75, 1.0
    obs[:, 15:] = rng.normal(0, 0.1, (n, 14))
    return dict(observations=obs, actions=rng.uniform(-1, 1, (n, 8)).astype(np.float32), terminals=p['terminals'])


CASES = {'pointmaze-medium': (synthetic.point_walks, 60), 'antmaze-medium': (ant_walks, 30)}


def config(env_name, horizon):
    cfg = pipeline.RunConfig.preset('ci', env=env_name, seed=SEED)
    return cfg.with_overrides(['train.subgoal_cap=end', 'train.initializer=lecun', 'train.steps=100',
                               'train.updates_per_call=50', 'train.log_every=50',
                               'train.checkpoint_every=50', 'protocol.tasks=1,2', f'protocol.horizon={horizon}',
                               'protocol.ablations=no-pruning,flat', 'protocol.split=dev'])


def run_three_paths(env_name, tmp, monkeypatch):
    make_data, horizon = CASES[env_name]
    data = make_data()
    path = os.path.join(tmp, f'{env_name}-navigate.npz')
    np.savez(path, **data)
    cfg = config(env_name, horizon)
    caught = []
    real = evaluation.evaluate

    def capture(*a, **k):
        caught.append(real(*a, **k))
        return caught[-1]

    monkeypatch.setattr(evaluation, 'evaluate', capture)  # calibrate_then_evaluate's evaluation (the last call)
    run_dir = os.path.join(tmp, 'run')
    run.run_stepwise(cfg, run_dir, dataset=path, log=lambda *_: None)
    stepwise = caught[-1]
    argv = ['evaluate', '--checkpoint', os.path.join(run_dir, 'train'), '--dataset', path, '--tasks', '1', '2',
            '--horizon', str(horizon), '--ablations', 'no-pruning', 'flat', '--seed', str(SEED), '--split', 'dev',
            '--out', os.path.join(tmp, 'ev')]
    assert cli.main(argv) == 0  # the ci preset from the checkpoint, these options on top
    command = caught[-1]
    kp_stepwise = json.load(open(os.path.join(run_dir, 'summary.json')))['keypoints']
    kp_command = json.load(open(os.path.join(tmp, 'ev', 'results.json')))['keypoints']
    program = pipeline.make_run(cfg, envs.make(env_name))
    one = jax.device_get(jax.jit(program)(jax.random.PRNGKey(SEED), ds_io.to_device(data)))
    as_lists = lambda s, p, k: dict(success=np.asarray(s).astype(int).tolist(), pruned=np.asarray(p).tolist(),  # noqa: E731
                                    keypoints=int(k))
    return dict(stepwise=as_lists(stepwise.success, stepwise.pruned, kp_stepwise),
                evaluate=as_lists(command.success, command.pruned, kp_command),
                one_program=as_lists(one['episode_success'], one['pruned'], one['keypoints']))


@pytest.mark.parametrize('env_name', [
    'pointmaze-medium',
    pytest.param('antmaze-medium', marks=pytest.mark.slow),  # minutes of MJX compiles and ant steps
])
def test_same_seeds_give_the_recorded_values(env_name, tmp_path, monkeypatch):
    got = run_three_paths(env_name, str(tmp_path), monkeypatch)
    want = RECORDED[env_name]
    for path in ('stepwise', 'one_program'):
        assert got[path] == {k: want[path][k] for k in ('success', 'pruned', 'keypoints')}, path
    # the evaluate command's intended change: its seed is split like the run's, so it equals the run
    assert got['evaluate'] == got['stepwise']
    assert got['evaluate'] == {k: want['evaluate_after_key_split'][k] for k in ('success', 'pruned', 'keypoints')}
    assert sum(want['stepwise']['pruned']) > 0  # kappa 0 overruns budgets: the values cover pruning


ORACLE_ROWS = ('no-pruning', 'paper=0.25', 'stall=40')


# the oracle per maze: its speed (m per control step), episode length and physics
ORACLE = {'pointmaze-medium': dict(speed=0.15, horizon=400, backend='mjx'),
          'antmaze-medium': dict(speed=0.12, horizon=1000, backend='ogbench')}  # the ant in plain MuJoCo: fast on CPU


def oracle_case(env_name: str = 'pointmaze-medium') -> dict:
    """Per-episode success, legs cut and edges removed of the oracle agent (no learning) on
    ``env_name``: the unchanged maze, close-3-3 and close-5-3 (task 4's route), 5 tasks x 2
    dev episodes of PRNGKey(SEED); the AQM row at the oracle's kappa 0.25 with parallel cuts 0.6."""
    base = mazes.layout('medium')
    closed = base.copy()
    closed[5, 3] = 1
    env = envs.make(env_name)
    o = ORACLE[env_name]
    agent, graph, match = oracle.oracle_agent(env, base, delta=4.0, speed=o['speed'])
    proto = protocol.ProtocolConfig(episodes=2, horizon=o['horizon'], ablations=ORACLE_ROWS, split='dev', envs=256,
                                    backend=o['backend'])
    variants = {'base': base, 'close-3-3': shifts.variant('medium', 'close-3-3'), 'close-5-3': closed}
    res = evaluation.evaluate(env, agent, graph, AgentConfig(**match, cut_slack=0.6), proto, variants,
                              key=jax.random.PRNGKey(SEED), progress=False)
    return dict(agents=res.agents, success=res.success.astype(int).tolist(), pruned=res.pruned.tolist(),
                removed=res.removed.tolist(), keypoints=int(graph.mask.sum()))


@pytest.mark.parametrize('env_name', [
    'pointmaze-medium',
    'antmaze-medium',  # 120 ant episodes (the scripted trot) in OGBench's MuJoCo: 40 s
])
def test_the_oracle_agent_gives_the_recorded_values_and_reaches_goals(env_name):
    got = oracle_case(env_name)
    want = RECORDED[f'oracle-{env_name}']
    assert got == want
    success, pruned = np.asarray(got['success']), np.asarray(got['pruned'])
    n = len(success) // len(got['agents'])  # episodes per row: 3 layouts x 5 tasks x 2
    assert success.sum() >= 0.5 * len(success) and pruned.sum() > 0  # goals reached, edges cut
    assert pruned[n:2 * n].sum() == 0  # the no-pruning row never cuts
