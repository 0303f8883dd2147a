"""IQE-maxmean: interval-union lengths by brute force and the quasimetric axioms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aqm_mjx.learn import losses
from aqm_mjx.learn import quasimetric as qm


def test_interval_union_length_hand_computed():
    # Intervals [0, 2], [1, 3], [5, 6]: union length 3 + 1 = 4; [2, 2] and y < x are empty.
    x = jnp.array([0.0, 1.0, 5.0, 2.0, 4.0])
    y = jnp.array([2.0, 3.0, 6.0, 2.0, 1.0])
    assert float(qm.interval_union_length(x, y)) == pytest.approx(4.0)
    # Reversed: [2, 2], [3, 3], [6, 6], [2, 2], [1, 4] -> length 3.
    assert float(qm.interval_union_length(y, x)) == pytest.approx(3.0)


def test_interval_union_length_matches_brute_force():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, (200, 8))
    y = rng.uniform(0, 1, (200, 8))
    grid = np.linspace(0, 1, 20001)[:-1] + 0.5 / 20000  # midpoints of a fine grid
    covered = ((grid[None, None] >= x[..., None]) & (grid[None, None] < np.maximum(x, y)[..., None])).any(1)
    brute = covered.mean(-1)
    for f in (qm.interval_union_length, qm.interval_union_length_sorted):
        ours = np.asarray(f(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32)))
        np.testing.assert_allclose(ours, brute, atol=2e-4)


def test_interval_union_sweep_equals_the_sort_with_ties_nesting_and_empty_intervals():
    # Starts and ends on a coarse grid, so equal starts, equal ends, nested and touching intervals
    # and empty ones (y <= x) all occur; lengths are exact in float32 (multiples of 1/4).
    rng = np.random.default_rng(3)
    x = rng.integers(0, 12, (4000, 8)).astype(np.float32) / 4
    y = rng.integers(0, 12, (4000, 8)).astype(np.float32) / 4
    sweep = np.asarray(qm.interval_union_length(jnp.asarray(x), jnp.asarray(y)))
    np.testing.assert_array_equal(sweep, np.asarray(qm.interval_union_length_sorted(jnp.asarray(x), jnp.asarray(y))))
    # One row by hand: [1, 3], [1, 2] (same start, nested), [3, 4] (touching), [5, 5] and [6, 0] empty,
    # [0.5, 1] (ends where two start), [2, 2.5] (inside), [1, 3] (a copy): union [0.5, 4], length 3.5.
    row_x = jnp.array([1.0, 1.0, 3.0, 5.0, 6.0, 0.5, 2.0, 1.0])
    row_y = jnp.array([3.0, 2.0, 4.0, 5.0, 0.0, 1.0, 2.5, 3.0])
    assert float(qm.interval_union_length(row_x, row_y)) == 3.5


def test_interval_union_sweep_gradients_equal_the_sort():
    # Continuous endpoints (no ties): the length is differentiable and both ways give d/dx, d/dy in
    # {-1, 0, 1}: -1 at an exposed start, +1 at an exposed end, 0 where another interval covers it.
    x = jax.random.normal(jax.random.PRNGKey(0), (256, 64, 8))
    y = jax.random.normal(jax.random.PRNGKey(1), (256, 64, 8))
    grads = [jax.grad(lambda a, b: jnp.sum(f(a, b)), argnums=(0, 1))(x, y)
             for f in (qm.interval_union_length, qm.interval_union_length_sorted)]
    for g_sweep, g_sort in zip(*grads):
        np.testing.assert_array_equal(np.asarray(g_sweep), np.asarray(g_sort))
        assert set(np.unique(np.asarray(g_sweep))) <= {-1.0, 0.0, 1.0}


@pytest.mark.parametrize('n,m', [(64, 8), (512, 1), (16, 4)])
def test_quasimetric_axioms_with_random_parameters(n, m):
    model = qm.IQE(hidden=(64, 64), n_components=n, component_size=m)
    x = jax.random.normal(jax.random.PRNGKey(1), (3, 256, 29))
    params = model.init(jax.random.PRNGKey(0), x[0], x[1])
    params['params']['alpha_logit'] = jnp.array(0.7)  # alpha strictly inside (0, 1)
    d = jax.jit(lambda a, b: model.apply(params, a, b))
    dxx, dxy, dyz, dxz, dyx = d(x[0], x[0]), d(x[0], x[1]), d(x[1], x[2]), d(x[0], x[2]), d(x[1], x[0])
    np.testing.assert_allclose(np.asarray(dxx), 0.0, atol=1e-6)
    assert float(dxy.min()) >= 0.0 and float(dxy.min()) > 0.0
    assert np.all(np.asarray(dxz) <= np.asarray(dxy + dyz) + 1e-4)  # triangle inequality
    assert np.abs(np.asarray(dxy - dyx)).max() > 1e-3  # asymmetric in general
    # maxmean by hand on the component distances.
    zx = model.apply(params, x[0], method=qm.IQE.encode)
    zy = model.apply(params, x[1], method=qm.IQE.encode)
    comps = qm.iqe_components(zx, zy, n)
    alpha = jax.nn.sigmoid(0.7)
    np.testing.assert_allclose(np.asarray(dxy), np.asarray(alpha * comps.max(-1) + (1 - alpha) * comps.mean(-1)), rtol=1e-5)


def test_qrl_losses_hand_computed():
    d_pos = jnp.array([0.5, 1.5, 3.0])  # relu(d - 1)^2 = 0, 0.25, 4
    d_goal = jnp.array([10.0, 60.0, 50.0])
    lam = jnp.array(2.0)
    loss, info = losses.qrl_loss(d_pos, d_goal, lam, epsilon=0.25, offset=50.0, scale=0.01)
    close = np.array([0.0, 0.25, 4.0]) - 0.0625
    push = np.log1p(np.exp(0.01 * (50.0 - np.array([10.0, 60.0, 50.0])))) / 0.01
    # Mean over the batch of lam * close + push.
    np.testing.assert_allclose(float(loss), 2.0 * close.mean() + push.mean(), rtol=1e-5)
    np.testing.assert_allclose(float(info['qrl/push']), push.mean(), rtol=1e-5)
    np.testing.assert_allclose(float(info['qrl/close']), close.mean(), rtol=1e-5)
    # lambda's loss: -lam * mean(close); its gradient ascends on the violation: -mean(close) < 0 here
    lam_loss, lam_info = losses.lambda_loss(d_pos, lam, 0.25)
    np.testing.assert_allclose(float(lam_loss), -2.0 * close.mean(), rtol=1e-5)
    np.testing.assert_allclose(float(lam_info['lambda/violation']), close.mean(), rtol=1e-5)
    g = jax.grad(lambda l: losses.lambda_loss(d_pos, l, 0.25)[0])(lam)
    np.testing.assert_allclose(float(g), -close.mean(), rtol=1e-5)
    # no gradient reaches the distances through lambda's loss, nor lambda through the quasimetric's
    assert float(jnp.abs(jax.grad(lambda dp: losses.lambda_loss(dp, lam, 0.25)[0])(d_pos)).sum()) == 0.0
    assert float(jax.grad(lambda l: losses.qrl_loss(d_pos, d_goal, l, 0.25, 50.0, 0.01)[0])(lam)) == 0.0
    gd = jax.grad(lambda dg: losses.qrl_loss(d_pos, dg, lam, 0.25, 50.0, 0.01)[0])(d_goal)
    assert np.all(np.asarray(gd) < 0)  # push decreases as d_goal grows


def test_training_steps_lambda_with_the_tested_loss():
    """AQM's update moves the multiplier by Adam on lambda_loss's gradient. With epsilon 10 the
    constraint holds by far (violation = mean(relu(d - 1)^2) - 100 < 0), so lambda shrinks, by the
    learning rate on Adam's first step; 'ogbench' steps log lambda the same way."""
    from aqm_mjx.data import dataset as dsm
    from aqm_mjx.data import synthetic
    from aqm_mjx.learn import aqm

    ds = dsm.to_device(synthetic.point_walks(n_traj=10, t_len=30))
    for qrl in ('paper', 'ogbench'):
        cfg = aqm.AQMConfig.preset('ci', env='pointmaze-medium', epsilon=10.0, qrl=qrl)
        learner = aqm.make(cfg, 2, 2)
        state = learner.init(jax.random.PRNGKey(0))
        new, m = jax.jit(learner.update)(state, ds)
        assert -100.0 <= float(m['lambda/violation']) < -99.0
        np.testing.assert_allclose(float(new.lam) - float(state.lam), -cfg.lr_lambda, rtol=1e-3)
