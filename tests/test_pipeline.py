"""The whole run as one jitted program equals the step-by-step path; seeds vmap in one compile."""

import dataclasses
import json

import jax
import numpy as np
import pytest

from aqm_mjx import envs, pipeline
from aqm_mjx.agent import rules
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.data import synthetic
from aqm_mjx.evaluation import evaluate, protocol
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import build_map


def assert_params_close(a, b):
    """Float tolerance for Adam-trained parameters: Adam turns gradient noise near zero into steps of
    the learning rate (1e-4 to 3e-4), so elementwise within a few steps, and close overall."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    for x, y in zip(la, lb):
        np.testing.assert_allclose(x, y, rtol=1e-3, atol=1e-3)
    diff = np.sqrt(sum(float(np.sum((np.asarray(x) - np.asarray(y)) ** 2)) for x, y in zip(la, lb)))
    norm = np.sqrt(sum(float(np.sum(np.asarray(y) ** 2)) for y in lb))
    assert diff <= 1e-4 * norm, (diff, norm)


def tiny_config():
    # the ci preset with a switch radius that the start states fall within; the AQM row's kappa is
    # calibrated at a 50% false-alarm rate (the median of steps / d, minus 1), so budgets are overrun,
    # edges pruned, and both paths calibrate
    return pipeline.RunConfig.preset('ci', env='pointmaze-medium').with_overrides(
        ['train.steps=100', 'train.updates_per_call=50', 'train.log_every=50', 'train.checkpoint_every=50',
         'protocol.tasks=1,2', 'protocol.ablations=flat,paper=cal', 'protocol.calibrate=fixed',
         'protocol.false_alarm=0.5',
         'protocol.calibration_episodes=3'])


@pytest.fixture(scope='module')
def one_program():
    """``(cfg, env, data, ds, run, single)``: the tiny run and its jitted program, compiled once for
    the tests of this module that call it unvmapped."""
    cfg = tiny_config()
    env = envs.make('pointmaze-medium')
    data = synthetic.point_walks()
    run = pipeline.make_run(cfg, env)
    return cfg, env, data, ds_io.to_device(data), run, jax.jit(run)


@pytest.mark.slow  # 3 minutes; the default tier checks all three paths against recorded values (test_regression.py)
def test_one_program_equals_the_step_by_step_path(tmp_path, one_program):
    cfg, env, data, ds, run, single = one_program
    key = jax.random.PRNGKey(3)
    out = jax.device_get(single(key, ds))
    # step by step: the host training loop with its checkpoints, then the map, then the chunked evaluation
    k_train, k_map, k_eval = pipeline.stage_keys(key)
    trained = fit.train('aqm', cfg.train, data, str(tmp_path / 'run'), key=k_train, progress=False,
                        log=lambda *_: None)
    loaded = fit.load(str(tmp_path / 'run'), log=lambda *_: None)  # what is on disk is what was in memory
    for x, y in zip(jax.tree.leaves(trained.state), jax.tree.leaves(loaded.state)):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
    agent = loaded.agent
    graph, kp = build_map(agent, ds.observations, cfg.map, k_map)
    # the calibration by hand: the no-pruning agent on its own episodes (cells no task uses), median of steps / d
    cal_eps = protocol.calibration_episodes(env, cfg.protocol)
    cal_res = evaluate.evaluate(env, agent, graph, dataclasses.replace(cfg.agent, kappa=np.inf),
                                protocol.calibration_protocol(cfg.protocol), progress=False,
                                key=jax.random.fold_in(k_eval, protocol.CALIBRATION_FOLD), episodes=cal_eps)
    n_cal = cfg.protocol.calibration_episodes
    assert len(cal_res.table.task) == n_cal and cal_res.agents == ['aqm'] and cal_res.pruned.sum() == 0
    legs = cal_res.legs.reshape(-1, cal_res.legs.shape[-1])
    legs = legs[(legs[:, 1] >= 0) & (legs[:, 0] > 0)]
    kappa = max(round(float(np.quantile(legs[:, 1] / legs[:, 0], 0.5)) - 1, 2), 0.0)
    cal = evaluate.calibration_pass(env, agent, graph, cfg.agent, cfg.protocol, k_eval, progress=False)
    assert cal['calibrated'] and cal['legs'] == len(legs) >= 2 and cal['patience'] == 0
    assert cal['kappa'] == pytest.approx(kappa, abs=1e-6)
    assert float(out['calibration']['kappa']) == pytest.approx(kappa, abs=1e-6)
    assert int(out['calibration']['legs']) == len(legs)
    # the paper=cal row: the kappa of the keypoint edges alone, on both paths
    edges = legs[legs[:, 3] == rules.LEG_EDGE]
    kappa_edges = (max(round(float(np.quantile(edges[:, 1] / edges[:, 0], 0.5)) - 1, 2), 0.0) if len(edges)
                   else cfg.agent.kappa)
    assert cal['kappa_edges'] == pytest.approx(kappa_edges, abs=1e-6) == float(out['calibration']['kappa_edges'])
    res = evaluate.evaluate(env, agent, graph, dataclasses.replace(cfg.agent, kappa=cal['kappa']),
                            cfg.with_overrides(['protocol.envs=5']).protocol, progress=False, key=k_eval,
                            budgets=cal['budgets'])
    assert res.agents == ['aqm', 'flat', 'paper=cal']
    assert int(out['keypoints']) == int(kp.count) >= 2
    assert_params_close(out['params'], trained.params)
    np.testing.assert_array_equal(out['episode_success'], res.success)
    np.testing.assert_array_equal(out['pruned'], res.pruned)
    assert out['pruned'].sum() > 0  # the median kappa: budgets overrun, so the comparison covers pruning
    assert pipeline.summary(run, out) == {a: {v: {k: r for k, r in row.items() if k != 'pruned_mean'}
                                              for v, row in rows.items()} for a, rows in res.summary.items()}
    assert set(out['metrics']) >= {'qrl/loss', 'policy/main_loss'}


@pytest.mark.slow  # 1.5 minutes; the default tier checks vmapped training seeds (test_compare.py)
def test_seeds_vmap_in_one_compile_and_match_separate_calls(one_program):
    _, _, _, ds, run, single = one_program
    traces = []

    def counted(k, d):
        traces.append(1)
        return run(k, d)

    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    many = jax.device_get(jax.jit(jax.vmap(counted, in_axes=(0, None)))(keys, ds))
    assert len(traces) == 1
    for i in range(2):
        one = jax.device_get(single(keys[i], ds))
        assert int(many['keypoints'][i]) == int(one['keypoints'])
        np.testing.assert_array_equal(many['episode_success'][i], one['episode_success'])
        np.testing.assert_array_equal(many['pruned'][i], one['pruned'])
        assert_params_close(jax.tree.map(lambda x: x[i], many['params']), one['params'])
    # different seeds give different models
    assert not np.allclose(jax.tree.leaves(many['params'])[0][0], jax.tree.leaves(many['params'])[0][1])


RUN_ARGV = ['run', '--env', 'pointmaze-medium', '--preset', 'ci', '--set', 'steps=100', '--set',
            'train.checkpoint_every=50', '--episodes', '1', '--horizon', '40', '--set', 'protocol.curve_episodes=1']


def interrupted_then_resumed_run(tmp_path, capsys, monkeypatch):
    """`aqm-mjx run` stopped by Ctrl-C right after its first checkpoint, then the same command again.
    Returns (argv, out folder, the second call's stdout)."""
    from aqm_mjx import cli  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import checkpoint as ckpt  # pylint: disable=import-outside-toplevel

    path = tmp_path / 'pointmaze-medium-navigate.npz'
    np.savez(path, **synthetic.point_walks())
    out = tmp_path / 'run'
    argv = RUN_ARGV + ['--dataset', str(path), '--out', str(out)]
    # Ctrl-C right after the first checkpoint (step 50): exit 130, a message, nothing evaluated yet
    save = ckpt.Checkpointer.save

    def save_then_interrupt(self, step, state, config):
        save(self, step, state, config)
        raise KeyboardInterrupt

    monkeypatch.setattr(ckpt.Checkpointer, 'save', save_then_interrupt)
    assert cli.main(argv) == 130
    assert 'interrupted' in capsys.readouterr().err and not (out / 'summary.json').exists()
    monkeypatch.setattr(ckpt.Checkpointer, 'save', save)
    # the same command again resumes at step 50 and finishes
    assert cli.main(argv) == 0
    return argv, out, capsys.readouterr().out


def test_run_command_resumes_after_an_interrupt(tmp_path, capsys, monkeypatch):
    _, out, first = interrupted_then_resumed_run(tmp_path, capsys, monkeypatch)
    assert 'resuming aqm ci preset' in first and 'mean success' in first
    lines = [json.loads(line) for line in (out / 'train' / 'metrics.jsonl').read_text().splitlines()]
    # one line per log_every, none repeated: it went on from 50; the learning curve's point at the
    # checkpoint it reached (the one at 50 was cut off by the interrupt), 1 episode of each of 5 tasks
    assert [ln['step'] for ln in lines] == [50, 100, 100]
    assert lines[-1]['eval/episodes'] == 5 and lines[-1]['eval/success'] in (0, 0.2, 0.4, 0.6, 0.8, 1.0)
    assert (out / 'train' / 'curves.png').exists()
    summary = json.loads((out / 'summary.json').read_text())
    assert str(out / 'train' / 'curves.png') in summary['pictures']
    assert set(summary['success']) == {'aqm', 'no-pruning', 'flat'} and summary['keypoints'] >= 1
    assert (out / 'eval' / 'trajectories.png').exists()
    # the run's config is saved beside it and reads back equal
    saved = pipeline.RunConfig.from_dict(json.loads((out / 'run.json').read_text()))
    assert saved.train.steps == 100 and saved.protocol.horizon == 40 and saved.map.delta == 0.5


@pytest.mark.slow  # two more evaluations and a whole-run compile (2-3 minutes); the one program itself is
# checked in CI by test_one_program_equals_the_step_by_step_path and the seed vmap test above
def test_run_command_reruns_without_training_and_runs_as_one_program(tmp_path, capsys, monkeypatch):
    from aqm_mjx import cli  # pylint: disable=import-outside-toplevel

    argv, out, _ = interrupted_then_resumed_run(tmp_path, capsys, monkeypatch)
    # re-running finds the finished training and does not train again
    assert cli.main(argv) == 0
    assert 'is complete at step 100' in capsys.readouterr().out
    assert cli.main(argv + ['--one-program', '--seeds', '2']) == 0
    res = json.loads((out / 'one_program.json').read_text())
    assert len(res['success']) == 2 and len(res['keypoints']) == 2


SHARD_SEEDS = r'''
import os, sys
import jax, numpy as np
sys.path.insert(0, os.path.dirname(sys.argv[1]))
from test_pipeline import tiny_config
from aqm_mjx import envs, pipeline, run as host
from aqm_mjx.data import dataset as ds_io, synthetic
from aqm_mjx.evaluation import evaluate, protocol
assert jax.device_count() == 2
run = pipeline.make_run(tiny_config(), envs.make('pointmaze-medium'))
ds = ds_io.to_device(synthetic.point_walks())
keys = jax.random.split(jax.random.PRNGKey(0), 2)
program = jax.jit(jax.vmap(run, in_axes=(0, None)))
outs = {}
for n in (1, 2):
    k = host.shard_seeds(keys, evaluate.device_mesh(jax.devices()[:n]))
    assert len(k.sharding.device_set) == n
    outs[n] = jax.device_get(program(k, ds))
for name in ('episode_success', 'pruned', 'keypoints', 'success'):
    assert np.array_equal(outs[1][name], outs[2][name]), name
print('same', outs[1]['keypoints'].tolist())
'''


@pytest.mark.slow  # 80 s: the environment-axis version runs in CI (test_evaluate.py)
def test_seed_axis_shards_over_two_devices(two_device_python):
    assert 'same' in two_device_python(SHARD_SEEDS, __file__)
