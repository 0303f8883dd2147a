"""How AQM's update wires its objectives: advantages, the KL's direction and the stop-gradients,
checked against numbers computed by hand and against the update itself."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aqm_mjx.data import dataset as dsm
from aqm_mjx.data import goals
from aqm_mjx.data import synthetic
from aqm_mjx.learn import aqm, losses, objectives
from aqm_mjx.learn.policy import kl, log_prob

T, CLIP = 2.0, 100.0


class B(NamedTuple):
    actions: jax.Array
    goals: jax.Array
    subgoals: jax.Array


def run(params, goal):
    """A stand-in policy: mean = w * goal, log_std = s (per branch), on 3 samples x 2 actions."""
    return params['w'] * goal, jnp.broadcast_to(params['s'], goal.shape)


PARAMS = {'main': {'w': jnp.float32(0.5), 's': jnp.float32(0.3)}, 'target': {'w': jnp.float32(2.0), 's': jnp.float32(-0.4)}}
BATCH = B(actions=jnp.array([[1.0, 0.0], [0.0, -1.0], [0.5, 0.5]]), goals=jnp.array([[1.0, 2.0], [0.0, 1.0], [-1.0, 0.5]]),
          subgoals=jnp.array([[0.5, 0.5], [1.0, -1.0], [0.0, 2.0]]))
# distances chosen so that every advantage differs per sample and flips sign under a swap
D = dict(sw=jnp.array([3.0, 1.0, 2.0]), s1w=jnp.array([2.5, 1.6, 2.0]), sg=jnp.array([10.0, 4.0, 6.0]),
         s1g=jnp.array([9.0, 4.5, 6.2]), wg=jnp.array([8.0, 4.4, 5.0]))


def by_hand(params=PARAMS, batch=BATCH, d=D):
    w = lambda adv: np.minimum(np.exp(T * np.asarray(adv)), CLIP)  # noqa: E731
    mu_t, ls_t = run(params['target'], batch.subgoals)
    mu_m, ls_m = run(params['main'], batch.goals)
    target = -np.mean(w(d['sw'] - d['s1w']) * np.asarray(log_prob(mu_t, ls_t, batch.actions)))
    # KL(main || target) of diagonal Gaussians, written out
    var_m, var_t = np.exp(2 * np.asarray(ls_m)), np.exp(2 * np.asarray(ls_t))
    k = np.sum(np.asarray(ls_t - ls_m) + (var_m + np.asarray(mu_m - mu_t) ** 2) / (2 * var_t) - 0.5, axis=-1)
    main = np.mean(w(d['sg'] - d['wg']) * k)
    awr = -np.mean(w(d['sg'] - d['s1g']) * np.asarray(log_prob(mu_m, ls_m, batch.actions)))
    bc = -np.mean(np.asarray(log_prob(mu_m, ls_m, batch.actions)))
    return dict(target=target, main=main, kl=k, awr=awr, bc=bc)


def test_saw_objective_by_hand():
    want = by_hand()
    loss, info = objectives.saw_objective(run, PARAMS, BATCH, D, T, CLIP)
    # Q-AWR advantage d(s, w) - d(s', w) and Q-SAW advantage d(s, g) - d(w, g), as the paper writes them
    assert float(info['policy/target_loss']) == pytest.approx(want['target'], rel=1e-5)
    assert float(info['policy/main_loss']) == pytest.approx(want['main'], rel=1e-5)
    assert float(loss) == pytest.approx(want['target'] + want['main'], rel=1e-5)
    # the KL is KL(main || target): the other direction is a different number here
    assert float(info['policy/kl']) == pytest.approx(np.mean(want['kl']), rel=1e-5)
    swapped = np.mean(np.asarray(kl(*run(PARAMS['target'], BATCH.subgoals), *run(PARAMS['main'], BATCH.goals))))
    assert abs(swapped - np.mean(want['kl'])) > 0.1


def test_sign_flips_change_the_saw_objective():
    # what a flipped advantage would give differs from the objective's value: the checks above can fail
    flipped = dict(D, sw=D['s1w'], s1w=D['sw'])
    assert abs(by_hand(d=flipped)['target'] - by_hand()['target']) > 1e-3
    flipped = dict(D, sg=D['wg'], wg=D['sg'])
    assert abs(by_hand(d=flipped)['main'] - by_hand()['main']) > 1e-3


def test_target_policy_gets_no_gradient_from_the_main_policy():
    grads = jax.grad(lambda p: objectives.saw_objective(run, p, BATCH, D, T, CLIP)[0])(PARAMS)

    def target_only(p):
        mu, ls = run(p['target'], BATCH.subgoals)
        return losses.awr_loss(log_prob(mu, ls, BATCH.actions), D['sw'] - D['s1w'], T, CLIP)[0]

    want = jax.grad(target_only)(PARAMS)
    for k in ('w', 's'):
        assert float(grads['target'][k]) == pytest.approx(float(want['target'][k]), rel=1e-5)
        assert float(grads['main'][k]) != 0.0
    # the distances never receive gradients through the weights
    g_d = jax.grad(lambda d: objectives.saw_objective(run, PARAMS, BATCH, d, T, CLIP)[0])(D)
    assert all(float(jnp.abs(v).sum()) == 0.0 for v in g_d.values())


def test_awr_and_bc_objectives_by_hand():
    want = by_hand()
    loss, info = objectives.awr_objective(run, PARAMS, BATCH, D, T, CLIP)
    assert float(loss) == pytest.approx(want['awr'], rel=1e-5)  # advantage d(s, g) - d(s', g)
    assert float(objectives.bc_objective(run, PARAMS, BATCH, D, T, CLIP)[0]) == pytest.approx(want['bc'], rel=1e-5)
    assert set(objectives.OBJECTIVES) == {'saw', 'awr', 'bc'}
    assert all(k.startswith('policy/') for k in info)


def test_advantage_distances_by_hand():
    d = lambda x, y: jax.nn.relu(y - x)[..., 0] + 2 * jax.nn.relu(x - y)[..., 0]  # noqa: E731  asymmetric
    s, s1, w, g = (jnp.array([[v]]) for v in (0.0, 1.0, 3.0, 5.0))
    got = objectives.advantage_distances(d, s, s1, w, g)
    assert {k: float(v[0]) for k, v in got.items()} == dict(sw=3.0, s1w=2.0, sg=5.0, s1g=4.0, wg=2.0)
    got = objectives.advantage_distances(d, w, s, s, s)  # backwards: twice the cost
    assert float(got['sw'][0]) == 6.0 and float(got['s1w'][0]) == 0.0


@pytest.mark.parametrize('objective', ['saw', 'awr'])
def test_update_feeds_the_objectives_the_distances_of_its_batch(objective):
    """One real update: the advantage weights it reports are recomputed from the same batch with
    the quasimetric before the update; a sign flip or a swapped distance in ``update`` breaks this."""
    data = synthetic.point_walks(n_traj=20, t_len=40)
    ds = dsm.to_device(data)
    cfg = aqm.AQMConfig.preset('ci', env='pointmaze-medium', objective=objective, batch_size=32, weight_clip=1e6)
    learner = aqm.make(cfg, 2, 2)
    state = learner.init(jax.random.PRNGKey(0))
    _, metrics = jax.jit(learner.update)(state, ds)
    # the update's own batch: the same key split as the update
    _, k_batch, _ = jax.random.split(state.key, 3)
    b = goals.sample(ds, k_batch, cfg.batch_size, cfg.goal_sampling)
    iqe = learner.modules['quasimetric']
    dist = lambda x, y: iqe.apply(state.q_params, x, y)  # noqa: E731
    w = lambda adv: np.minimum(np.exp(cfg.temperature * np.asarray(adv)), cfg.weight_clip)  # noqa: E731
    s, s1, sub, g = b.observations, b.next_observations, b.subgoals, b.goals
    if objective == 'saw':
        assert float(metrics['policy/target_weight']) == pytest.approx(np.mean(w(dist(s, sub) - dist(s1, sub))), rel=1e-4)
        assert float(metrics['policy/main_weight']) == pytest.approx(np.mean(w(dist(s, g) - dist(sub, g))), rel=1e-4)
    else:
        assert float(metrics['policy/main_weight']) == pytest.approx(np.mean(w(dist(s, g) - dist(s1, g))), rel=1e-4)
    assert float(metrics['qrl/lambda']) == pytest.approx(cfg.lambda_init)  # the multiplier before its step
