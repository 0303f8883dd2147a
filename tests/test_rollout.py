"""The test-time agent: planning, budgets, pruning and replanning inside one jitted program, shown
without learning (exact maze distance as the quasimetric, the scripted expert as the controller)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aqm_mjx import envs
from aqm_mjx.agent import oracle, plan, rollout, rules
from aqm_mjx.agent.rules import START, AgentConfig
from aqm_mjx.envs import mazes
from aqm_mjx.mapping.graph import Graph


def _agent_step_case():
    # 3 keypoints on a line, latents are positions; d = |x - y|.
    dist = lambda x, y: jnp.abs(x[0] - y[0])  # noqa: E731
    z = jnp.array([[0.0], [10.0], [20.0]])
    w = jnp.array([[0, 10, jnp.inf], [10, 0, 10], [jnp.inf, 10, 0]], jnp.float32)
    g = Graph(z=z, obs=jnp.zeros((3, 2)), mask=jnp.ones(3, bool), w=w, tau=jnp.float32(6.0))
    cfg = AgentConfig(kappa=0.5, switch_radius=1.0)
    return dist, g, cfg


def test_agent_switches_budgets_and_prunes_by_hand():
    dist, g, cfg = _agent_step_case()
    a = rules.agent_init(dist, g, jnp.array([0.5]), jnp.array([20.5]), 0.5)
    # the start leg s -> z0 is budgeted too: (1 + 0.5) * 0.5
    assert int(a.node) == 0 and int(a.prev) == START and float(a.budget) == pytest.approx(0.75)
    a = rules.agent_step(dist, g, cfg, a, jnp.array([0.2]), 0.5)  # reaches z0: next hop z1, budget 15
    assert (int(a.node), int(a.prev), float(a.budget), int(a.t_edge)) == (1, 0, 15.0, 0)
    for _ in range(15):
        a = rules.agent_step(dist, g, cfg, a, jnp.array([3.0]), 0.5)
    assert int(a.pruned) == 0 and int(a.t_edge) == 15
    a = rules.agent_step(dist, g, cfg, a, jnp.array([3.0]), 0.5)  # step 16 > budget: prune 0 -> 1
    assert int(a.pruned) == 1 and bool(a.needs_replan) and int(a.node) == 0 and int(a.prev) == -1
    assert not np.isfinite(float(a.w[0, 1])) and float(a.w[1, 0]) == 10.0
    a = rules.replan(jax.tree.map(lambda x: x[None], a))
    a = jax.tree.map(lambda x: x[0], a)
    assert int(a.nxt[0, 2]) == -1  # goal side now unreachable from z0
    a = jax.tree.map(lambda x: x[0], jax.vmap(rules.redirect)(jax.tree.map(lambda x: x[None], a), jnp.array([0.5])))
    assert int(a.node) == -1 and int(a.prev) == -1  # no path left from z0: aim at the goal
    # kappa = inf never prunes
    b = rules.agent_init(dist, g, jnp.array([0.5]), jnp.array([20.5]), jnp.inf)
    assert not np.isfinite(float(b.budget))
    b = rules.agent_step(dist, g, cfg, b, jnp.array([0.2]), jnp.inf)
    for _ in range(100):
        b = rules.agent_step(dist, g, cfg, b, jnp.array([3.0]), jnp.inf)
    assert int(b.pruned) == 0 and int(b.node) == 1


def test_leg_kinds_and_the_two_budget_rules_by_hand():
    prev = jnp.array([rules.START, 3, 3, rules.NO_LEG])
    node = jnp.array([0, 5, -1, -1])
    np.testing.assert_array_equal(rules.leg_kind(prev, node),
                                  [rules.LEG_START, rules.LEG_EDGE, rules.LEG_GOAL, rules.LEG_NONE])
    # (t, stall, budget): the paper's rule reads the steps on the leg, the stall rule the steps without progress
    t, stall, budget = jnp.array([16, 16, 5]), jnp.array([0, 16, 5]), jnp.array([15.0, 15.0, 5.0])
    np.testing.assert_array_equal(rules.fixed_overrun(t, stall, budget), [True, True, False])
    np.testing.assert_array_equal(rules.stall_overrun(t, stall, budget), [False, True, False])
    np.testing.assert_array_equal(rules.overrun(jnp.array([0.0, 15.0, 0.0]), t, stall, budget), [True, True, False])
    np.testing.assert_array_equal(rules.overrun(jnp.array([15.0, 0.0, 5.0]), t, stall, budget), [False, True, False])


def test_goal_and_start_legs_are_budgeted_by_hand():
    dist, g, cfg = _agent_step_case()  # z = 0, 10, 20 on a line, kappa 0.5, tau 6
    step = lambda a, x: rules.agent_step(dist, g, cfg, a, jnp.array([x]), 0.5)  # noqa: E731
    # goal leg: the goal at 25 hangs off z2 (to_g = [inf, inf, 5])
    a = rules.agent_init(dist, g, jnp.array([10.3]), jnp.array([25.0]), 0.5)
    assert (int(a.node), int(a.prev), float(a.budget)) == (1, START, pytest.approx(1.5 * 0.3))
    a = step(a, 10.0)  # z1 reached: edge z1 -> z2, budget 15
    assert (int(a.node), int(a.prev), float(a.budget)) == (2, 1, 15.0)
    a = step(a, 20.0)  # z2 reached: the goal leg z2 -> g, budget 1.5 * 5
    assert (int(a.node), int(a.prev), float(a.budget)) == (-1, 2, 7.5)
    for _ in range(7):
        a = step(a, 20.0)
    assert int(a.pruned) == 0 and int(a.t_edge) == 7
    a = step(a, 20.0)  # step 8 > 7.5: the attachment z2 -> g is cut, the weights are untouched
    assert int(a.pruned) == 1 and bool(a.needs_replan) and not np.isfinite(float(a.to_g[2]))
    np.testing.assert_array_equal(a.w, g.w)
    assert (a.cuts == -1).all()  # cuts keeps keypoint edges only
    # start leg: from 4.0 only z0 is within tau (budget 1.5 * 4 = 6)
    b = rules.agent_init(dist, g, jnp.array([4.0]), jnp.array([20.5]), 0.5)
    assert (int(b.node), int(b.prev), float(b.budget)) == (0, START, 6.0)
    for _ in range(6):
        b = step(b, 4.0)
    assert int(b.pruned) == 0 and int(b.node) == 0
    b = step(b, 4.0)  # overrun: z0 banned as an entry; re-attached from 4.0 to the nearest other, z1 (6 away)
    assert bool(b.banned[0]) and not b.banned[1:].any() and int(b.pruned) == 1 and not bool(b.needs_replan)
    assert (int(b.node), int(b.prev), float(b.budget), int(b.t_edge)) == (1, START, 9.0, 0)


def test_a_step_skips_the_re_attachment_only_where_no_start_leg_overruns():
    """The rollout computes the K distances of a re-attachment only in a step where some environment
    overran its start leg (``reenters``); in every other step ``attach=False`` gives the same agent,
    and in that one it would not (it has no entry to re-attach to)."""
    dist, g, cfg = _agent_step_case()  # z = 0, 10, 20 on a line, kappa 0.5, tau 6
    b = rules.agent_init(dist, g, jnp.array([4.0]), jnp.array([20.5]), 0.5)  # start leg to z0, budget 6
    for t in range(7):
        s = jnp.array([4.0])
        assert bool(rules.reenters(dist, g, cfg, b, s, 0.0)) == (t == 6)  # the 7th step overruns it
        full = rules.agent_step(dist, g, cfg, b, s, 0.5)
        lean = rules.agent_step(dist, g, cfg, b, s, 0.5, attach=False)
        # the rollout's way: d(s, target) computed once (|4 - z0| = 4, not within the switch radius 1)
        followed = rules.follow(dist, g, cfg, b, s)
        assert (bool(followed[0]), float(followed[1])) == (False, 4.0)
        assert bool(rules.reenters(dist, g, cfg, b, s, 0.0, followed)) == (t == 6)
        jax.tree.map(np.testing.assert_array_equal, rules.agent_step(dist, g, cfg, b, s, 0.5, followed=followed), full)
        if t < 6:
            jax.tree.map(np.testing.assert_array_equal, lean, full)
        else:  # re-attached to z1 from 4.0 (6 away); without the attachment, no keypoint to enter
            assert int(full.node) == 1 and int(lean.node) != 1
        b = full
    a = rules.agent_init(dist, g, jnp.array([10.3]), jnp.array([25.0]), 0.5)  # an edge overrun does not re-attach
    for x in (10.0,) + (13.0,) * 16:
        assert not bool(rules.reenters(dist, g, cfg, a, jnp.array([x]), 0.0))
        lean = rules.agent_step(dist, g, cfg, a, jnp.array([x]), 0.5, attach=False)
        a = rules.agent_step(dist, g, cfg, a, jnp.array([x]), 0.5)
        jax.tree.map(np.testing.assert_array_equal, lean, a)
    assert int(a.pruned) == 1


def test_the_papers_rule_budgets_keypoint_edges_alone_by_hand():
    """``edges_only`` (the paper's rule, section 4.5): the start leg s -> z_1 and the goal leg z_n -> g
    run without a budget; a keypoint edge overruns after (1 + kappa) d steps and only that edge is
    cut, whatever the AQM row's parallel cuts are set to (the row passes cut_slack 0)."""
    dist, g, _ = _agent_step_case()  # z = 0, 10, 20 on a line, tau 6
    cfg = AgentConfig(kappa=0.5, switch_radius=1.0, cut_slack=0.9)  # the AQM row's slack, not the paper row's
    step = lambda a, x: rules.agent_step(dist, g, cfg, a, jnp.array([x]), 0.5, 0.0, True, 0.0)  # noqa: E731
    # start leg from 4.0 to z0: the fixed rule would cut it after 6 steps (test above); here never
    b = rules.agent_init(dist, g, jnp.array([4.0]), jnp.array([20.5]), 0.5, True, 0.0, True)
    assert (int(b.node), int(b.prev)) == (0, START) and not np.isfinite(float(b.budget))
    for _ in range(100):
        b = step(b, 4.0)
    assert int(b.pruned) == 0 and int(b.node) == 0 and not b.banned.any()
    b = step(b, 0.3)  # z0 reached: the edge z0 -> z1 has the paper's budget 1.5 * 10
    assert (int(b.node), int(b.prev), float(b.budget)) == (1, 0, 15.0)
    np.testing.assert_array_equal(b.legs[0], [4.0, 101, 99, rules.LEG_START])  # 100 steps standing, 99 stalled
    for _ in range(15):
        b = step(b, 3.0)
    assert int(b.pruned) == 0
    b = step(b, 3.0)  # step 16 > 15: the one edge z0 -> z1 is cut
    assert int(b.pruned) == 1 and int(b.removed) == 1 and not np.isfinite(float(b.w[0, 1]))
    assert np.isfinite(np.asarray(b.w)[[1, 1, 2], [0, 2, 1]]).all()
    # goal leg: the goal at 25 hangs off z2; at z2 the leg to g has no budget
    a = rules.agent_init(dist, g, jnp.array([10.3]), jnp.array([25.0]), 0.5, True, 0.0, True)
    assert (int(a.node), int(a.prev)) == (1, START) and not np.isfinite(float(a.budget))
    a = step(a, 10.0)  # z1 reached: edge z1 -> z2, budget 15
    assert (int(a.node), int(a.prev), float(a.budget)) == (2, 1, 15.0)
    a = step(a, 20.0)  # z2 reached: the goal leg, unbudgeted
    assert (int(a.node), int(a.prev)) == (-1, 2) and not np.isfinite(float(a.budget))
    for _ in range(100):
        a = step(a, 20.0)
    assert int(a.pruned) == 0 and np.isfinite(float(a.to_g[2]))
    np.testing.assert_array_equal(a.legs[:2, 3], [rules.LEG_START, rules.LEG_EDGE])


def test_stall_rule_and_leg_log_by_hand():
    """patience 3, progress 1 on the line z = 0, 10, 20: a slow walk (0.4 per step: progress every
    third step) is never cut although it overruns the fixed budget; standing still is cut after 4
    stalled steps. Every leg reached is logged as (d, steps, longest stall)."""
    dist, g, cfg = _agent_step_case()  # switch radius 1
    step = lambda a, x, p=3.0: rules.agent_step(dist, g, cfg, a, jnp.array([x]), 0.5, p)  # noqa: E731
    a = rules.agent_init(dist, g, jnp.array([0.5]), jnp.array([20.5]), 0.5, True, 3.0)
    assert (int(a.node), int(a.prev), float(a.budget), float(a.leg_d)) == (0, START, 3.0, 0.5)
    a = step(a, 0.2)  # z0 reached at once: start leg logged (d 0.5, 1 step, stall 0); edge 0 -> 1
    assert (int(a.node), int(a.prev), float(a.budget), float(a.leg_d), int(a.n_legs)) == (1, 0, 3.0, 10.0, 1)
    np.testing.assert_array_equal(a.legs[0], [0.5, 1, 0, rules.LEG_START])
    stalls = []
    for k in range(1, 22):  # x = 0.6 .. 8.6: d to z1 = 9.4, 9.0, 8.6, 8.2 (progress), ...
        a = step(a, 0.2 + 0.4 * k)
        stalls.append(int(a.stall))
    assert stalls[:5] == [0, 1, 2, 0, 1] and max(stalls) == 2 and int(a.max_stall) == 2
    assert int(a.pruned) == 0 and int(a.t_edge) == 21 > 1.5 * 10  # the fixed budget (15) would have cut it
    a = step(a, 9.5)  # d = 0.5 <= 1: z1 reached after 22 steps, longest stall 2
    assert int(a.node) == 2 and int(a.n_legs) == 2
    np.testing.assert_array_equal(a.legs[1], [10.0, 22, 2, rules.LEG_EDGE])
    np.testing.assert_array_equal(a.legs[2:], -1.0)
    for i in range(4):  # standing at 11 (d to z2 = 9): the first step sets the best, then 3 stalls
        a = step(a, 11.0)
    assert int(a.pruned) == 0 and int(a.stall) == 3
    a = step(a, 11.0)  # stall 4 > patience 3: edge 1 -> 2 cut
    assert int(a.pruned) == 1 and bool(a.needs_replan) and not np.isfinite(float(a.w[1, 2]))
    assert (int(a.stall), int(a.max_stall), int(a.n_legs)) == (0, 0, 2)  # a cut leg is not logged
    # kappa = inf never cuts under the stall rule either
    b = rules.agent_init(dist, g, jnp.array([0.5]), jnp.array([20.5]), jnp.inf, True, 3.0)
    assert not np.isfinite(float(b.budget))
    for _ in range(50):
        b = rules.agent_step(dist, g, cfg, b, jnp.array([3.0]), jnp.inf, 3.0)
    assert int(b.pruned) == 0 and int(b.max_stall) > 40


def _ladder_case(slack):
    """Keypoints on two sides of a gap, latents are positions, d is Euclidean, tau 12 (every A -> B
    edge exists, none A -> C): A0 (0, 0), A1 (0, 1), A2 (-1, 3) | B0 (10, 0), B1 (10, 1), B2 (10, 3)
    | C (20, 0). Map distances from A0: A1 1, A2 sqrt 10 = 3.16; from B0: B1 1, B2 3."""
    dist = lambda x, y: jnp.linalg.norm(x - y)  # noqa: E731
    z = np.array([[0, 0], [0, 1], [-1, 3], [10, 0], [10, 1], [10, 3], [20, 0]], np.float32)
    d = np.linalg.norm(z[:, None] - z[None], axis=-1)
    w = np.where(d <= 12.0, d, np.inf).astype(np.float32)
    g = Graph(z=jnp.asarray(z), obs=jnp.zeros((7, 2)), mask=jnp.ones(7, bool), w=jnp.asarray(w), tau=jnp.float32(12.0))
    return dist, g, AgentConfig(kappa=0.5, switch_radius=0.5, cut_slack=slack)


A_TO_B = [(a, b) for a in (0, 1, 2) for b in (3, 4, 5)]


@pytest.mark.parametrize('slack, cut, hop', [
    (0.0, [(0, 3)], 4),  # the paper: the overrun edge alone; the new plan crosses A0 -> B1 (10.05 + 10.05)
    (0.05, [(0, 3)], 4),  # neighbourhoods of radius 0.5: A0 and B0 alone
    (0.15, [(0, 3), (0, 4), (1, 3), (1, 4)], 5),  # radius 1.5: A0, A1 -> B0, B1; A0 -> B2 -> C is left
    (0.5, A_TO_B, -1),  # radius 5: every A -> B edge; no path is left, the agent aims at the goal
])
def test_an_overrun_cuts_its_parallel_edges_by_hand(slack, cut, hop):
    """Planned s -> A0 -> B0 -> C -> g and stuck between A0 and B0: after (1 + 0.5) 10 = 15 steps
    the edge A0 -> B0 overruns (one leg pruned) and, with ``cut_slack``, takes with it the edges
    from within ``slack * 10`` of A0 to within ``slack * 10`` of B0. The edges back (B -> A), inside
    a side (A -> A, B -> B) and on (B -> C) stay."""
    dist, g, cfg = _ladder_case(slack)
    # s 2.5 from A0 and 12.5 from B0 (beyond tau), g 2.5 from C
    a = rules.agent_init(dist, g, jnp.array([-2.5, 0.0]), jnp.array([22.5, 0.0]), 0.5)
    a = rules.agent_step(dist, g, cfg, a, jnp.array([0.0, 0.0]), 0.5)  # A0 reached: next hop B0, budget 15
    assert (int(a.node), int(a.prev), float(a.budget)) == (3, 0, 15.0)
    for _ in range(16):
        a = rules.agent_step(dist, g, cfg, a, jnp.array([4.0, 0.0]), 0.5)
    assert int(a.pruned) == 1 and int(a.removed) == len(cut) and bool(a.needs_replan)
    expect = np.asarray(g.w).copy()
    for i, j in cut:
        expect[i, j] = np.inf
    np.testing.assert_array_equal(np.asarray(a.w), expect)
    np.testing.assert_array_equal(np.asarray(a.cuts[0]), [0, 3])  # the overrun edge is the one logged
    batch = lambda x: jax.tree.map(lambda v: v[None], x)  # noqa: E731
    a = jax.tree.map(lambda v: v[0], jax.vmap(rules.redirect)(rules.replan(batch(a)), jnp.array([0.5])))
    assert int(a.node) == hop


def test_cut_into_takes_every_edge_into_the_targets_neighbourhood_by_hand():
    """``cut_into``: the overrun of A0 -> B0 at slack 0.15 (radius 1.5: B0 and B1) cuts every edge into
    B0 and B1, from A, from B2 and from C alike, and between them; edges into A, B2 and C stay."""
    dist, g, cfg = _ladder_case(0.15)
    cfg = AgentConfig(kappa=0.5, switch_radius=0.5, cut_slack=0.15, cut_into=True)
    a = rules.agent_init(dist, g, jnp.array([-2.5, 0.0]), jnp.array([22.5, 0.0]), 0.5)
    a = rules.agent_step(dist, g, cfg, a, jnp.array([0.0, 0.0]), 0.5)
    for _ in range(16):
        a = rules.agent_step(dist, g, cfg, a, jnp.array([4.0, 0.0]), 0.5)
    w0 = np.asarray(g.w)
    expect = w0.copy()
    for b in (3, 4):
        for src in range(7):
            if src != b and np.isfinite(w0[src, b]):
                expect[src, b] = np.inf
    np.testing.assert_array_equal(np.asarray(a.w), expect)
    assert int(a.pruned) == 1 and int(a.removed) == int(np.isfinite(w0[:, 3:5]).sum()) - 2


def _tick(dist, g, cfg, a, x, kappa=0.5):
    """One control step of the decide half for one environment: step, replan, keep_route, redirect."""
    batch = lambda v: jax.tree.map(lambda y: y[None], v)  # noqa: E731
    new = rules.replan(batch(rules.agent_step(dist, g, cfg, a, jnp.asarray(x, jnp.float32), kappa)))
    if cfg.keep_route:
        new = jax.vmap(rules.keep_last_route)(batch(a), new)
    return jax.tree.map(lambda v: v[0], jax.vmap(rules.redirect)(new, jnp.array([kappa])))


def test_keep_route_does_not_cut_the_last_route_by_hand():
    """On the line z0 - z1 - z2 the edge z0 -> z1 is the only way to the goal: with ``keep_route`` its
    overrun is not cut, the leg to z1 starts again with a fresh budget, and ``kept`` counts it; in the
    ladder, where A0 -> B1 is left, the same overrun is cut as usual."""
    dist, g, _ = _agent_step_case()
    cfg = AgentConfig(kappa=0.5, switch_radius=1.0, keep_route=True)
    a = rules.agent_init(dist, g, jnp.array([0.5]), jnp.array([20.5]), 0.5)
    a = _tick(dist, g, cfg, a, [0.2])  # z0 reached: edge z0 -> z1, budget 15
    for k in range(1, 33):
        a = _tick(dist, g, cfg, a, [3.0])
        if k in (15, 31):
            assert int(a.t_edge) == 15 and int(a.kept) == (k - 15) // 16
    assert (int(a.kept), int(a.pruned), int(a.node), int(a.prev), int(a.t_edge)) == (2, 0, 1, 0, 0)
    np.testing.assert_array_equal(np.asarray(a.w), np.asarray(g.w))
    dist, g, _ = _ladder_case(0.0)
    cfg = AgentConfig(kappa=0.5, switch_radius=0.5, keep_route=True)
    b = rules.agent_init(dist, g, jnp.array([-2.5, 0.0]), jnp.array([22.5, 0.0]), 0.5)
    b = _tick(dist, g, cfg, b, [0.0, 0.0])
    for _ in range(16):
        b = _tick(dist, g, cfg, b, [4.0, 0.0])
    assert (int(b.kept), int(b.pruned), int(b.node)) == (0, 1, 4) and not np.isfinite(float(b.w[0, 3]))


def test_cut_slack_must_be_below_one():
    with pytest.raises(ValueError, match='cut_slack must be in'):
        AgentConfig(cut_slack=1.0)
    with pytest.raises(ValueError, match='cut_slack must be in'):
        AgentConfig(cut_slack=-0.1)


def _scenario(agent, n, steps, kappas, patience=None):
    """antmaze/pointmaze-medium task 4, the shortest route's corridor cell (5, 3) closed; ``n``
    episodes per kappa (and per ``patience``, 0 the fixed rule)."""
    base = mazes.layout('medium')
    closed = base.copy()
    closed[5, 3] = 1
    env = envs.make(f'{agent}maze-medium')
    speed = 0.12 if agent == 'ant' else 0.15
    # the map and the controller know only the training layout
    agent, graph, match = oracle.oracle_agent(env, base, delta=4.0, speed=speed)
    aux = agent.aux
    cfg = AgentConfig(switch_radius=match['switch_radius'])
    traces = []

    def counted(*args):
        traces.append(1)
        return rollout.make_rollout(env, agent, cfg, steps)(*args)

    run = jax.jit(counted)
    b = n * len(kappas)
    kappa = jnp.repeat(jnp.asarray(kappas, jnp.float32), n)
    patience = jnp.repeat(jnp.asarray(patience or [0.0] * len(kappas), jnp.float32), n)
    keys = rollout.episode_keys(jax.random.PRNGKey(0), np.arange(b))
    out = run(aux, graph, rollout.episode_inputs(keys, np.full(b, 4), closed, kappa, True, patience))
    return jax.device_get(out), run, (aux, graph, base, b, kappa, patience), traces


def _check(out, n, kappas):
    """The first two row groups: kappa 0.25 (reroutes), then inf (stuck at the wall)."""
    rates = {k: float(out['success'][i * n:(i + 1) * n].mean()) for i, k in enumerate(kappas)}
    assert rates[0.25] >= 0.9, rates
    assert rates[float('inf')] <= 0.2, rates
    assert out['pruned'][:n].min() >= 1 and out['pruned'][n:2 * n].max() == 0
    return rates


def test_pruning_reroutes_the_point_around_a_closed_corridor_and_compiles_once():
    """Rows: the fixed budget (kappa 0.25), no pruning, and the stall rule (patience 20) in one batch."""
    kappas = [0.25, float('inf'), 0.25]
    out, run, (aux, graph, base, b, kappa, patience), traces = _scenario('point', 10, 400, kappas, [0, 0, 20])
    _check(out, 10, kappas[:2])
    stall = slice(20, 30)
    assert out['success'][stall].mean() >= 0.9 and out['pruned'][stall].min() >= 1  # the stall rule reroutes too
    # without parallel cuts an overrun removes at most its one keypoint edge (goal and start legs: none)
    assert (out['removed'] <= out['pruned']).all() and out['removed'][:10].min() >= 1
    # a second call with other tasks, seeds and walls does not recompile
    keys = rollout.episode_keys(jax.random.PRNGKey(7), np.arange(b))
    out2 = jax.device_get(run(aux, graph, rollout.episode_inputs(keys, np.arange(b) % 5 + 1, base, kappa, True,
                                                                 patience)))
    assert len(traces) == 1
    assert out2['success'][:10].mean() >= 0.9 and out2['success'][20:].mean() >= 0.9  # open maze, tasks 1..5
    # the leg log: one row per completed leg, steps >= its longest stall, nothing logged past the count
    legs, n = out2['legs'], out2['n_legs']
    logged = legs[..., 1] >= 0
    np.testing.assert_array_equal(logged.sum(1), np.minimum(n, rules.MAX_LEGS))
    assert n[10:20].min() >= 1 and (legs[logged][:, 0] > 0).all() and (legs[logged][:, 1] >= 1).all()
    assert (legs[logged][:, 2] <= legs[logged][:, 1]).all()
    assert out2['pruned'][10:20].max() == 0  # the calibration rows (no pruning) never cut
    # an episode that ends at the goal freezes its agent: no target change (nor cut) after the end
    ended = 0
    for i in np.flatnonzero(out2['success']):
        moving = np.any(out2['xy'][1:, i] != out2['xy'][:-1, i], axis=-1)
        k = np.flatnonzero(moving).max() + 1  # the step after which the point no longer moves
        if k < 350:
            ended += 1
            assert (out2['node'][k:, i] == out2['node'][k, i]).all(), i
    assert ended >= 10


@pytest.mark.slow  # about 3 minutes on the 2-core CPU
def test_pruning_reroutes_the_ant_around_a_closed_corridor():
    kappas = [0.25, float('inf')]
    out, *_ = _scenario('ant', 20, 1000, kappas)
    rates = _check(out, 20, kappas)
    print('ant, closed corridor, 20 episodes each:', rates, 'edges pruned (kappa 0.25):', out['pruned'][:20].tolist())


def test_replan_touches_only_pruning_agents_and_ignores_the_slot_count():
    rng = np.random.default_rng(0)
    b, k = 13, 12
    w = np.where(rng.random((b, k, k)) < 0.3, rng.uniform(1, 10, (b, k, k)), np.inf).astype(np.float32)
    g = Graph(z=jnp.zeros((k, 1)), obs=jnp.zeros((k, 2)), mask=jnp.ones(k, bool), w=jnp.asarray(w[0]),
              tau=jnp.float32(20.0))
    dist = lambda x, y: jnp.abs(x[0] - y[0])  # noqa: E731
    a = jax.vmap(lambda _: rules.agent_init(dist, g, jnp.zeros(1), jnp.zeros(1), 0.25))(jnp.arange(b))
    need = rng.random(b) < 0.5
    a = a.replace(w=jnp.asarray(w), needs_replan=jnp.asarray(need))
    want_d, want_n = plan.floyd_warshall_batch(jnp.asarray(w))
    outs = [rules.replan(a, slots) for slots in (1, 4, 8, b)]
    for o in outs:
        np.testing.assert_array_equal(o.dist[need], want_d[need])  # pruning agents: their new shortest paths
        np.testing.assert_array_equal(o.nxt[need], want_n[need])
        np.testing.assert_array_equal(o.dist[~need], a.dist[~need])  # the others: untouched
        np.testing.assert_array_equal(o.dist, outs[0].dist)
