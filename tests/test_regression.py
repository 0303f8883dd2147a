"""Regression: per-episode success, prunes and keypoint counts of the three ways to run AQM.

Recorded at a small fixed configuration (tiny preset, 100 updates, 2 tasks x 2 episodes, kappa 0 so
that budgets are overrun) before the package was split into stage packages; the same seeds must give
the same values afterwards. ``tests/regression_values.json`` holds them; change an entry only where a
change of behaviour is intended, and say so in the commit.
"""

import json
import os

import jax
import numpy as np
import pytest

from aqm_mjx import cli, envs, evaluate, pipeline, synthetic, train
from aqm_mjx import dataset as ds_io

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


def run_three_paths(env_name, tmp):
    make_data, steps = CASES[env_name]
    data = make_data()
    path = os.path.join(tmp, f'{env_name}-navigate.npz')
    np.savez(path, **data)
    tcfg = train.TrainConfig.preset('tiny', env=env_name, steps=100, updates_per_call=50, log_every=50,
                                    checkpoint_every=50, seed=SEED)
    ecfg = evaluate.EvalConfig(episodes=2, tasks=(1, 2), steps=steps, delta=0.5, max_keypoints=32, candidates=400,
                               switch_radius=0.6, kappa=0.0, ablations=('no-pruning', 'flat'), envs=64, seed=SEED)
    cfg = pipeline.RunConfig(train=tcfg, eval=ecfg)
    caught = []
    orig = evaluate.evaluate

    def capture(*a, **k):
        caught.append(orig(*a, **k))
        return caught[-1]

    evaluate.evaluate = capture
    try:
        run_dir = os.path.join(tmp, 'run')
        pipeline.run_stepwise(cfg, env_name, run_dir, dataset=path, seed=SEED, log=lambda *_: None)
        stepwise = caught[-1]
        argv = ['evaluate', '--checkpoint', os.path.join(run_dir, 'train'), '--dataset', path, '--episodes', '2',
                '--tasks', '1', '2', '--steps', str(steps), '--delta', '0.5', '--max-keypoints', '32',
                '--candidates', '400', '--switch-radius', '0.6', '--kappa', '0', '--ablations', 'no-pruning', 'flat',
                '--envs', '64', '--seed', str(SEED), '--out', os.path.join(tmp, 'ev')]
        assert cli.main(argv) == 0
        command = caught[-1]
    finally:
        evaluate.evaluate = orig
    kp_stepwise = json.load(open(os.path.join(run_dir, 'summary.json')))['keypoints']
    kp_command = json.load(open(os.path.join(tmp, 'ev', 'results.json')))['keypoints']
    run = pipeline.make_run(cfg, envs.make(env_name))
    one = jax.device_get(jax.jit(run)(jax.random.PRNGKey(SEED), ds_io.to_device(data)))
    as_lists = lambda s, p, k: dict(success=np.asarray(s).astype(int).tolist(), pruned=np.asarray(p).tolist(),  # noqa: E731
                                    keypoints=int(k))
    return dict(stepwise=as_lists(stepwise.success, stepwise.pruned, kp_stepwise),
                evaluate=as_lists(command.success, command.pruned, kp_command),
                one_program=as_lists(one['episode_success'], one['pruned'], one['keypoints']))


@pytest.mark.parametrize('env_name', [
    'pointmaze-medium',
    pytest.param('antmaze-medium', marks=pytest.mark.slow),  # about 4 minutes of MJX compiles and ant steps
])
def test_same_seeds_give_the_recorded_values(env_name, tmp_path):
    got = run_three_paths(env_name, str(tmp_path))
    want = RECORDED[env_name]
    for path in ('stepwise', 'evaluate', 'one_program'):
        assert got[path] == {k: want[path][k] for k in ('success', 'pruned', 'keypoints')}, path
    assert sum(want['stepwise']['pruned']) > 0  # kappa 0 overruns budgets: the values cover pruning
