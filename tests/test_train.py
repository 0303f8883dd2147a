"""Policies by hand, the training config, calibration on a directed grid, Orbax resume."""

import json
import math
import os
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import spearmanr

from aqm_mjx import cli
from aqm_mjx.data import dataset as dsm
from aqm_mjx.data import synthetic
from aqm_mjx.learn import aqm, fit, policy


# ----------------------------------------------------------------------------------- objectives
def test_log_prob_and_kl_by_hand():
    mean, log_std, a = jnp.array([0.5, -1.0]), jnp.array([0.0, math.log(2.0)]), jnp.array([1.0, 1.0])
    want = (-0.5 * 0.25 - 0.5 * math.log(2 * math.pi)) + (-0.5 * 1.0 - math.log(2.0) - 0.5 * math.log(2 * math.pi))
    assert float(policy.log_prob(mean, log_std, a)) == pytest.approx(want, rel=1e-6)
    # unit std: KL = |mu_p - mu_q|^2 / 2
    assert float(policy.kl(jnp.array([1.0, 2.0]), jnp.zeros(2), jnp.array([0.0, 0.0]), jnp.zeros(2))) == pytest.approx(2.5)
    # KL(N(0, 1) || N(0, 2^2)) = log 2 + 1/8 - 1/2
    assert float(policy.kl(jnp.zeros(1), jnp.zeros(1), jnp.zeros(1), jnp.log(jnp.full(1, 2.0)))) == pytest.approx(
        math.log(2) + 0.125 - 0.5, rel=1e-6)


def test_direction_conditioning():
    obs, goal = jnp.array([[1.0, 1.0, 7.0]]), jnp.array([[4.0, 5.0, -3.0]])
    np.testing.assert_allclose(policy.goal_input(obs, goal, 'direction'), [[0.6, 0.8]], atol=1e-6)
    np.testing.assert_array_equal(policy.goal_input(obs, goal, 'goal'), goal)
    with pytest.raises(ValueError, match='conditioning'):
        policy.goal_input(obs, goal, 'polar')
    # egocentric: the goal, then the unit direction in the torso frame; a 3-d observation has no quaternion
    np.testing.assert_allclose(policy.goal_input(obs, goal, 'egocentric'), [[4.0, 5.0, -3.0, 0.6, 0.8]], atol=1e-6)
    assert policy.goal_input_size(3, 'egocentric') == 5 and policy.goal_input_size(29, 'direction') == 2


def test_egocentric_direction_turns_with_the_torso_yaw():
    # ant observations: x, y, z, quaternion (w, x, y, z) about the vertical for yaw psi, 22 more numbers
    psi = np.array([0.0, np.pi / 2, np.pi, -np.pi / 4])
    obs = np.zeros((4, 29), np.float32)
    obs[:, 3], obs[:, 6] = np.cos(psi / 2), np.sin(psi / 2)
    goal = obs.copy()
    goal[:, 0] = 3.0  # straight along world +x, 3 m away
    got = np.asarray(policy.goal_input(jnp.asarray(obs), jnp.asarray(goal), 'egocentric'))
    np.testing.assert_array_equal(got[:, :29], goal)
    # world +x seen from a torso turned by psi is (cos psi, -sin psi)
    np.testing.assert_allclose(got[:, 29:], np.stack([np.cos(psi), -np.sin(psi)], -1), atol=1e-6)


# ---------------------------------------------------------------------------------------- config
def test_config_presets_validation_and_json():
    paper = aqm.AQMConfig.preset('paper', env='antmaze-large')
    assert (paper.q_hidden, paper.n_components, paper.component_size, paper.batch_size, paper.steps) == (
        (512, 512, 512), 512, 1, 1024, 1_000_000)
    assert (paper.lr_quasimetric, paper.lr_policy, paper.lr_lambda, paper.lambda_init, paper.temperature) == (
        1e-4, 3e-4, 1e-2, 1.0, 3.0)
    assert paper.offset == 125.0 and aqm.AQMConfig.preset('cpu', env='antmaze-giant').offset == 250.0
    assert aqm.AQMConfig.preset('cpu', qrl='ogbench').offset == 500.0
    assert paper.conditioning == 'goal' and aqm.AQMConfig.preset('cpu').conditioning == 'egocentric'
    assert aqm.AQMConfig.preset('cpu').lr_quasimetric == 3e-4
    cfg = aqm.AQMConfig.preset('cpu').with_overrides(['batch_size=64', 'q_hidden=64,32', 'objective=bc',
                                                          'push_offset=30'])
    assert (cfg.batch_size, cfg.q_hidden, cfg.objective, cfg.offset) == (64, (64, 32), 'bc', 30.0)
    assert aqm.AQMConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    for bad, msg in ((dict(objective='ppo'), 'objective: unknown value'), (dict(steps=1001), 'multiple of updates_per_call'),
                     (dict(conditioning='polar'), 'conditioning: unknown value'), (dict(lr_policy=-1.0), 'lr_policy'),
                     (dict(env='antmaze-huge'), 'unknown environment'), (dict(env=None), 'push_offset')):
        with pytest.raises(ValueError, match=msg):
            aqm.AQMConfig.preset('cpu', **bad)
    with pytest.raises(ValueError, match='unknown preset'):
        aqm.AQMConfig.preset('gpu')
    with pytest.raises(ValueError, match="unknown AQMConfig field 'learning_rate'"):
        cfg.with_overrides(['learning_rate=1'])
    with pytest.raises(ValueError, match=r'AQMConfig.batch_size \(int\): cannot read'):
        cfg.with_overrides(['batch_size=abc'])


def test_saved_configs_without_new_fields_keep_their_old_behaviour():
    """Today's defaults are SAW's subgoal cap and OGBench's initialiser; a config saved before those
    fields existed reads back as what its run was trained with (end cap, flax's init)."""
    new = aqm.AQMConfig.preset('cpu', env='antmaze-medium')
    assert (new.subgoal_cap, new.initializer) == ('goal', 'ogbench')
    assert (new.goal_sampling.subgoal_cap, new.goal_sampling.subgoal_offset) == ('goal', 25)
    old = {k: v for k, v in new.to_dict().items() if k not in ('subgoal_cap', 'initializer')}
    assert (aqm.AQMConfig.from_dict(old).subgoal_cap, aqm.AQMConfig.from_dict(old).initializer) == ('end', 'lecun')
    assert aqm.AQMConfig.from_dict(new.to_dict()) == new
    assert aqm.AQMConfig.preset('cpu', policy_goals='random', subgoal_cap='end').goal_sampling.subgoal_cap == 'end'
    with pytest.raises(ValueError, match='initializer: unknown value'):
        aqm.AQMConfig.preset('cpu', initializer='xavier')
    # push pairs: a config saved before the field pushed towards B more sampled states
    assert new.push_pairs == 'rolled'
    old = {k: v for k, v in new.to_dict().items() if k != 'push_pairs'}
    assert aqm.AQMConfig.from_dict(old).push_pairs == 'sampled'
    with pytest.raises(ValueError, match='push_pairs: unknown value'):
        aqm.AQMConfig.preset('cpu', push_pairs='shuffled')


@pytest.mark.parametrize('initializer', ['ogbench', 'lecun'])
def test_initializers_have_the_variance_they_name(initializer):
    """'ogbench': kernels uniform on +-sqrt(3 s / fan_avg), s = 1 (1e-2 for the policy's mean layer);
    'lecun': std 1 / sqrt(fan_in); biases 0. Checked on every Dense kernel of an AQM state."""
    cfg = aqm.AQMConfig.preset('ci', env='antmaze-medium', q_hidden=(256, 256), n_components=256,
                               pi_hidden=(256, 256), initializer=initializer)
    state = aqm.make(cfg, obs_size=29, action_size=8).init(jax.random.PRNGKey(0))
    layers = [('q', k, v) for k, v in state.q_params['params']['encoder'].items() if k.startswith('Dense')] + \
        [('pi', k, v) for k, v in state.pi_params['main']['params'].items()]
    for net, name, p in layers:
        w = np.asarray(p['kernel'])
        fan_in, fan_out = w.shape
        assert np.all(np.asarray(p['bias']) == 0)
        if initializer == 'ogbench':
            scale = 1e-2 if (net, name) == ('pi', 'Dense_2') else 1.0
            bound = np.sqrt(3 * scale / ((fan_in + fan_out) / 2))
            assert np.abs(w).max() <= bound * (1 + 1e-6) and np.abs(w).max() > 0.95 * bound, (net, name)
            want = bound / np.sqrt(3)
        else:
            want = 1 / np.sqrt(fan_in)
        assert abs(w.std() / want - 1) < 0.1, (net, name, w.std(), want)


@pytest.mark.parametrize('pairs', ['rolled', 'sampled'])
def test_push_term_reaches_the_states_its_pairing_names(pairs):
    """The update's mean d(s, g) of the push term, recomputed from the same keys: 'rolled' pairs row i's
    s with row i - 1's s', 'sampled' with B states drawn with the update's third key."""
    from aqm_mjx.data import goals
    from aqm_mjx.learn.quasimetric import IQE
    rng = np.random.default_rng(0)
    term = np.zeros(400, bool)
    term[99::100] = True
    ds = dsm.to_device(dict(observations=rng.normal(size=(400, 5)).astype(np.float32),
                            actions=rng.uniform(-1, 1, (400, 2)).astype(np.float32), terminals=term))
    cfg = aqm.AQMConfig.preset('ci', env=None, push_offset=30.0, batch_size=16, push_pairs=pairs)
    learner = aqm.make(cfg, obs_size=5, action_size=2)
    state = learner.init(jax.random.PRNGKey(3))
    _, m = jax.jit(learner.update)(state, ds)
    _, k_batch, k_rand = jax.random.split(state.key, 3)
    batch = goals.sample(ds, k_batch, 16, cfg.goal_sampling)
    iqe = learner.modules['quasimetric']
    zs, zs1 = (iqe.apply(state.q_params, x, method=IQE.encode) for x in (batch.observations, batch.next_observations))
    if pairs == 'rolled':
        zg = np.concatenate([zs1[-1:], zs1[:-1]])
    else:
        zg = iqe.apply(state.q_params, ds.observations[jax.random.randint(k_rand, (16,), 0, 400)], method=IQE.encode)
    d = np.asarray(iqe.apply(state.q_params, zs, zg, method=IQE.distance))
    assert d.shape == (16,)
    np.testing.assert_allclose(float(m['qrl/d_goal_mean']), d.mean(), rtol=1e-5)
    # the transitions' own pairs give another mean (the test tells the pairings apart)
    other = np.asarray(iqe.apply(state.q_params, zs, zs1, method=IQE.distance)).mean()
    assert abs(other - d.mean()) > 1e-3


def test_infer_env():
    assert dsm.infer_env('/data/antmaze-large-navigate-v0.npz') == ('antmaze-large', 'navigate')
    assert dsm.infer_env('pointmaze-medium-explore.npz') == ('pointmaze-medium', 'explore')
    with pytest.raises(ValueError, match='pass --env'):
        dsm.infer_env('my_data.npz')


# ----------------------------------------------------------------------------------- calibration
def _grid_config(**kw):
    base = dict(env=None, push_offset=30.0, push_scale=0.1, steps=6000, batch_size=256, updates_per_call=500,
                log_every=500, checkpoint_every=500, q_hidden=(64, 64), n_components=64, pi_hidden=(32,),
                lr_quasimetric=1e-3, subgoal_offset=3)
    return aqm.AQMConfig.preset('ci', **{**base, **kw})


def test_quasimetric_calibrates_on_a_directed_grid(one_way_grid_walks):
    data, truth = one_way_grid_walks
    learner = aqm.make(_grid_config(), obs_size=2, action_size=2)
    state, m = jax.jit(lambda k, d: fit.train_scan(learner, k, d))(jax.random.PRNGKey(0), dsm.to_device(data))
    cells = np.array([(x, y) for x in range(5) for y in range(5)], np.float32)
    d = np.asarray(jax.jit(learner.modules['quasimetric'].apply)(state.q_params, cells[:, None], cells[None]))
    off = ~np.eye(25, dtype=bool)
    rho = spearmanr(d[off], truth[off]).correlation
    assert rho >= 0.9, rho
    # asymmetric where the graph is: (2, 0) -> (3, 0) is one step, the way back a 9-step detour
    a, b = 2 * 5 + 0, 3 * 5 + 0
    assert truth[a, b] == 1 and truth[b, a] == 9
    assert d[b, a] > 3 * d[a, b], (d[a, b], d[b, a])
    assert float(m['qrl/lambda']) >= 0


# ----------------------------------------------------------------------------------- checkpoints
def _write_grid_dataset(tmp_path):
    data = synthetic.grid_walks(synthetic.one_way_grid(5), episodes=50, steps=20, seed=1)
    path = str(tmp_path / 'grid.npz')
    dsm.write_ogbench(path, {k: data[k] for k in ('observations', 'actions', 'terminals')})
    return path


def _train_cmd(dataset, out, steps, *extra):
    return [sys.executable, '-m', 'aqm_mjx.cli', 'train', '--dataset', dataset, '--env', 'pointmaze-medium', '--preset',
            'ci', '--set', 'checkpoint_every=50', '--set', 'updates_per_call=50', '--set', 'log_every=50',
            '--set', 'keep=20', '--steps', str(steps), '--out', out, *extra]


def _params(run):
    t = fit.load(run, log=lambda *_: None)
    return t.step, jax.tree.leaves(t.state)


def test_resume_after_kill_is_bit_identical(tmp_path):
    dataset = _write_grid_dataset(tmp_path)
    env = dict(os.environ, JAX_PLATFORMS='cpu')
    ref, cut = str(tmp_path / 'ref'), str(tmp_path / 'cut')
    subprocess.run(_train_cmd(dataset, ref, 300), check=True, env=env, capture_output=True)
    proc = subprocess.Popen(_train_cmd(dataset, cut, 10 ** 7), env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    ckdir = os.path.join(cut, 'checkpoints')
    deadline = time.time() + 300
    while time.time() < deadline:
        done = [s for s in (os.listdir(ckdir) if os.path.isdir(ckdir) else []) if s.isdigit()]
        if done:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    steps_at_kill = sorted(int(s) for s in os.listdir(ckdir) if s.isdigit())
    assert steps_at_kill and steps_at_kill[-1] < 300
    subprocess.run(_train_cmd(dataset, cut, 300, '--resume'), check=True, env=env, capture_output=True)
    s_ref, leaves_ref = _params(ref)
    s_cut, leaves_cut = _params(cut)
    assert s_ref == s_cut == 300
    assert len(leaves_ref) == len(leaves_cut)
    for x, y in zip(leaves_ref, leaves_cut):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
    steps_logged = [json.loads(ln)['step'] for ln in open(os.path.join(cut, 'metrics.jsonl'))]
    assert steps_logged == sorted(set(steps_logged)) and steps_logged[-1] == 300  # no duplicate lines


def test_unreadable_newest_checkpoint_falls_back(tmp_path, capsys):
    dataset = _write_grid_dataset(tmp_path)
    out = str(tmp_path / 'run')
    assert cli.main(['train', '--dataset', dataset, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', out]) == 0
    ck = os.path.join(out, 'checkpoints')
    assert sorted(int(s) for s in os.listdir(ck) if s.isdigit()) == [100, 200]
    # corrupt every file of the newest checkpoint
    for root, _, files in os.walk(os.path.join(ck, '200')):
        for f in files:
            with open(os.path.join(root, f), 'wb') as fh:
                fh.write(b'garbage')
    logs = []
    t = fit.load(out, log=logs.append)
    assert t.step == 100 and len(logs) == 1 and logs[0].startswith('warning: checkpoint 200')
    assert os.path.isdir(os.path.join(ck, '200'))  # a reader leaves the folder as it is
    agent = t.agent
    a = jax.vmap(lambda o, g: agent.controller(agent.aux, o, g, 0, None))(jnp.zeros((3, 2)), jnp.ones((3, 2)))
    assert a.shape == (3, 2)
    # a new run refuses to write over it; a bad dataset is named
    assert cli.main(['train', '--dataset', dataset, '--env', 'pointmaze-medium', '--preset', 'ci', '--out', out]) == 2
    assert '--resume' in capsys.readouterr().err
    assert cli.main(['train', '--dataset', dataset, '--env', 'antmaze-medium', '--out', str(tmp_path / 'r2')]) == 2
    assert 'observations are 2-d but the environment expects 29' in capsys.readouterr().err


_DATA_PARALLEL = '''
import jax, numpy as np
from aqm_mjx.data import dataset as dsm
from aqm_mjx.learn import fit, methods
assert jax.device_count() == 2
rng = np.random.default_rng(0)
term = np.zeros(2000, bool); term[99::100] = True
ds = dsm.to_device(dict(observations=rng.normal(size=(2000, 29)).astype(np.float32),
                        actions=rng.uniform(-1, 1, (2000, 8)).astype(np.float32), terminals=term))
for name in ('aqm', 'gcivl'):
    entry = methods.get(name)
    cfg = entry.preset('ci', env='antmaze-medium')
    learner = entry.make(cfg, 29, 8)
    step_fn = fit.chunk_step(learner.update, 20)
    one, m1 = jax.jit(step_fn)(learner.init(jax.random.PRNGKey(0)), ds)
    chunk, state, dsr = fit._data_parallel(step_fn, learner.init(jax.random.PRNGKey(0)), ds)
    rep = jax.tree.leaves(state)[0].sharding  # replicated on the mesh over both devices
    with jax.set_mesh(rep.mesh):
        text = jax.jit(step_fn, in_shardings=(rep, rep)).lower(state, dsr).compile().as_text()
    two, m2 = chunk(state, dsr)
    loss = [k for k in m1 if k.endswith('loss')][0]
    print(name, len(jax.tree.leaves(two)[0].sharding.device_set), text.count('all-reduce') > 0,
          float(abs(m1[loss] - m2[loss]) / abs(m1[loss])), flush=True)
'''


def test_a_data_parallel_update_splits_the_batch_and_keeps_the_numbers(two_device_python):
    """What several processes run for one training run (``fit._data_parallel``), on two devices of one
    process: the state replicated on both, each batch split over them (``goals.spread``), the gradients
    summed across them (an all-reduce in the compiled chunk), and the losses those of one device to
    float rounding, for AQM and a baseline."""
    out = two_device_python(_DATA_PARALLEL, __file__)
    rows = {ln.split()[0]: ln.split()[1:] for ln in out.strip().splitlines()}
    for name in ('aqm', 'gcivl'):
        devices, reduces, rel = rows[name]
        assert devices == '2' and reduces == 'True', rows[name]
        assert float(rel) < 1e-4, rows[name]
