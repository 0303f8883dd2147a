"""The planners around any method (issue: the map around every method): each method's value read as
steps by hand, the check a distance passes before a map is built on it, and the TTGS-style map and
rule (edge weights, Dijkstra's path, the subgoal choice) by hand."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aqm_mjx.agent import planners, ttgs_rule
from aqm_mjx.interface import Agent
from aqm_mjx.learn import distance as to_steps
from aqm_mjx.learn import methods
from aqm_mjx.mapping import build, ttgs_nodes

GAMMA = 0.99


def test_steps_from_value_inverts_the_discounted_value_and_stays_finite_at_its_ends():
    d = jnp.array([1.0, 10.0, 50.0, 200.0])
    np.testing.assert_allclose(to_steps.steps_from_value(to_steps.value_from_steps(d, GAMMA), GAMMA), d, rtol=1e-3)
    # V = -(1 - 0.99^10) / 0.01 = -9.5618 by hand
    assert float(to_steps.value_from_steps(10.0, GAMMA)) == pytest.approx(-9.5618, abs=1e-3)
    ends = to_steps.steps_from_value(jnp.array([0.5, 0.0, -100.0, -1e6]), GAMMA)
    assert np.all(np.isfinite(ends)) and float(ends[0]) < 0.01 and float(ends[1]) < 0.01
    # -1/(1 - gamma) + 1e-3 -> log(1e-5) / log(0.99) = 1145.5 steps: "farther than anything", not NaN
    assert float(ends[2]) == pytest.approx(math.log(1e-5) / math.log(GAMMA), rel=1e-3)
    assert float(ends[3]) == pytest.approx(float(ends[2]))
    # CRL: a critic that falls by log(1/gamma) a step reads as steps
    assert float(to_steps.steps_from_log_ratio(2.0, 2.0 - 7 * -math.log(GAMMA), GAMMA)) == pytest.approx(7.0)


def _learner(name):
    m = methods.get(name)
    learner = m.make(m.preset('ci'), 29, 8)
    return learner, learner.params(learner.init(jax.random.PRNGKey(0)))


def _constant_value(params, value_steps):
    """``params`` with the value network's last layer outputting ``V = value_from_steps(value_steps)``."""
    net = params['value']['params']['value_net']
    last = max((k for k in net if k.startswith('Dense')), key=lambda k: int(k.split('_')[1]))
    v = float(to_steps.value_from_steps(value_steps, GAMMA))
    net = dict(net, **{last: {'kernel': jnp.zeros_like(net[last]['kernel']), 'bias': jnp.full_like(net[last]['bias'], v)}})
    return dict(params, value={'params': dict(params['value']['params'], value_net=net)})


@pytest.mark.parametrize('name', ['gcivl', 'gciql', 'hiql', 'saw'])
def test_a_value_of_known_steps_reads_as_those_steps(name):
    learner, params = _learner(name)
    p = _constant_value(params, 37.0)  # every head outputs V(37 steps)
    dist = learner.distance
    s, g = jnp.linspace(-1, 1, 29), jnp.linspace(2, 0, 29)
    assert float(dist.dist(p, dist.encode(p, s), dist.encode(p, g))) == pytest.approx(37.0, rel=1e-3)
    assert 'log_gamma' in dist.about


@pytest.mark.parametrize('name', ['hilp', 'gas'])
def test_a_hilbert_value_reads_its_norm_as_steps(name):
    learner, params = _learner(name)
    dist = learner.distance
    norm = -float(to_steps.value_from_steps(12.0, GAMMA))  # ||phi(s) - phi(g)|| of a goal 12 steps away
    u = jnp.zeros(dist.encode(params, jnp.zeros(29)).shape)
    v = u.at[0].set(norm * 0.6).at[1].set(norm * 0.8)
    assert float(dist.dist(params, u, v)) == pytest.approx(12.0, rel=1e-3)
    assert float(dist.dist(params, u, u)) < 0.01


def test_crl_reads_its_critic_from_the_state_itself_at_its_actors_action():
    learner, params = _learner('crl')
    dist = learner.distance
    s, g = jnp.linspace(-1, 1, 29), jnp.linspace(2, 0, 29)
    a = jnp.clip(learner.agent(params).controller(params, s, g, 0, None), -1, 1)
    f = lambda goal: learner.modules['critic'].apply(params['critic'], s[None], goal[None], a[None])[0].mean()  # noqa: E731
    by_hand = max((float(f(s)) - float(f(g))) / -math.log(GAMMA), 0.0)
    assert float(dist.dist(params, s, g)) == pytest.approx(by_hand, rel=1e-4, abs=1e-5)
    assert float(dist.dist(params, s, s)) == 0.0


@pytest.mark.parametrize('name', ['qrl', 'aqm'])
def test_a_quasimetric_is_its_own_distance(name):
    learner, params = _learner(name)
    agent, dist = learner.agent(params), learner.distance
    s, g = jnp.linspace(-1, 1, 29), jnp.linspace(2, 0, 29)
    assert float(dist.dist(params, dist.encode(params, s), dist.encode(params, g))) == \
        float(agent.dist(params, agent.encode(params, s), agent.encode(params, g)))


def test_around_builds_each_planner_and_refuses_a_method_without_a_value():
    learner, params = _learner('gcivl')
    own = learner.agent(params)
    assert not own.plans
    flat = planners.around(own, learner.distance, 'flat')
    aqm = planners.around(own, learner.distance, 'aqm')
    ttgs = planners.around(own, learner.distance, 'ttgs', ttgs=dict(nodes=64, tau=24.0, horizon=48.0, window=8))
    assert not flat.plans and aqm.prunes and aqm.rule is None and aqm.controller is own.controller
    assert ttgs.plans and not ttgs.prunes and ttgs.rule[0] == 'ttgs' and dict(ttgs.mapper[1])['nodes'] == 64
    assert planners.around(own, learner.distance, 'own') is own
    gcbc, p_bc = _learner('gcbc')
    assert gcbc.distance is None
    with pytest.raises(ValueError, match='gcbc has no value to plan with'):
        planners.around(gcbc.agent(p_bc), None, 'aqm', 'gcbc')
    with pytest.raises(ValueError, match="unknown planner 'astar'"):
        planners.around(own, learner.distance, 'astar')


# ------------------------------------------------------------------------------ the distance check
def _line_data(n_traj=8, t_len=60):
    """Trajectories along the x axis, one unit a step: the true distance is the x gap."""
    x = np.tile(np.arange(t_len, dtype=np.float32), n_traj)
    obs = np.stack([x, np.zeros_like(x)], 1)
    terminals = np.zeros(len(x), bool)
    terminals[t_len - 1::t_len] = True
    return obs, terminals


def _agent(dist):
    return Agent(lambda aux, o: o, lambda aux, a, b: dist(b[0] - a[0]), None, aux=())


def test_the_distance_check_passes_steps_and_names_a_wrong_sign_or_scale_in_one_line():
    obs, terminals = _line_data()
    key = jax.random.PRNGKey(0)
    out = build.distance_check(_agent(jnp.abs), obs, terminals, key, name='exact')
    assert out == dict(d0=0.0, d1=1.0, d25=25.0)
    for wrong, what in ((lambda gap: 100.0 - jnp.abs(gap), 'does not grow'),  # a value (larger = nearer) read as d
                        (lambda gap: 0.01 * jnp.abs(gap), 'reads 25 steps of data as 0.25'),  # other units
                        (lambda gap: jnp.zeros_like(gap), 'does not grow')):  # learned nothing
        with pytest.raises(ValueError, match=what) as e:
            build.distance_check(_agent(wrong), obs, terminals, key, name='bad')
        assert '\n' not in str(e.value) and 'the distance of bad' in str(e.value)
    assert build.distance_check(_agent(jnp.abs), *_line_data(t_len=20), key) is None  # nothing to check on


# ------------------------------------------------------------------------------------- the TTGS map
def test_ttgs_edge_weights_by_hand():
    d = jnp.array([[0.0, 10.0, 0.4], [30.0, 0.0, 24.0], [48.0, 5.0, 0.0]])
    w = np.asarray(ttgs_nodes.soft_weights(d, tau=24.0))
    assert np.all(np.isinf(np.diag(w)))
    assert w[0, 1] == 10.0 and w[0, 2] == 1.0 and w[1, 2] == 24.0 and w[2, 1] == 5.0  # within tau; floored at 1
    assert w[1, 0] == pytest.approx(30.0 * 1000.0 ** (30.0 / 24.0), rel=1e-5)  # 168,702: past tau, penalised
    assert w[2, 0] == pytest.approx(48.0 * 1000.0 ** 2, rel=1e-5)


def test_ttgs_map_draws_its_nodes_and_weighs_every_pair():
    obs = jnp.stack([jnp.arange(50.0), jnp.zeros(50)], 1)
    enc, dist = (lambda aux, o: o), (lambda aux, a, b: jnp.abs(b[0] - a[0]))
    g = ttgs_nodes.ttgs_map(enc, dist, None, obs, jax.random.PRNGKey(3), nodes=20, tau=4.0)
    x = np.asarray(g.obs[:, 0])
    assert g.w.shape == (20, 20) and len(set(x.tolist())) == 20 and bool(g.mask.all())
    np.testing.assert_allclose(np.asarray(g.w), np.asarray(ttgs_nodes.soft_weights(jnp.abs(x[None] - x[:, None]), 4.0)))


def test_dijkstra_takes_the_cheap_detour_and_reads_the_path_back():
    inf = jnp.inf
    # 0 -> 1 -> 2 -> 3 costs 3; 0 -> 3 costs 10; 0 -> 4 -> 3 costs 6; node 5 is masked out
    w = jnp.full((6, 6), inf)
    for a, b, c in ((0, 1, 1.0), (1, 2, 1.0), (2, 3, 1.0), (0, 3, 10.0), (0, 4, 2.0), (4, 3, 4.0), (0, 5, 0.1),
                    (5, 3, 0.1)):
        w = w.at[a, b].set(c)
    mask = jnp.array([True] * 5 + [False])
    dist, prev = ttgs_rule.dijkstra(w, mask, jnp.int32(0), jnp.int32(3))
    assert float(dist[3]) == 3.0
    path, length = ttgs_rule.path_nodes(prev, jnp.int32(0), jnp.int32(3), jnp.bool_(True), 8)
    assert int(length) == 4 and np.asarray(path).tolist() == [0, 1, 2, 3, -1, -1, -1, -1]
    path, length = ttgs_rule.path_nodes(prev, jnp.int32(0), jnp.int32(3), jnp.bool_(True), 2)  # too long: its end
    assert int(length) == 2 and np.asarray(path).tolist() == [2, 3]
    _, length = ttgs_rule.path_nodes(prev, jnp.int32(0), jnp.int32(3), jnp.bool_(False), 8)
    assert int(length) == 0


def test_ttgs_subgoal_is_the_farthest_path_point_within_t_else_the_next_else_the_goal():
    path = jnp.array([7, 8, 9, 10, 11, -1])
    idx = jnp.arange(6)

    def choose(d_goal, d_window, closest=0, length=5, end=10.0, horizon=48.0):
        c, n = ttgs_rule.subgoal(jnp.float32(d_goal), jnp.asarray(d_window, jnp.float32), idx, jnp.int32(length),
                                 jnp.int32(closest), jnp.float32(end), path, horizon)
        return int(c), int(n)

    far = [60.0, 5.0, 30.0, 47.0, 90.0, 0.0]  # closest point 1; 2 and 3 within T = 48; 4 beyond
    assert choose(100.0, far) == (1, 10)  # the farthest within T: point 3 (node 10), not 4; point 5 is padding
    assert choose(40.0, far) == (1, -1)  # the goal itself within T
    none_near = [60.0, 5.0, 50.0, 70.0, 90.0, 0.0]  # nothing ahead within T: the point after the closest
    assert choose(100.0, none_near) == (1, 9)
    at_end = [90.0, 80.0, 70.0, 60.0, 5.0, 0.0]  # closest is the last point
    assert choose(100.0, at_end, end=10.0) == (4, 11)  # its end is near the goal: stay on it
    assert choose(100.0, at_end, end=60.0) == (4, -1)  # its end is far from the goal: the goal
    assert choose(100.0, far, length=0) == (0, -1)  # no path: the goal


# ------------------------------------------------------------------------------ end to end
@pytest.mark.slow  # three pointmaze evaluations (a compile each): about 2 minutes
def test_evaluate_runs_a_method_under_each_planner_on_the_same_episodes(tmp_path, point_model):
    import json
    import os

    from aqm_mjx import assess

    model = point_model('gcivl', 100)
    over = ['protocol.episodes=2', 'protocol.horizon=30', 'protocol.tasks=1,2', 'agent.distance_check=false',
            'agent.ttgs_nodes=48', 'agent.ttgs_window=8']
    runs = {}
    for planner in ('flat', 'aqm', 'ttgs'):
        lines = []
        res, rep = assess.evaluate_checkpoint(model, out=str(tmp_path / planner), log=lines.append,
                                              overrides=over + [f'agent.planner={planner}'])
        runs[planner] = res
        stage = [str(ln) for ln in lines if ' preset at step ' in str(ln)]
        assert len(stage) == 1 and (': no map;' in stage[0]) == (planner == 'flat'), stage
        saved = json.load(open(os.path.join(tmp_path, planner, 'results.json')))
        assert saved['config']['agent']['planner'] == planner
    assert runs['flat'].agents == ['flat'] and runs['ttgs'].agents == ['planner']
    assert runs['aqm'].agents[0] == 'aqm' and 'flat' in runs['aqm'].agents
    # AQM's map around GCIVL keeps GCIVL's controller: its flat row is the flat run, episode for episode
    for t in (1, 2):
        np.testing.assert_array_equal(runs['aqm'].traces[('flat', 'base', t)]['xy'], runs['flat'].traces[('flat', 'base', t)]['xy'])
    nodes = np.concatenate([runs['ttgs'].traces[('planner', 'base', t)]['node'].ravel() for t in (1, 2)])
    assert nodes.min() >= -1 and nodes.max() < 48  # map nodes, or -1: the goal


@pytest.mark.slow  # two pointmaze compiles: about 70 s
def test_ttgs_around_the_exact_maze_distance_follows_its_path_to_the_goal():
    """The TTGS planner on a distance that is right (the exact maze distance in steps) around a point
    that steers straight at whatever it is given: flat, it runs into the walls on task 4; with the
    map, it goes round them through the path's nodes to the goal."""
    from aqm_mjx import envs
    from aqm_mjx.agent import oracle
    from aqm_mjx.agent.rules import AgentConfig
    from aqm_mjx.envs import mazes
    from aqm_mjx.evaluation import evaluate, protocol
    from aqm_mjx.interface import Distance

    env = envs.make('pointmaze-medium')
    grid = mazes.layout('medium')
    exact, _, _ = oracle.oracle_agent(env, grid, delta=4.0, speed=0.15)
    straight = exact._replace(controller=lambda aux, o, g, t, k: (g[:2] - o[:2]) / (jnp.linalg.norm(g[:2] - o[:2]) + 1e-6))
    ttgs = planners.around(straight, Distance(exact.encode, exact.dist), 'ttgs',
                           ttgs=dict(nodes=600, tau=16.0, horizon=16.0, window=16))
    free = np.argwhere(grid == 0)
    rng = np.random.default_rng(0)
    xy = mazes.ij_to_xy(free[rng.integers(len(free), size=3000)]) + rng.uniform(-1.5, 1.5, (3000, 2))
    obs = np.zeros((3000, env.obs_size), np.float32)
    obs[:, :2] = xy
    graph = ttgs_nodes.ttgs_map(ttgs.encode, ttgs.dist, ttgs.aux, jnp.asarray(obs), jax.random.PRNGKey(0), 600, 16.0)
    proto = protocol.ProtocolConfig(episodes=2, tasks=(1, 4), horizon=500, ablations=())
    res = evaluate.evaluate(env, ttgs, graph, AgentConfig(), proto, progress=False)
    flat = evaluate.evaluate(env, planners.around(straight, None, 'flat'), None, AgentConfig(), proto, progress=False)
    assert res.agents == ['planner'] and flat.agents == ['flat']
    assert res.summary['planner']['base']['task_4'] == 1.0 and flat.summary['flat']['base']['task_4'] == 0.0
    assert res.summary['planner']['base']['task_1'] == 1.0
    nodes = np.concatenate([res.traces[('planner', 'base', t)]['node'].ravel() for t in (1, 4)])
    assert (nodes >= 0).mean() > 0.1 and nodes.max() < 600  # map nodes on the way, then the goal


def test_a_dense_map_is_drawn_with_its_edges_within_tau_and_a_keypoint_graph_whole():
    from aqm_mjx.evaluation.report import drawn_edges
    from aqm_mjx.mapping.graph import Graph

    x = jnp.arange(6.0)
    d = jnp.abs(x[None] - x[:, None])
    dense = Graph(z=x[:, None], obs=jnp.zeros((6, 2)), mask=jnp.ones(6, bool), w=ttgs_nodes.soft_weights(d, 1.5),
                  tau=jnp.float32(1.5))
    assert sorted(map(tuple, drawn_edges(dense).tolist())) == [(i, j) for i in range(6) for j in range(6) if abs(i - j) == 1]
    near = dense.replace(w=ttgs_nodes.soft_weights(d, 4.5), tau=jnp.float32(4.5))  # 28 pairs within tau
    shortest = drawn_edges(near, limit=12)  # only the 12 shortest: the 10 of length 1, 2 of length 2
    assert len(shortest) == 12 and sorted(abs(i - j) for i, j in shortest.tolist()) == [1] * 10 + [2] * 2
    sparse_w = jnp.where(d == 1.0, d, jnp.inf).at[0, 5].set(9.0)  # a keypoint graph: one long joining edge kept
    sparse = dense.replace(w=sparse_w)
    assert len(drawn_edges(sparse)) == 11
    # fewer than half the pairs joined (a value that reads most pairs unreachable) but more than the limit:
    # capped all the same, the shortest within tau
    two = (d == 2.0) & (jnp.minimum(x[:, None], x[None]) < 2)  # 0-2 and 1-3 both ways: past tau 1.5
    part = dense.replace(w=jnp.where((d == 1.0) | two, ttgs_nodes.soft_weights(d, 1.5), jnp.inf))  # 14 of 30 pairs
    assert len(drawn_edges(part)) == 14  # under the limit: every one
    assert len(drawn_edges(part, limit=12)) == 10  # over it: the 10 within tau
    assert len(drawn_edges(part, limit=9)) == 9


def test_distance_profile_reads_a_quasimetric_along_the_data_and_refuses_a_flat_method(tmp_path, point_model):
    """benchmarks/experiments/distance_profile.py on a small QRL model: every offset's quantiles in order,
    d(s, s) = 0 exactly (an IQE), so at k = 0 every pair is 'not above d0'; on GCBC (no distance) one line."""
    import json
    import subprocess
    import sys

    qrl, gcbc = point_model('qrl', 50), point_model('gcbc', 50)
    data = str(tmp_path / 'pointmaze-medium-navigate.npz')
    script = 'benchmarks/experiments/distance_profile.py'
    out = tmp_path / 'profile.json'
    run = subprocess.run([sys.executable, script, '--dataset', data, '--checkpoint', qrl, '--offsets', '0', '1', '5',
                          '10', '--pairs', '64', '--coverage', '2', '600', '--delta', '1', '--candidates', '500',
                          '--out', str(out)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    (row,) = json.load(open(out))['rows']
    assert row['method'] == 'qrl' and row['pairs'] == 64 and list(row['offsets']) == ['0', '1', '5', '10']
    # --coverage: 2 slots leave candidates outside delta 1; 600 slots (more than the 500 candidates) cover them
    few, enough = row['coverage']
    assert (few['slots'], few['keypoints'], few['overflow'], few['candidates']) == (2, 2, True, 500)
    assert 0 < few['uncovered'] <= 500 - 2
    assert not enough['overflow'] and enough['uncovered'] == 0 and 2 < enough['keypoints'] <= 500
    assert f"with 2 slots: 2 keypoints, {few['uncovered']:,} of 500 candidates left uncovered" in run.stdout
    assert row['offsets']['0'] == dict(q10=0.0, q50=0.0, q90=0.0, not_above_d0=1.0)
    for q in row['offsets'].values():
        assert q['q10'] <= q['q50'] <= q['q90'] and 0.0 <= q['not_above_d0'] <= 1.0
    flat = subprocess.run([sys.executable, script, '--dataset', data, '--checkpoint', gcbc, '--offsets', '0', '1'],
                          capture_output=True, text=True, timeout=300)
    assert flat.returncode != 0
    assert flat.stderr.strip().splitlines()[-1] == f'distance_profile: {gcbc}: gcbc has no distance in steps (it runs flat): nothing to profile'
    far = subprocess.run([sys.executable, script, '--dataset', data, '--checkpoint', qrl, '--offsets', '0', '60'],
                         capture_output=True, text=True, timeout=300)
    assert far.stderr.strip().splitlines()[-1] == 'distance_profile: the data hold no trajectory of 61 states: lower --offsets'
