"""GAS's and HILP's parts by hand: temporal-efficiency filtering, TD-aware clustering, GAS's edges, the Hilbert value."""

import jax.numpy as jnp
import pytest
import numpy as np

from aqm_mjx.learn.baselines import gas
from aqm_mjx.mapping import gas_nodes


def _line(xs):
    """Embeddings on the x axis: ``[len(xs), 2]``."""
    return np.stack([np.asarray(xs, np.float32), np.zeros(len(xs), np.float32)], axis=1)


def _ends(lengths):
    return np.concatenate([np.full(n, sum(lengths[:k + 1]) - 1) for k, n in enumerate(lengths)]).astype(np.int32)


def test_te_filtering_drops_the_turning_state_and_never_searches_the_next_trajectory():
    # trajectory A turns back at x = 2; H = 2, cosine threshold 0.5
    #   i=1 (x=1): f[3] - f[1] = 0 (no direction: cosine 0) -> dropped; every other direction agrees
    #   with where the trajectory first gets 2 away; i=5, 6 lie in the last H states -> kept
    # trajectory B: 0, 1, 2, 2.5 never gets 2 away from x=1 (i=8): its own last state is the target
    #   (cosine 1, kept); trajectory C starts at -5, which a search past B's end would have found
    f = np.concatenate([_line([0, 1, 2, 1, 0, -1, -2]), _line([0, 1, 2, 2.5]), _line([-5, -6])])
    keep = gas_nodes.efficient_states(jnp.asarray(f), jnp.asarray(_ends([7, 4, 2])), 2, 0.5, max_len=7)
    np.testing.assert_array_equal(keep, [True, False, True, True, True, True, True,
                                         True, True, True, True, True, True])


def test_te_filtering_drops_a_state_whose_next_steps_point_away_from_its_progress():
    # an L-shaped trajectory with a detour: from (0, 0) it steps to (1, 0), back to (0, 0), then up the y axis.
    # H = 2. i=0: f[2] - f[0] = 0 -> dropped. i=1: f[3] - f[1] = (-1, 1); the first state 2 away from (1, 0)
    # is (0, 2) at j=4: (-1, 2): cosine 3 / sqrt(10) = 0.949 -> kept at 0.9, dropped at 0.95
    f = np.array([[0, 0], [1, 0], [0, 0], [0, 1], [0, 2], [0, 3]], np.float32)
    ends = np.full(6, 5, np.int32)
    for thr, want1 in ((0.9, True), (0.95, False)):
        keep = np.asarray(gas_nodes.efficient_states(jnp.asarray(f), jnp.asarray(ends), 2, thr, max_len=6))
        assert not keep[0] and keep[1] == want1 and keep[2:].all()


def test_td_aware_clustering_by_hand():
    # H = 4: radius 2. In order: 0 founds node 0; 1.5 joins it (1.5 <= 2); 5 founds node 1 (5 from
    # leader 0); 2.5 founds node 2 (2.5 from leader 0 and from leader 5, both > 2); 100 is filtered
    # out; 6.5 joins node 1 (1.5 from leader 5). Centres: the mean of each node's members.
    f = _line([0, 1.5, 5, 2.5, 100, 6.5])
    keep = np.array([True, True, True, True, False, True])
    nodes = gas_nodes.td_aware_clustering(jnp.asarray(f), jnp.asarray(keep), 4, max_nodes=4)
    np.testing.assert_array_equal(nodes.assign, [0, 0, 1, 2, -1, 1])
    assert int(nodes.count) == 3 and not bool(nodes.overflow)
    np.testing.assert_allclose(nodes.centers[:, 0], [0.75, 5.75, 2.5, 0.0])
    np.testing.assert_array_equal(nodes.mask, [True, True, True, False])
    # with room for two nodes, 2.5 joins its nearest leader (0: 2.5 away, against 2.5 from 5: the first wins)
    small = gas_nodes.td_aware_clustering(jnp.asarray(f), jnp.asarray(keep), 4, max_nodes=2)
    np.testing.assert_array_equal(small.assign, [0, 0, 1, 0, -1, 1])
    assert bool(small.overflow) and int(small.count) == 2


def test_gas_edges_join_nodes_within_reach_and_connect_the_components_by_their_closest_pairs():
    # nodes on a line at 0, 3, 4, 10, 20 (the last not valid); H = 3.5: edges 0-3, 3-4 (weights 3, 1);
    # 10 is alone: its component is joined to the first node's by the closest pair, 4-10 (weight 6)
    c = _line([0, 3, 4, 10, 20])
    mask = np.array([True, True, True, True, False])
    w = np.asarray(gas_nodes.gas_edges(jnp.asarray(c), jnp.asarray(mask), 3.5))
    inf = np.inf
    np.testing.assert_array_equal(w, [[0, 3, inf, inf, inf], [3, 0, 1, inf, inf], [inf, 1, 0, 6, inf],
                                      [inf, inf, 6, 0, inf], [inf, inf, inf, inf, inf]])
    # two far groups and a lone node: {0, 1} and {30, 31} and {15}; the first node's group grows by the
    # closest pair each time: 1-15 (14), then 15-30 (15)
    w = np.asarray(gas_nodes.gas_edges(jnp.asarray(_line([0, 1, 30, 31, 15])), jnp.ones(5, bool), 2.0))
    assert np.isfinite(w).sum() == 5 + 2 * 4  # diagonal, 0-1, 30-31, 1-15, 15-30 both ways
    assert w[1, 4] == w[4, 1] == 14 and w[4, 2] == w[2, 4] == 15


def test_the_hilbert_representation_value_and_its_loss_by_hand():
    import jax

    from aqm_mjx.learn import losses, networks

    # V = -||phi(s) - phi(g)||: a 3-4-5 triangle, and the 1e-3 floor where the two coincide
    v = networks.hilbert_value(jnp.array([[0.0, 0.0], [1.0, 1.0]]), jnp.array([[3.0, 4.0], [1.0, 1.0]]))
    np.testing.assert_allclose(v, [-5.0, -1e-3], rtol=1e-6)
    # the module: two heads, each the distance of its own representation; phi is the first head's
    net = networks.HilbertValue((16,), latent=3)
    obs, goal = jnp.ones((4, 5)), jnp.zeros((4, 5))
    params = net.init(jax.random.PRNGKey(0), obs, goal)
    heads = net.apply(params, obs, goal)
    phi_s, phi_g = net.apply(params, obs, method='phi'), net.apply(params, goal, method='phi')
    assert heads.shape == (2, 4)
    np.testing.assert_allclose(heads[0], -np.linalg.norm(np.asarray(phi_s - phi_g), axis=-1), rtol=1e-5)
    # the representation's loss is implicit V-learning on that value (both references' value loss):
    # online heads V = (-5, -3), targets (-4, -4) at (s, g) and (-3, -2) at (s', g), r = -1, mask 1,
    # discount 0.99, expectile 0.7: q_i = -1 + 0.99 V'_i(s') = (-3.97, -2.98); adv = -1 + 0.99 * -3 + 4
    # = 0.03 >= 0, so weight 0.7: loss = 0.7 (1.03^2 + 0.02^2) = 0.74291
    loss, _ = losses.ivl_value_loss(jnp.array([[-5.0], [-3.0]]), jnp.array([[-4.0], [-4.0]]), jnp.array([[-3.0], [-2.0]]),
                                    jnp.array([-1.0]), jnp.array([1.0]), 0.99, 0.7)
    np.testing.assert_allclose(float(loss), 0.7 * (1.03 ** 2 + 0.02 ** 2), rtol=1e-5)
    # a negative advantage takes the other side: targets (-2, -2) at (s, g) make adv = -1.97: weight 0.3
    loss, _ = losses.ivl_value_loss(jnp.array([[-5.0], [-3.0]]), jnp.array([[-2.0], [-2.0]]), jnp.array([[-3.0], [-2.0]]),
                                    jnp.array([-1.0]), jnp.array([1.0]), 0.99, 0.7)
    np.testing.assert_allclose(float(loss), 0.3 * (1.03 ** 2 + 0.02 ** 2), rtol=1e-5)


def test_waystep_indices_by_hand():
    # H = 2 on trajectory A (x = 0, 1, 2, 1, 0, -1, -2) and B (0, 1, 2, 2.5): the first state of the
    # same trajectory at least 2 away, else the trajectory's last state (6 for A, 10 for B)
    f = np.concatenate([_line([0, 1, 2, 1, 0, -1, -2]), _line([0, 1, 2, 2.5])])
    idx = gas_nodes.waystep_indices(jnp.asarray(f), jnp.asarray(_ends([7, 4])), 2, max_len=7)
    np.testing.assert_array_equal(idx, [2, 5, 4, 5, 6, 6, 6, 9, 10, 10, 10])


def test_hilp_rewards_progress_along_its_direction_and_steers_by_the_goal_direction():
    import jax

    from aqm_mjx.data import dataset as dsm
    from aqm_mjx.data import goals, synthetic
    from aqm_mjx.learn import methods
    from aqm_mjx.learn.baselines import hilp

    np.testing.assert_allclose(hilp.unit(jnp.array([[3.0, 4.0], [0.0, 0.0]])), [[0.6, 0.8], [0.0, 0.0]])
    m = methods.get('hilp')
    cfg = m.preset('ci', env='pointmaze-medium')
    learner = m.make(cfg, 2, 2)
    state = learner.init(jax.random.PRNGKey(0))
    params = learner.params(state)
    value = learner.modules['value']
    phi = lambda o: value.apply(params['value'], o, method='phi')  # noqa: E731
    # the intrinsic reward is the progress (phi(s') - phi(s)) . z along the loss's own random directions
    ds = dsm.to_device(synthetic.point_walks(n_traj=20, t_len=60))
    batch = goals.sample_gc(ds, jax.random.PRNGKey(1), 64, cfg.sampling)
    key = jax.random.PRNGKey(2)
    _, info = learner.loss(params, state.target, batch, key)
    z = hilp.unit(jax.random.normal(key, (64, cfg.latent)))
    r = jnp.sum((phi(batch.next_observations) - phi(batch.observations)) * z, axis=-1)
    np.testing.assert_allclose(float(info['skill/reward_mean']), float(jnp.mean(r)), rtol=1e-5)
    # at test time the actor is given the unit direction from phi(s) to phi(g)
    obs, goal = jnp.array([0.5, -1.0]), jnp.array([8.0, 3.0])
    want = learner.modules['actor'].apply(params['actor'], obs, hilp.unit(phi(goal) - phi(obs)))[0]
    np.testing.assert_allclose(learner.agent(params).controller(params, obs, goal, 0, None), want, rtol=1e-6)


# ------------------------------------------------------------------------------------- GAS, the method
def _gas_rule_case():
    """Nodes on a line at x = 0, 4, 8, 12, 16 (one slot unused), edges between neighbours (weight 4), H = 5."""
    from aqm_mjx.agent import plan

    centers = jnp.asarray(np.concatenate([_line([0, 4, 8, 12, 16]), np.zeros((1, 2), np.float32)]))
    mask = jnp.array([True] * 5 + [False])
    w = np.full((6, 6), np.inf, np.float32)
    for i in range(4):
        w[i, i + 1] = w[i + 1, i] = 4.0
    return centers, mask, plan.shortest_distances(jnp.asarray(w))


def test_gas_rule_goal_attachment_start_and_furthest_path_node_by_hand():
    from aqm_mjx.agent import gas_rule

    centers, mask, dist = _gas_rule_case()
    phi_g = jnp.array([17.0, 0.0])
    # the goal at 17: distances 17, 13, 9, 5, 1 -> radius max(H = 5, 1.2 * 1) = 5, strictly: node 16 alone
    att = gas_rule.goal_attachment(centers, mask, phi_g, 5.0)
    np.testing.assert_allclose(att[:5], [np.inf, np.inf, np.inf, np.inf, 1.0])
    assert np.isinf(att[5])
    to_goal = gas_rule.distances_to_goal(dist, att)
    np.testing.assert_allclose(to_goal[:5], [17.0, 13.0, 9.0, 5.0, 1.0])
    # at x = 2.5: nodes 0 (2.5 away) and 4 (1.5) are within H; 4's total 1.5 + 13 beats 0's 2.5 + 17: start 4.
    # Its path 4, 8, 12, 16 (then the goal); within H of x = 2.5: node 4 alone (8 is 5.5 away) -> node 1
    start, final, node, z = gas_rule.target(dist, to_goal, centers, mask, jnp.array([2.5, 0.0]), phi_g,
                                            jnp.int32(0), jnp.bool_(False), 5.0)
    assert (int(start), bool(final), int(node)) == (1, False, 1)
    np.testing.assert_allclose(z, [4.0, 0.0])
    # at x = 7.5: start 8 (0.5 + 9 against 3.5 + 13); path nodes within 5: 4 (3.5), 8, 12 (4.5): the furthest, 12
    start, final, node, z = gas_rule.target(dist, to_goal, centers, mask, jnp.array([7.5, 0.0]), phi_g,
                                            start, final, 5.0)
    assert (int(start), bool(final), int(node)) == (2, False, 3)
    # far from every node (y = 9): the start stays, no path node within H -> the start itself
    start2, _, node2, _ = gas_rule.target(dist, to_goal, centers, mask, jnp.array([7.5, 9.0]), phi_g,
                                          start, final, 5.0)
    assert (int(start2), int(node2)) == (2, 2)
    # at x = 15: start 16, whose path is [16, goal]: the goal from now on, also back at x = 3
    start, final, node, z = gas_rule.target(dist, to_goal, centers, mask, jnp.array([15.0, 0.0]), phi_g,
                                            start, final, 5.0)
    assert (int(start), bool(final), int(node)) == (4, True, -1)
    np.testing.assert_allclose(z, phi_g)
    _, final, node, _ = gas_rule.target(dist, to_goal, centers, mask, jnp.array([3.0, 0.0]), phi_g, start, final, 5.0)
    assert bool(final) and int(node) == -1
    np.testing.assert_allclose(gas.skill(jnp.array([1.0, 1.0]), jnp.array([4.0, 5.0])), [0.6, 0.8], rtol=1e-6)


def test_gas_actor_goal_is_the_geometric_offset_capped_at_the_waystep_by_hand():


    # window of 4 after each source (5 states); H = 2. Row 0: x = 0, 1, 2, 3, 4: waystep 2.
    # Row 1: x = 0, .5, 1, 1.5, 1.9, trajectory going on: no waystep in the window -> its last state (4), not found.
    # Row 2: x = 0, 1, 1, 1, 1 with the trajectory ending at offset 1 (clamped): waystep = the end (1), found.
    f = jnp.stack([jnp.asarray(_line(r)) for r in ([0, 1, 2, 3, 4], [0, .5, 1, 1.5, 1.9], [0, 1, 1, 1, 1])])
    index, end = jnp.array([10, 20, 30]), jnp.array([50, 50, 31])
    off, found = gas.actor_goal_offsets(f, index, end, jnp.array([7, 7, 7]), 2)
    np.testing.assert_array_equal(off, [2, 4, 1])
    np.testing.assert_array_equal(found, [True, False, True])
    off, _ = gas.actor_goal_offsets(f, index, end, jnp.array([1, 3, 1]), 2)  # a shorter geometric draw wins
    np.testing.assert_array_equal(off, [1, 3, 1])


def test_gas_trains_its_representation_then_its_policy_each_with_its_own_adam():
    import jax

    from aqm_mjx.data import dataset as dsm
    from aqm_mjx.data import synthetic
    from aqm_mjx.learn import fit, methods

    m = methods.get('gas')
    cfg = m.preset('ci', env='pointmaze-medium', steps=8, updates_per_call=2, log_every=2, checkpoint_every=2)
    assert cfg.tdr_steps == 4
    learner = m.make(cfg, 2, 2)
    ds = dsm.to_device(synthetic.point_walks(n_traj=20, t_len=60))
    s0 = learner.init(jax.random.PRNGKey(0))
    run = jax.jit(fit.chunk_step(learner.update, 4))
    s1, m1 = run(s0, ds)
    s2, m2 = run(s1, ds)

    def moved(a, b, n):
        return any(bool(jnp.any(x != y)) for x, y in zip(jax.tree.leaves(a.params[n]), jax.tree.leaves(b.params[n])))

    assert moved(s0, s1, 'tdr') and not any(moved(s0, s1, n) for n in gas.POLICY)
    assert not moved(s1, s2, 'tdr') and all(moved(s1, s2, n) for n in gas.POLICY)
    counts = lambda s, g: [int(x) for x in jax.tree.leaves(s.opt[g]) if getattr(x, 'dtype', None) == jnp.int32]  # noqa: E731
    assert counts(s1, 'tdr') == [4] and counts(s1, 'policy') == [0]  # the policy's Adam starts at the switch
    assert counts(s2, 'tdr') == [4] and counts(s2, 'policy') == [4]
    assert float(m1['phase']) == 0.0 and float(m2['phase']) == 1.0 and float(m2['tdr/loss']) == 0.0
    assert np.isfinite(float(m2['actor/loss'])) and float(m2['critic/loss']) > 0


def test_seeds_vmapped_share_their_step_so_gas_pays_for_one_phase_an_update_and_match_each_seed_alone():
    import jax

    from aqm_mjx.data import dataset as dsm
    from aqm_mjx.data import synthetic
    from aqm_mjx.learn import fit, methods

    m = methods.get('gas')
    cfg = m.preset('ci', env='pointmaze-medium', steps=8, updates_per_call=2, log_every=2, checkpoint_every=2)
    learner = m.make(cfg, 2, 2)
    ds = dsm.to_device(synthetic.point_walks(n_traj=20, t_len=60))
    alone = [learner.init(jax.random.PRNGKey(s)) for s in (0, 1)]
    both = jax.tree.map(lambda *x: jnp.stack(x), *alone)
    run, vrun = jax.jit(fit.chunk_step(learner.update, 3)), jax.jit(fit.seeds_chunk(learner.update, 3))
    # the phase is one cond in the vmapped program; vmap with a per-seed step turns it into a select
    # over both phases' updates (the control)
    assert 'cond[' in str(jax.make_jaxpr(fit.seeds_chunk(learner.update, 3))(both, ds))
    assert 'cond[' not in str(jax.make_jaxpr(jax.vmap(fit.chunk_step(learner.update, 3), in_axes=(0, None)))(both, ds))
    for _ in range(2):  # 6 updates: across the boundary at 4
        alone = [run(s, ds)[0] for s in alone]
        both, metrics = vrun(both, ds)
    np.testing.assert_array_equal(both.step, [6, 6])
    np.testing.assert_allclose(metrics['phase'], [2 / 3, 2 / 3])  # updates 3, 4, 5: the last two in phase 2
    for i, a in enumerate(alone):
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(jax.tree.map(lambda v: v[i], both))):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=2e-4, atol=2e-5)


def test_gas_map_representatives_and_trajectory_ends():
    from aqm_mjx.data.dataset import trajectory_ends

    np.testing.assert_array_equal(trajectory_ends(np.array([0, 0, 1, 0, 1])), [2, 2, 2, 4, 4])
    # members of node 0 at x = 0, 1.5 (centre 0.75: 1.5 is 0.75 away, 0 too: the lower index); node 1: 5, 6.5
    f = jnp.asarray(_line([0, 1.5, 5, 100, 6.5, 5.5]))
    nodes = gas_nodes.td_aware_clustering(f, jnp.array([True, True, True, False, True, True]), 4, max_nodes=3)
    np.testing.assert_allclose(nodes.centers[:2, 0], [0.75, 17 / 3], rtol=1e-6)
    np.testing.assert_array_equal(gas_nodes.representatives(f, nodes), [0, 5, 0])


def test_hilp_planning_midpoints_by_hand_and_without_planning_the_flat_agent():
    from aqm_mjx.agent import hilp_rule
    from aqm_mjx.learn import methods

    # states at x = 0..10, from 0 toward 10: the 2 nearest of max(|x - 0|, |x - 10|) are 4, 6 (5 is missing):
    # waypoint 5; again toward 5: max(|x|, |x - 5|) is smallest at 2 and 3: waypoint 2.5
    z = jnp.asarray(_line([0, 1, 2, 3, 4, 6, 7, 8, 9, 10]))
    s, g = jnp.array([0.0, 0.0]), jnp.array([10.0, 0.0])
    np.testing.assert_allclose(hilp_rule.waypoint(z, s, g, 1, 2), [5.0, 0.0])
    np.testing.assert_allclose(hilp_rule.waypoint(z, s, g, 2, 2), [2.5, 0.0])
    np.testing.assert_allclose(hilp_rule.waypoint(z, s, g, 0, 2), g)
    m = methods.get('hilp')
    planning = m.make(m.preset('ci', env='pointmaze-medium'), 2, 2).agent()
    assert planning.plans and not planning.prunes and planning.rule is not None and planning.dist is None
    flat = m.make(m.preset('ci', env='pointmaze-medium', planning_recursions=0), 2, 2).agent()
    assert not flat.plans and flat.rule is None
    with pytest.raises(ValueError, match='planning_knns'):
        m.preset('ci', env='pointmaze-medium', planning_knns=600)


@pytest.mark.slow
def test_compare_trains_and_evaluates_gas_and_hilp_with_their_own_planners(tmp_path):
    import json
    import os

    from aqm_mjx import compare
    from aqm_mjx.data import synthetic

    path = str(tmp_path / 'pointmaze-medium-navigate.npz')
    np.savez(path, **synthetic.point_walks(n_traj=60, t_len=60, seed=0))
    out = str(tmp_path / 'cmp')
    over = ['steps=100', 'protocol.tasks=1', 'protocol.episodes=2', 'protocol.horizon=20', 'protocol.ablations=flat']
    said = []
    res = compare.compare('pointmaze-medium', ['gas', 'hilp'], 2, out, preset='ci', dataset=path, overrides=over,
                          log=lambda *a: said.append(' '.join(map(str, a))))
    assert list(res['rows']) == ['gas', 'hilp'] and all(r['base']['episodes'] == 4 for r in res['rows'].values())
    # an ablation asked of a method that does not prune is not run, and the log says so
    for m in ('gas', 'hilp'):  # once per evaluated seed
        assert sum(f'{m} does not prune, so its own agent runs alone' in s for s in said) == 2, m
    for m in ('gas', 'hilp'):
        ev = json.load(open(os.path.join(out, 'eval', m, 'results.json')))
        assert set(ev['summary']) == {f'{m}:seed_0/planner', f'{m}:seed_1/planner'}
        assert all(c['keypoints'] > 0 for c in ev['checkpoints'].values())


@pytest.mark.slow
@pytest.mark.parametrize('method', ['gas', 'hilp'])
def test_the_one_program_trains_maps_and_evaluates_gas_and_hilp(method):
    import jax

    from aqm_mjx import envs, pipeline
    from aqm_mjx.data import dataset as dsm
    from aqm_mjx.data import synthetic

    cfg = pipeline.RunConfig.preset('ci', method=method, env='pointmaze-medium').with_overrides(
        ['train.steps=100', 'train.updates_per_call=50', 'train.log_every=50', 'train.checkpoint_every=50',
         'protocol.tasks=1', 'protocol.episodes=2', 'protocol.horizon=20'])
    run = pipeline.make_run(cfg, envs.make('pointmaze-medium'))
    assert list(run.episodes.agents) == ['planner']
    out = jax.jit(run)(jax.random.PRNGKey(0), dsm.to_device(synthetic.point_walks(n_traj=20, t_len=60)))
    assert int(out['keypoints']) > 0 and out['episode_success'].shape == (2,) and int(out['pruned'].sum()) == 0


def test_a_gas_config_saved_with_a_phase_share_reads_back_as_the_same_boundary_in_updates():
    """Runs saved before the boundary was ``tdr_steps`` carry ``tdr_fraction``: the share of the
    run's steps, rounded and kept inside (0, steps); anything else is an error that names it."""
    d = gas.GASConfig.preset('cpu', env='antmaze-medium').to_dict()
    d.pop('tdr_steps')
    for frac, steps, want in [(0.5, 20_000, 10_000), (0.25, 1_500, 375), (1e-4, 1_000, 1), (0.9999, 1_000, 999)]:
        assert gas.GASConfig.from_dict({**d, 'tdr_fraction': frac, 'steps': steps}).tdr_steps == want
    with pytest.raises(ValueError, match='tdr_fraction must be in'):
        gas.GASConfig.from_dict({**d, 'tdr_fraction': 1.5})
    with pytest.raises(ValueError, match='unknown GASConfig field'):
        gas.GASConfig.from_dict({**d, 'tdr_fraction': 0.5, 'tdr_steps': 3, 'bogus': 1})
