"""The baselines: losses by hand on tiny inputs, the goal sampler's mixtures against a chi-square
test that a wrong mixture fails, the wiring of HIQL's and SAW's targets, and resume."""

import os

import numpy as np
import jax
import jax.numpy as jnp
import pytest
from scipy import stats

from aqm_mjx.data import dataset as dsm
from aqm_mjx.data import goals, synthetic
from aqm_mjx.learn import fit, losses, methods, networks, policy

BASELINES = ('gcbc', 'gcivl', 'gciql', 'qrl', 'crl', 'hiql', 'saw', 'hilp')  # gas: tests/test_gas_hilp.py (two phases)


# ------------------------------------------------------------------------------- losses by hand
def test_expectile_loss_by_hand():
    adv = jnp.array([1.0, -1.0, 0.0])
    diff = jnp.array([2.0, 3.0, -1.0])
    np.testing.assert_allclose(losses.expectile_loss(adv, diff, 0.9), [0.9 * 4, 0.1 * 9, 0.9 * 1], rtol=1e-6)


def test_ivl_value_loss_uses_the_target_for_the_side_and_the_online_value_for_the_difference():
    # two heads, two transitions; the second is at its goal (reward 0, mask 0)
    v = jnp.array([[-2.0, -0.5], [-3.0, 0.5]])
    v_t = jnp.array([[-2.5, -1.0], [-1.5, 0.0]])
    nv_t = jnp.array([[-1.0, -7.0], [-2.0, -9.0]])
    r, m, gamma, tau = jnp.array([-1.0, 0.0]), jnp.array([1.0, 0.0]), 0.5, 0.9
    loss, info = losses.ivl_value_loss(v, v_t, nv_t, r, m, gamma, tau)
    # by hand: adv = r + gamma m min(nv_t) - mean(v_t)
    adv = np.array([-1 + 0.5 * -2.0 - (-2.0), 0.0 - (-0.5)])  # [0.0, 0.5]: both >= 0 -> weight 0.9
    q1 = np.array([-1 + 0.5 * -1.0, 0.0])  # head 1 targets
    q2 = np.array([-1 + 0.5 * -2.0, 0.0])
    want = np.mean(0.9 * (q1 - [-2.0, -0.5]) ** 2) + np.mean(0.9 * (q2 - [-3.0, 0.5]) ** 2)
    assert adv.tolist() == [0.0, 0.5]
    assert float(loss) == pytest.approx(want, rel=1e-6)
    assert float(info['value/adv_mean']) == pytest.approx(0.25)
    # a negative advantage takes the other side: make transition 1's target mean higher
    loss2, _ = losses.ivl_value_loss(v, v_t.at[:, 0].set(0.0), nv_t, r, m, gamma, tau)
    want2 = np.mean([0.1 * (q1[0] + 2.0) ** 2, 0.9 * (0 + 0.5) ** 2]) + np.mean([0.1 * (q2[0] + 3.0) ** 2,
                                                                                  0.9 * (0 - 0.5) ** 2])
    assert float(loss2) == pytest.approx(want2, rel=1e-6)


def test_iql_value_and_critic_losses_by_hand():
    q_t = jnp.array([[1.0, -2.0], [0.5, -1.0]])  # min over heads: [0.5, -2.0]
    v = jnp.array([0.0, 0.0])
    loss, _ = losses.iql_value_loss(q_t, v, 0.9)
    assert float(loss) == pytest.approx(np.mean([0.9 * 0.25, 0.1 * 4.0]))
    q = jnp.array([[1.0, 2.0], [0.0, 3.0]])
    loss, _ = losses.iql_critic_loss(q, jnp.array([2.0, 4.0]), jnp.array([-1.0, 0.0]), jnp.array([1.0, 0.0]), 0.5)
    target = np.array([-1 + 0.5 * 2.0, 0.0])  # [0, 0]
    assert float(loss) == pytest.approx(np.mean([(1 - 0) ** 2 + (0 - 0) ** 2, (2 - 0) ** 2 + (3 - 0) ** 2]))
    assert target.tolist() == [0.0, 0.0]


def test_ddpgbc_normalises_q_by_its_mean_absolute_value():
    q = jnp.array([[-2.0, -4.0], [-1.0, -6.0]])  # min: [-2, -6], mean -4, mean |q| 4
    logp = jnp.array([-1.0, -3.0])
    loss, info = losses.ddpgbc_actor_loss(q, logp, 0.3)
    assert float(info['actor/q_loss']) == pytest.approx(4.0 / (4.0 + 1e-6))
    assert float(info['actor/bc_loss']) == pytest.approx(0.3 * 2.0)
    assert float(loss) == pytest.approx(4.0 / (4.0 + 1e-6) + 0.6)
    # the normaliser carries no gradient: d loss / d q_i = -1 / (B |q|mean) for the minimum head
    g = jax.grad(lambda qq: losses.ddpgbc_actor_loss(qq, logp, 0.3)[0])(q)
    np.testing.assert_allclose(np.asarray(g), [[-1 / 8, 0.0], [0.0, -1 / 8]], rtol=1e-5)


def test_infonce_logits_and_labels_by_hand():
    phi = jnp.array([[[1.0, 0.0], [0.0, 2.0]]])  # one head, B = 2, L = 2
    psi = jnp.array([[[3.0, 1.0], [1.0, 1.0]]])
    logits = np.asarray(losses.contrastive_logits(phi, psi))[..., 0]
    np.testing.assert_allclose(logits, np.array([[3.0, 1.0], [2.0, 2.0]]) / np.sqrt(2), rtol=1e-6)
    loss, info = losses.infonce_loss(phi, psi)

    def bce(x, y):
        return -(y * np.log(1 / (1 + np.exp(-x))) + (1 - y) * np.log(1 - 1 / (1 + np.exp(-x))))

    want = np.mean([bce(logits[i, j], float(i == j)) for i in range(2) for j in range(2)])
    assert float(loss) == pytest.approx(want, rel=1e-5)
    assert float(info['critic/accuracy']) == pytest.approx(0.5)  # row 0 picks column 0, row 1 ties -> column 0


def test_awr_and_saw_waypoint_terms_by_hand():
    logp, adv = jnp.array([-1.0, -2.0]), jnp.array([0.5, 2.0])
    loss, _ = losses.awr_actor_loss(logp, adv, 3.0, clip=100.0)
    assert float(loss) == pytest.approx(-(np.exp(1.5) * -1 + 100.0 * -2) / 2, rel=1e-5)
    mu, mu_sub = jnp.array([[1.0, 0.0], [0.0, 0.0]]), jnp.array([[0.0, 0.0], [1.0, 2.0]])
    loss, info = losses.waypoint_loss(mu, mu_sub, jnp.array([0.0, -1.0]), 3.0)
    assert float(info['waypoint/kl']) == pytest.approx((1.0 + 5.0) / 2)
    assert float(loss) == pytest.approx((1.0 * 1.0 + np.exp(-3.0) * 5.0) / 2, rel=1e-6)
    # the sub-policy is a fixed target: no gradient reaches it
    g = jax.grad(lambda m: losses.waypoint_loss(mu, m, jnp.zeros(2), 3.0)[0])(mu_sub)
    assert not np.any(np.asarray(g))


def test_qrl_value_loss_by_hand():
    d_neg, d_pos, lam = jnp.array([100.0, 700.0]), jnp.array([0.5, 3.0]), jnp.float32(2.0)
    loss, info = losses.qrl_value_loss(d_neg, d_pos, lam, 0.05)
    sp = lambda x: np.log1p(np.exp(x))  # noqa: E731
    d_neg_loss = np.mean([100 * sp(4.0), 100 * sp(-2.0)])
    d_pos_loss = np.mean([0.0, 4.0])
    assert float(info['value/d_pos_loss']) == pytest.approx(d_pos_loss)
    assert float(loss) == pytest.approx(d_neg_loss + 2 * d_pos_loss + 2 * (0.05 - d_pos_loss), rel=1e-6)
    # the multiplier ascends on the violation: d loss / d lam = eps - d_pos_loss
    g = jax.grad(lambda l: losses.qrl_value_loss(d_neg, d_pos, l, 0.05)[0])(lam)
    assert float(g) == pytest.approx(0.05 - d_pos_loss, rel=1e-6)


def test_actor_initialisation_follows_ogbench():
    actor = networks.Actor((64, 64), 8)
    p = actor.init(jax.random.PRNGKey(0), jnp.zeros((1, 29)), jnp.zeros((1, 29)))['params']
    # variance scaling fan_avg uniform: limit sqrt(3 scale / fan_avg)
    k0 = np.asarray(p['actor_net']['Dense_0']['kernel'])
    assert np.abs(k0).max() <= np.sqrt(3 / ((58 + 64) / 2)) and np.abs(k0).max() > 0.9 * np.sqrt(3 / 61)
    km = np.asarray(p['mean_net']['kernel'])
    assert np.abs(km).max() <= np.sqrt(3e-2 / 36) and np.abs(km).max() > 0.8 * np.sqrt(3e-2 / 36)
    mean, log_std = actor.apply({'params': p}, jnp.ones((3, 29)), jnp.ones((3, 29)))
    assert mean.shape == (3, 8) and not np.any(np.asarray(log_std))


# ------------------------------------------------------------------------------------- sampler
def _indexed_dataset(n_traj=50, length=400):
    n = n_traj * length
    term = np.zeros(n, bool)
    term[length - 1::length] = True
    obs = np.stack([np.arange(n), np.zeros(n)], 1).astype(np.float32)  # observation 0 = its own index
    return dsm.to_device({'observations': obs, 'actions': np.zeros((n, 2), np.float32), 'terminals': term})


def _chi2_p(counts, probs):
    counts, probs = np.asarray(counts, float), np.asarray(probs, float)
    keep = probs > 0
    assert counts[~keep].sum() == 0, 'draws from a component of probability 0'
    return stats.chisquare(counts[keep], probs[keep] * counts.sum()).pvalue


def test_gc_sampler_mixtures_pass_a_chi_square_test_that_a_wrong_mixture_fails():
    ds = _indexed_dataset()
    cfg = goals.GCSampling(value=goals.GoalSampling(0.2, 0.5, 0.3, geometric=True, discount=0.9),
                           actor=goals.GoalSampling(0.0, 0.5, 0.5, geometric=False), subgoal_offset=25)
    n = 100_000
    b = jax.jit(lambda k: goals.sample_gc(ds, k, n, cfg))(jax.random.PRNGKey(0))
    vk, ak = np.bincount(np.asarray(b.value_kind), minlength=3), np.bincount(np.asarray(b.actor_kind), minlength=3)
    assert _chi2_p(vk, [0.2, 0.5, 0.3]) > 1e-3 and _chi2_p(ak, [0.0, 0.5, 0.5]) > 1e-3
    # the test has the power to see a mixture off by a few points
    assert _chi2_p(vk, [0.22, 0.5, 0.28]) < 1e-6 and _chi2_p(ak, [0.0, 0.53, 0.47]) < 1e-6
    idx, vg, ag, sub = (np.asarray(x) for x in (b.index, b.value_goal_index, b.actor_goal_index, b.subgoal_index))
    vkind, akind = np.asarray(b.value_kind), np.asarray(b.actor_kind)
    end = idx // 400 * 400 + 399
    # rewards and masks from the value goal (0 / 0 at the goal, -1 / 1 elsewhere)
    at = vg == idx
    np.testing.assert_array_equal(np.asarray(b.rewards), np.where(at, 0.0, -1.0))
    np.testing.assert_array_equal(np.asarray(b.masks), np.where(at, 0.0, 1.0))
    np.testing.assert_array_equal(np.asarray(b.value_goals[:, 0]), vg)
    # geometric value offsets: P(1) = 1 - discount away from the end
    far = (vkind == 1) & (idx % 400 < 200)
    assert abs(((vg - idx)[far] == 1).mean() - 0.1) < 4 * np.sqrt(0.09 / far.sum())
    # subgoals: capped at the actor goal on the trajectory, at the end for random goals
    t = akind == 1
    np.testing.assert_array_equal(sub[t], np.minimum(idx[t] + 25, ag[t]))
    np.testing.assert_array_equal(sub[~t], np.minimum(idx[~t] + 25, end[~t]))
    assert np.any(sub[t] < np.minimum(idx[t] + 25, end[t]))  # the cap binds somewhere
    np.testing.assert_array_equal(np.asarray(b.low_goals[:, 0]), np.minimum(idx + 25, end))
    # 'end' caps every subgoal at the trajectory's end
    e = goals.sample_gc(ds, jax.random.PRNGKey(1), 1000, goals.GCSampling(subgoal_cap='end'))
    ei = np.asarray(e.index)
    np.testing.assert_array_equal(np.asarray(e.subgoal_index), np.minimum(ei + 25, ei // 400 * 400 + 399))


def test_sampler_settings_are_validated():
    with pytest.raises(ValueError, match='subgoal_cap'):
        goals.GCSampling(subgoal_cap='middle')
    with pytest.raises(ValueError, match='sum to 1'):
        methods.get('gcivl').preset('ci', value_p_random=0.5)


# --------------------------------------------------------------------------------- wiring
def _batch_and_learner(name, **over):
    data = synthetic.point_walks(n_traj=20, t_len=60)
    ds = dsm.to_device(data)
    m = methods.get(name)
    cfg = m.preset('ci', env='pointmaze-medium', **{'conditioning': 'goal', **over})
    learner = m.make(cfg, 2, 2)
    state = learner.init(jax.random.PRNGKey(0))
    batch = goals.sample_gc(ds, jax.random.PRNGKey(3), 16, cfg.sampling)
    return learner, state, batch


def test_hiql_targets_high_on_the_goal_capped_subgoal_and_low_on_the_end_capped_one():
    learner, state, b = _batch_and_learner('hiql')
    _, info = learner.loss(state.params, state.target, b, jax.random.PRNGKey(0))
    p = state.params
    rep, value, high = learner.modules['goal_rep'], learner.modules['value'], learner.modules['high_actor']

    def phi(s, g):
        return rep.apply(p['goal_rep'], jnp.concatenate([s, g], -1))

    def v(s, g):
        return np.asarray(value.apply(p['value'], s, phi(s, g))).mean(0)

    s, s1 = b.observations, b.next_observations
    assert float(info['low_actor/adv_mean']) == pytest.approx(np.mean(v(s1, b.low_goals) - v(s, b.low_goals)),
                                                              rel=1e-5, abs=1e-7)
    assert float(info['high_actor/adv_mean']) == pytest.approx(
        np.mean(v(b.subgoals, b.actor_goals) - v(s, b.actor_goals)), rel=1e-5, abs=1e-7)
    mu_h, ls_h = high.apply(p['high_actor'], s, b.actor_goals)
    want = np.mean(np.asarray(policy.log_prob(mu_h, ls_h, phi(s, b.subgoals))))
    assert float(info['high_actor/log_prob']) == pytest.approx(want, rel=1e-5)
    assert np.any(np.asarray(b.subgoal_index) != np.asarray(jnp.minimum(b.index + 25, b.subgoal_index.max())))


def test_hiql_both_levels_see_the_goal_direction_as_the_other_actors():
    """With direction conditioning (the cpu preset's egocentric works the same, in the torso frame)
    the high policy predicts [phi([s; w]), unit(w - s)] and the low policy acts on [phi([s; w]),
    direction to w]: trained on the true subgoal, driven by the high policy's prediction at test time."""
    learner, state, b = _batch_and_learner('hiql', conditioning='direction')
    _, info = learner.loss(state.params, state.target, b, jax.random.PRNGKey(0))
    p = state.params
    rep, low, high = learner.modules['goal_rep'], learner.modules['low_actor'], learner.modules['high_actor']

    def phi(s, g):
        return rep.apply(p['goal_rep'], jnp.concatenate([s, g], -1))

    def unit(s, g):
        d = np.asarray(g)[:, :2] - np.asarray(s)[:, :2]
        return d / (np.linalg.norm(d, axis=-1, keepdims=True) + 1e-6)

    s = b.observations
    low_in = jnp.concatenate([phi(s, b.low_goals), unit(s, b.low_goals)], -1)
    mu, ls = low.apply(p['low_actor'], s, low_in)
    assert float(info['low_actor/log_prob']) == pytest.approx(
        float(jnp.mean(policy.log_prob(mu, ls, b.actions))), rel=1e-5)
    mu_h, ls_h = high.apply(p['high_actor'], s, unit(s, b.actor_goals))  # the goal's direction, as every actor
    assert mu_h.shape[-1] == 10 + 2
    target = jnp.concatenate([phi(s, b.subgoals), unit(s, b.subgoals)], -1)
    assert float(info['high_actor/log_prob']) == pytest.approx(
        float(jnp.mean(policy.log_prob(mu_h, ls_h, target))), rel=1e-5)
    act = jax.vmap(lambda o, g: learner.agent(p).controller(p, o, g, 0, None))(s, b.actor_goals)
    pred = np.asarray(mu_h)
    sub = jnp.concatenate([networks.length_normalize(pred[:, :10]),
                           pred[:, 10:] / (np.linalg.norm(pred[:, 10:], axis=-1, keepdims=True) + 1e-6)], -1)
    np.testing.assert_allclose(act, low.apply(p['low_actor'], s, sub)[0], rtol=1e-4, atol=1e-6)


def test_saw_bootstraps_from_the_sub_policy_at_the_goal_capped_subgoal():
    learner, state, b = _batch_and_learner('saw')
    _, info = learner.loss(state.params, state.target, b, jax.random.PRNGKey(0))
    p = state.params
    sub = learner.modules['sub_actor']
    ag = learner.agent(p)
    mu_main = jax.vmap(lambda o, g: ag.controller(p, o, g, 0, None))(b.observations, b.actor_goals)
    mu_sub = sub.apply(p['sub_actor'], b.observations, b.subgoals)[0]
    assert float(info['waypoint/kl']) == pytest.approx(float(jnp.mean(jnp.sum((mu_main - mu_sub) ** 2, -1))), rel=1e-5)


def test_saw_three_advantages_by_hand_and_a_sign_flip_of_each_fails():
    """SAW's three weighted terms recomputed from its value: the sub-policy's AWR towards w with
    V(s', w) - V(s, w), the main policy's one-step AWR towards g with V(s', g) - V(s, g), and the
    bootstrap with V(w_g, g) - V(s, g). After 30 updates the values differ enough that each term with
    its advantage's sign flipped is far from the loss SAW computes (the test can see a flip)."""
    learner, state, b = _batch_and_learner('saw')
    ds = dsm.to_device(synthetic.point_walks(n_traj=20, t_len=60))
    state, _ = jax.jit(fit.chunk_step(learner.update, 30))(state, ds)
    _, info = learner.loss(state.params, state.target, b, jax.random.PRNGKey(0))
    p, m = state.params, learner.modules
    rep, value, sub, actor = m['goal_rep'], m['value'], m['sub_actor'], m['actor']

    def v(s, g):
        return np.asarray(value.apply(p['value'], s, rep.apply(p['goal_rep'], jnp.concatenate([s, g], -1)))).mean(0)

    def weighted(adv, per_sample, sign):
        return float(np.mean(np.minimum(np.exp(3.0 * sign * adv), 100.0) * per_sample))

    s, s1, act = b.observations, b.next_observations, b.actions
    mu_s, ls_s = sub.apply(p['sub_actor'], s, b.low_goals)
    logp_sub = -np.asarray(policy.log_prob(mu_s, ls_s, act))
    mu, ls = actor.apply(p['actor'], s, rep.apply(p['actor_goal_rep'], jnp.concatenate([s, b.actor_goals], -1)))
    logp = -np.asarray(policy.log_prob(mu, ls, act))
    mu_w = sub.apply(p['sub_actor'], s, b.subgoals)[0]
    sq = np.sum((np.asarray(mu) - np.asarray(mu_w)) ** 2, -1)
    terms = {'sub_actor/loss': (v(s1, b.low_goals) - v(s, b.low_goals), logp_sub),
             'actor/loss': (v(s1, b.actor_goals) - v(s, b.actor_goals), logp),
             'waypoint/loss': (v(b.subgoals, b.actor_goals) - v(s, b.actor_goals), sq)}
    for key, (adv, per) in terms.items():
        got = float(info[key])
        assert got == pytest.approx(weighted(adv, per, 1.0), rel=1e-4), key
        assert abs(weighted(adv, per, -1.0) - got) > 0.01 * abs(got), f'{key}: a sign flip would pass unseen'


@pytest.mark.parametrize('name', BASELINES)
def test_every_baseline_updates_to_finite_parameters_and_moves_its_targets(name):
    learner, state, _ = _batch_and_learner(name)
    ds = dsm.to_device(synthetic.point_walks(n_traj=20, t_len=60))
    new, metrics = jax.jit(fit.chunk_step(learner.update, 5))(state, ds)
    assert int(new.step) == 5
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(new.params))
    assert all(np.isfinite(float(v)) for v in metrics.values())
    keys = [k.split('/')[0] for k in metrics]
    assert all('/' in k for k in metrics) and keys  # namespaced
    for n in state.target:  # targets move, slowly: tau = 0.005
        before, params, after = (jax.tree.leaves(t[n]) for t in (state.target, new.params, new.target))
        gap0 = sum(float(jnp.sum(jnp.abs(a - b))) for a, b in zip(before, params))
        moved = sum(float(jnp.sum(jnp.abs(a - b))) for a, b in zip(before, after))
        assert 0 < moved < gap0
    action = learner.agent(new.params).controller(new.params, jnp.zeros(2), jnp.ones(2), 0, None)
    assert action.shape == (2,)


@pytest.mark.parametrize('name', [pytest.param(n, marks=pytest.mark.slow)
                                  for n in BASELINES + ('gas',)])
def test_baseline_resume_is_bit_identical(tmp_path, name):
    data = synthetic.point_walks(n_traj=20, t_len=60)
    m = methods.get(name)
    cfg = m.preset('ci', env='pointmaze-medium', steps=100, checkpoint_every=50, updates_per_call=50, log_every=50)
    quiet = dict(progress=False, log=lambda *_: None)
    ref = fit.train(m, cfg, data, str(tmp_path / 'ref'), **quiet)
    fit.train(m, cfg, data, str(tmp_path / 'cut'), steps=50, **quiet)
    cut = fit.train(m, None, data, str(tmp_path / 'cut'), resume=True, steps=100, **quiet)
    assert cut.step == ref.step == 100 and cut.method == name
    for x, y in zip(jax.tree.leaves(ref.state), jax.tree.leaves(cut.state)):
        assert np.asarray(x).tobytes() == np.asarray(y).tobytes()
    loaded = fit.load(str(tmp_path / 'cut'), log=lambda *_: None)
    assert loaded.method == name and type(loaded.config) is type(cfg)


# ------------------------------------------------------------------------------- evaluation
@pytest.mark.slow  # the compare tests evaluate flat methods in CI (tests/test_compare.py)
def test_a_flat_method_is_evaluated_without_a_map(tmp_path, point_model):
    from aqm_mjx import assess as run_lib

    point_model('gcbc', 50)
    lines = []
    res, rep = run_lib.evaluate_checkpoint(str(tmp_path / 'gcbc'), overrides=['protocol.episodes=2',
                                           'protocol.horizon=30', 'protocol.tasks=1'], log=lines.append)
    assert res.agents == ['flat'] and rep['keypoints'] == 0 and rep['edges'] == 0
    assert int(res.pruned.sum()) == 0 and len(res.success) == 2
    assert any('gcbc runs flat: no map, its controller aimed at the goal (it has no distance to plan on)' == str(ln)
               for ln in lines)
    # the stage line says there is no map, not '0 keypoints at delta ...'
    assert any('at step 50: no map;' in str(ln) for ln in lines)
    assert not any('keypoints at delta' in str(ln) for ln in lines)
    assert os.path.exists(tmp_path / 'gcbc' / 'eval' / 'trajectories.png')


@pytest.mark.slow
def test_flat_methods_meet_the_same_episodes_as_aqm_and_compare_in_one_table(tmp_path):
    from aqm_mjx import envs
    from aqm_mjx import assess as run_lib
    from aqm_mjx.agent.rules import AgentConfig
    from aqm_mjx.evaluation.evaluate import evaluate
    from aqm_mjx.evaluation.protocol import ProtocolConfig
    from aqm_mjx.mapping.build import trimmed_map
    from aqm_mjx.pipeline import RunConfig

    data = synthetic.point_walks(n_traj=60, t_len=60)
    path = str(tmp_path / 'pointmaze-medium-navigate.npz')
    np.savez(path, **data)
    quiet = dict(progress=False, log=lambda *_: None, dataset_path=path)
    for name in ('aqm', 'gcbc'):
        cfg = methods.get(name).preset('ci', env='pointmaze-medium', steps=100)
        fit.train(name, cfg, data, str(tmp_path / name), **quiet)
    # the AQM model's flat row and the same controller without a quasimetric: identical episodes
    env = envs.make('pointmaze-medium')
    trained = fit.load(str(tmp_path / 'aqm'), log=lambda *_: None)
    rc = RunConfig.preset('ci', env='pointmaze-medium')
    graph, _ = trimmed_map(trained.agent, data['observations'], rc.map, jax.random.PRNGKey(1))
    proto = ProtocolConfig(episodes=2, horizon=40, tasks=(1, 2), envs=16)
    full = evaluate(env, trained.agent, graph, AgentConfig(kappa=0.0, switch_radius=0.6), proto, progress=False)
    flat_agent = trained.agent._replace(encode=None, dist=None)
    flat = evaluate(env, flat_agent, None, AgentConfig(), proto, progress=False)
    assert flat.agents == ['flat'] and full.agents == ['aqm', 'no-pruning', 'flat']
    for t in (1, 2):
        np.testing.assert_array_equal(flat.traces[('flat', 'base', t)]['xy'], full.traces[('flat', 'base', t)]['xy'])
    assert flat.summary['flat'] == full.summary['flat']
    # several checkpoints, one table
    over = ['protocol.episodes=2', 'protocol.horizon=40', 'protocol.tasks=1,2']
    out = str(tmp_path / 'cmp')
    combined = run_lib.evaluate_checkpoints([str(tmp_path / 'aqm'), str(tmp_path / 'gcbc')], out, overrides=over,
                                            log=lambda *_: None)
    assert list(combined['summary']) == ['aqm/aqm', 'aqm/no-pruning', 'aqm/flat', 'gcbc/flat']
    assert combined['checkpoints']['gcbc']['keypoints'] == 0
    assert os.path.exists(os.path.join(out, 'success.png')) and os.path.exists(os.path.join(out, 'gcbc', 'results.json'))
    with pytest.raises(ValueError, match='different environments'):
        bad = methods.get('gcbc').preset('ci', env='pointmaze-large', steps=50)
        fit.train('gcbc', bad, data, str(tmp_path / 'large'), **quiet)
        run_lib.evaluate_checkpoints([str(tmp_path / 'aqm'), str(tmp_path / 'large')], out, overrides=over)


# --------------------------------------------------------------------------------- value sanity
def _grid_values(name, learner, params, cells):
    """``[C, C]`` a distance-like score from cell i to goal j (larger = farther)."""
    s = jnp.repeat(cells, len(cells), 0)
    g = jnp.tile(cells, (len(cells), 1))
    if name == 'gcivl':
        v = learner.modules['value'].apply(params['value'], s, g).mean(0)
    elif name == 'hiql':
        phi = learner.modules['goal_rep'].apply(params['goal_rep'], jnp.concatenate([s, g], -1))
        v = learner.modules['value'].apply(params['value'], s, phi).mean(0)
    elif name == 'qrl':
        ag = learner.agent(params)
        return np.asarray(jax.vmap(lambda a, b: ag.dist(params, ag.encode(params, a), ag.encode(params, b)))(s, g)
                          ).reshape(len(cells), len(cells))
    else:  # crl: the critic's logit at the best of the four moves
        moves = jnp.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
        q = jnp.stack([learner.modules['critic'].apply(params['critic'], s, g, jnp.broadcast_to(m, s.shape))[0].mean(0)
                       for m in moves])
        v = q.max(0)
    return -np.asarray(v).reshape(len(cells), len(cells))


@pytest.mark.slow
@pytest.mark.parametrize('name', ['gcivl', 'hiql', 'qrl', 'crl'])
def test_values_order_states_by_shortest_path_on_the_one_way_grid(name, one_way_grid_walks):
    data, truth = one_way_grid_walks
    m = methods.get(name)
    over = dict(env=None, steps=6000, batch_size=256, updates_per_call=500, log_every=500, checkpoint_every=500,
                value_hidden=(64, 64), actor_hidden=(32,), lr=1e-3, conditioning='goal', subgoal_offset=3)
    if name in ('qrl', 'crl'):
        over['latent'] = 64
    learner = m.make(m.preset('ci', **over), 2, 2)
    state, _ = jax.jit(lambda k, d: fit.train_scan(learner, k, d))(jax.random.PRNGKey(0), dsm.to_device(data))
    cells = jnp.array([(x, y) for x in range(5) for y in range(5)], jnp.float32)
    d = _grid_values(name, learner, state.params, cells)
    off = ~np.eye(25, dtype=bool)
    rho = stats.spearmanr(d[off], truth[off]).correlation
    print(f'{name}: Spearman {rho:.3f} against the shortest-path distance')  # pytest -m slow -s shows it
    assert rho >= 0.8, (name, rho)


def test_length_normalize_scales_to_sqrt_dim_and_keeps_zero_finite():
    x = jnp.array([[3.0, 4.0], [0.0, 0.0]])
    y = np.asarray(networks.length_normalize(x))
    np.testing.assert_allclose(y[0], np.array([3.0, 4.0]) / 5 * np.sqrt(2), rtol=1e-6)
    assert np.all(y[1] == 0)
    g = jax.grad(lambda v: networks.length_normalize(v).sum())(x)
    assert np.all(np.isfinite(np.asarray(g)))


def test_parity_benchmark_skips_and_says_why_without_a_reference_copy(tmp_path, capsys, monkeypatch):
    import importlib.util  # pylint: disable=import-outside-toplevel

    spec = importlib.util.spec_from_file_location('bench_parity', os.path.join(os.path.dirname(__file__), '..',
                                                                               'benchmarks', 'parity', 'bench_parity.py'))
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    monkeypatch.delenv('AQM_OGBENCH_REF', raising=False)
    assert bench.main([]) == 0
    assert 'skipped: no copy of seohongpark/ogbench given' in capsys.readouterr().out
    assert bench.main(['--reference', str(tmp_path)]) == 0
    assert 'holds neither impls/agents nor a git repository' in capsys.readouterr().out
    # the stand-in Gaussian is the diagonal normal density
    g = bench._gaussian_standin().MultivariateNormalDiag(jnp.array([0.5, -1.0]), jnp.array([1.0, 2.0]))
    x = jnp.array([1.0, 0.0])
    want = stats.norm.logpdf(1.0, 0.5, 1.0) + stats.norm.logpdf(0.0, -1.0, 2.0)
    assert float(g.log_prob(x)) == pytest.approx(want, rel=1e-6)
