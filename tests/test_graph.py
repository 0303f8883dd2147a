"""Keypoints (IWE, FPS, random), the keypoint graph and Floyd-Warshall, against brute force and SciPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.sparse.csgraph import floyd_warshall as scipy_fw

from aqm_mjx.agent import plan
from aqm_mjx.mapping import graph, keypoints
from aqm_mjx.envs import mazes


# the next-hop table read back into paths (test helpers: the agent follows next_subgoal, not whole paths)
def extract_path(next_hop: jax.Array, i: jax.Array, j: jax.Array, max_len: int) -> tuple[jax.Array, jax.Array]:
    """Nodes of the shortest path from ``i`` to ``j``: ``[max_len]`` int32 padded with -1, and its
    number of nodes (0 if unreachable; a path longer than ``max_len`` is cut)."""
    reachable = (i >= 0) & (j >= 0) & (next_hop[jnp.maximum(i, 0), jnp.maximum(j, 0)] >= 0)

    def body(cur, _):
        nxt = jnp.where((cur >= 0) & (cur != j), next_hop[jnp.maximum(cur, 0), j], -1)
        return nxt, cur

    _, path = jax.lax.scan(body, jnp.where(reachable, i, -1).astype(jnp.int32), None, length=max_len)
    return path, jnp.sum(path >= 0).astype(jnp.int32)


def path_cost(weights: jax.Array, path: jax.Array) -> jax.Array:
    """Sum of edge weights along a -1-padded path ``[L]``."""
    a, b = path[:-1], path[1:]
    ok = (a >= 0) & (b >= 0)
    return jnp.sum(jnp.where(ok, weights[jnp.maximum(a, 0), jnp.maximum(b, 0)], 0.0))


def random_graphs(rng, b, k, p_edge=0.1):
    w = rng.uniform(0.5, 10.0, (b, k, k)).astype(np.float32)
    w[rng.random((b, k, k)) > p_edge] = np.inf
    return w


@pytest.mark.parametrize('k,b', [(8, 16), (37, 5), (40, 8), (256, 2)])
def test_floyd_warshall_equals_scipy_distances_and_paths(k, b):
    rng = np.random.default_rng(k)
    w = random_graphs(rng, b, k, p_edge=min(1.0, 4.0 / k))
    d, nxt = jax.jit(jax.vmap(plan.floyd_warshall))(jnp.asarray(w))
    d, nxt = np.asarray(d), np.asarray(nxt)
    for g in range(b):
        ref = scipy_fw(np.where(np.isfinite(w[g]), w[g], 0.0), directed=True)
        np.testing.assert_allclose(d[g], ref, rtol=1e-5)
    assert np.isinf(d).any() and np.isfinite(d[~np.eye(k, dtype=bool)[None].repeat(b, 0)]).any()
    # Every extracted path is a real path whose summed weight equals the distance.
    over_j = jax.vmap(lambda n, i, j: extract_path(n, i, j, k), (None, None, 0))
    ext = jax.jit(jax.vmap(jax.vmap(over_j, (None, 0, None)), (0, None, None)))
    idx = jnp.arange(k)
    paths, lens = ext(jnp.asarray(nxt), idx, idx)
    cost = jax.jit(jax.vmap(jax.vmap(jax.vmap(path_cost, (None, 0)), (None, 0))))(jnp.asarray(w), paths)  # graph, i, j
    paths, lens, cost = np.asarray(paths), np.asarray(lens), np.asarray(cost)
    finite = np.isfinite(d)
    np.testing.assert_allclose(cost[finite], d[finite], rtol=1e-4, atol=1e-4)
    assert np.all(lens[~finite] == 0)
    gi, ii, jj = np.nonzero(finite)
    assert np.all(paths[gi, ii, jj, 0] == ii)
    assert np.all(paths[gi, ii, jj, lens[gi, ii, jj] - 1] == jj)


def test_batched_and_single_entry_forms_agree():
    rng = np.random.default_rng(7)
    w = jnp.asarray(random_graphs(rng, 11, 30, p_edge=0.15))
    d, n = jax.vmap(plan.floyd_warshall)(w)
    db, nb = jax.jit(lambda x: plan.floyd_warshall_batch(x, chunk=4))(w)  # 11 graphs in chunks of 4
    np.testing.assert_array_equal(np.asarray(db), np.asarray(d))
    np.testing.assert_array_equal(np.asarray(nb), np.asarray(n))
    d_only, none = plan.floyd_warshall_batch(w, chunk=4, with_next=False)
    assert none is None
    np.testing.assert_array_equal(np.asarray(d_only), np.asarray(d))


def directed_grid_quasimetric(n=12):
    """Points on an n x n grid; moving +x costs 1, -x costs 3, +-y costs 1 (one-way-ish streets).
    Exact shortest paths: d((x1, y1), (x2, y2)) = max(dx, 0) + 3 max(-dx, 0) + |dy|."""
    pts = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing='ij'), -1).reshape(-1, 2).astype(np.float32)

    def d(a, b):
        dx, dy = b[0] - a[0], b[1] - a[1]
        return jnp.maximum(dx, 0) + 3 * jnp.maximum(-dx, 0) + jnp.abs(dy)

    return pts, d


@pytest.mark.parametrize('selector', ['iwe', 'fps'])
def test_iwe_separated_and_covering_brute_force(selector):
    pts, d = directed_grid_quasimetric()
    fn = keypoints.iwe if selector == 'iwe' else keypoints.farthest_point
    delta = 4.0
    kp = jax.jit(lambda k: fn(d, jnp.asarray(pts), k, delta, 64, chunk=50))(jax.random.PRNGKey(0))
    assert not bool(kp.overflow) and int(kp.uncovered) == 0
    dm = np.asarray(graph.pairwise(d, jnp.asarray(pts), jnp.asarray(pts)))
    dsym = np.maximum(dm, dm.T)
    zi = np.asarray(kp.index)[np.asarray(kp.mask)]
    sep = dsym[np.ix_(zi, zi)] + np.eye(len(zi)) * 1e9
    assert sep.min() >= delta  # delta-separated
    assert dsym[:, zi].min(axis=1).max() < delta  # every candidate within delta of a keypoint
    assert len(zi) == int(kp.count) and len(set(zi.tolist())) == len(zi)
    # IWE: each keypoint after the first attaches to an earlier one at distance >= delta (the wavefront).
    par, att = np.asarray(kp.parent)[: len(zi)], np.asarray(kp.attach)[: len(zi)]
    assert par[0] == -1 and np.all(par[1:] < np.arange(1, len(zi)))
    np.testing.assert_allclose(att[1:], dsym[zi[1:], zi[par[1:]]], rtol=1e-6)
    if selector == 'iwe':
        assert np.all(att[1:] >= delta) and np.all(att[1:] < 2 * delta)


def test_iwe_count_scales_like_area_over_delta_squared():
    """Euclidean metric on a uniform unit square. A delta-separated delta-cover of the square has
    count >= 1 / (pi delta^2) (covering) and <= (1 + delta)^2 / (pi delta^2 / 4) (packing)."""
    rng = np.random.default_rng(0)
    pts = jnp.asarray(rng.random((20000, 2)), jnp.float32)
    d = lambda a, b: jnp.linalg.norm(a - b)  # noqa: E731
    run = jax.jit(lambda k, dl: keypoints.iwe(d, pts, k, dl, 600, chunk=8192))
    c = {}
    for delta in (0.05, 0.1, 0.2):
        kp = run(jax.random.PRNGKey(1), delta)
        assert not bool(kp.overflow)
        c[delta] = int(kp.count) * delta ** 2
        assert 1 / np.pi <= c[delta] <= 4 * (1 + delta) ** 2 / np.pi, (delta, int(kp.count))
    # Scaling: count * delta^2 is the same constant within 25% across a 4x range of delta (16x in count).
    assert max(c.values()) / min(c.values()) < 1.25, c
    assert run._cache_size() == 1  # delta is data, not a recompile


def test_overflow_flag_and_random_and_batch_variants():
    pts, d = directed_grid_quasimetric()
    kp = keypoints.iwe(d, jnp.asarray(pts), jax.random.PRNGKey(0), 1.5, 10)
    assert bool(kp.overflow) and int(kp.count) == 10
    # how far 10 slots fell short, by hand: the grid's points that are no keypoint and lie at d_sym >= 1.5
    # from every keypoint (144 points, each keypoint covering itself and its 2-4 neighbours at most)
    dm = np.asarray(graph.pairwise(d, jnp.asarray(pts), jnp.asarray(pts)))
    zi = np.asarray(kp.index)[np.asarray(kp.mask)]
    left = np.maximum(dm, dm.T)[:, zi].min(axis=1) >= 1.5
    left[zi] = False
    assert int(kp.uncovered) == int(left.sum()) and 144 - 5 * 10 <= int(kp.uncovered) < 144 - 10
    # the coverage curve: after each keypoint the candidates outside the first i + 1 keypoints' delta
    curve = np.asarray(kp.left)
    for i in range(10):
        out = np.maximum(dm, dm.T)[:, zi[: i + 1]].min(axis=1) >= 1.5
        out[zi[: i + 1]] = False
        assert curve[i] == out.sum(), i
    assert curve[9] == int(kp.uncovered) and np.all(np.diff(curve) <= 0)
    # more slots do not change the greedy order: a 30-slot run's first 10 keypoints and curve are these
    more = keypoints.iwe(d, jnp.asarray(pts), jax.random.PRNGKey(0), 1.5, 30)
    np.testing.assert_array_equal(np.asarray(more.index)[:10], np.asarray(kp.index))
    np.testing.assert_array_equal(np.asarray(more.left)[:10], curve)
    r = keypoints.uniform_random(jnp.asarray(pts), jax.random.PRNGKey(0), 20, valid=jnp.arange(len(pts)) < 15)
    assert int(r.count) == 15 and set(np.asarray(r.index)[np.asarray(r.mask)].tolist()) == set(range(15))
    b = keypoints.iwe_best_of_batches(d, jnp.asarray(pts), jax.random.PRNGKey(0), 4.0, 64, n_batches=4, batch_size=64)
    idx = np.asarray(b.index)[np.asarray(b.mask)]
    assert len(idx) == int(b.count) > 1 and idx.max() < len(pts)
    dm = np.asarray(graph.pairwise(d, jnp.asarray(pts[idx]), jnp.asarray(pts[idx])))
    assert (np.maximum(dm, dm.T) + np.eye(len(idx)) * 1e9).min() >= 4.0


def test_graph_edges_and_parent_edges_and_components():
    pts, d = directed_grid_quasimetric()
    kp = keypoints.iwe(d, jnp.asarray(pts), jax.random.PRNGKey(0), 4.0, 64)
    z = jnp.asarray(pts)[jnp.maximum(kp.index, 0)]
    w = np.asarray(graph.build_graph(d, z, kp.mask, 4.0))
    m = np.asarray(kp.mask)
    dm = np.asarray(graph.pairwise(d, z, z))
    dsym = np.maximum(dm, dm.T)
    off = m[:, None] & m[None, :] & ~np.eye(64, dtype=bool)
    np.testing.assert_array_equal(np.isfinite(w) & off, (dsym < 8.0) & off)  # tau = 2 delta
    np.testing.assert_allclose(w[np.isfinite(w) & off], dm[np.isfinite(w) & off])  # directed weights
    assert np.any(w[np.isfinite(w) & off] != w.T[np.isfinite(w) & off])  # asymmetric where the metric is
    assert np.all(np.isinf(w[~m]))
    _, n = graph.components(jnp.asarray(w), kp.mask)
    assert int(n) == 1
    # A tiny tau leaves isolated nodes; parent edges reconnect everything.
    w_small = graph.build_graph(d, z, kp.mask, 4.0, tau=1.0)
    _, n_small = graph.components(w_small, kp.mask)
    assert int(n_small) == int(kp.count)
    _, n_par = graph.components(graph.build_graph(d, z, kp.mask, 4.0, tau=1.0, keypoints=kp), kp.mask)
    assert int(n_par) == 1


def test_attach_plan_and_next_subgoal_on_a_line():
    # Keypoints on a line at x = 0, 2, 4, 6, 8; Euclidean; tau = 2.5.
    z = jnp.array([[0.0], [2.0], [4.0], [6.0], [8.0]])
    d = lambda a, b: jnp.abs(a[0] - b[0])  # noqa: E731
    mask = jnp.ones(5, bool)
    w = graph.build_graph(d, z, mask, delta=1.25)
    dk, nxt = plan.floyd_warshall(w)
    fs, tg, direct = plan.attach(d, z, mask, jnp.array([-0.5]), jnp.array([8.5]), tau=2.5)
    np.testing.assert_array_equal(np.isfinite(np.asarray(fs)), [1, 0, 0, 0, 0])  # d_sym < tau only to z_0
    p = plan.plan(dk, fs, tg, direct)
    assert int(p.first) == 0 and int(p.last) == 4 and not bool(p.direct)
    np.testing.assert_allclose(float(p.cost), 9.0, rtol=1e-6)
    hops = [int(p.first)]
    while hops[-1] != -1:
        hops.append(int(plan.next_subgoal(nxt, jnp.asarray(hops[-1]), p.last)))
    assert hops == [0, 1, 2, 3, 4, -1]
    # Pruning the edge 2 -> 3 (as a blocked corridor) makes the goal unreachable on a line.
    dk2, _ = plan.floyd_warshall(w.at[2, 3].set(jnp.inf))
    p2 = plan.plan(dk2, fs, tg, direct)
    assert not bool(p2.reachable) and int(p2.first) == -1
    # Close start and goal: go direct.
    fs, tg, direct = plan.attach(d, z, mask, jnp.array([3.0]), jnp.array([4.5]), tau=2.5)
    assert bool(plan.plan(dk, fs, tg, direct).direct)


@pytest.mark.parametrize('maze', mazes.MAZE_NAMES)
def test_maze_graph_connected_at_two_delta(maze):
    """Exact maze distance as the quasimetric: IWE + tau = 2 delta gives a connected graph (one
    component per connected region of free space: the teleport maze has 2 without its portals)."""
    grid = mazes.layout(maze)
    sub = 4
    table = jnp.asarray(mazes.geodesic_table(grid, sub))
    rng = np.random.default_rng(0)
    free = np.argwhere(grid == 0)
    xy = mazes.ij_to_xy(free[rng.integers(len(free), size=20000)]) + rng.uniform(-2, 2, (20000, 2))
    cand = jnp.asarray(mazes.xy_to_subcell(xy, grid.shape, sub))[:, None]
    d = lambda a, b: table[a[0], b[0]]  # noqa: E731
    regions = 2 if maze == 'teleport' else 1
    t1 = mazes.geodesic_table(grid, 1)
    free = np.flatnonzero(grid.reshape(-1) == 0)
    assert len({tuple(np.isfinite(t1[f, free])) for f in free}) == regions
    # Paper scale: delta = 15 control steps; the ant walks about 1.4 m/s = 0.14 m per step -> 2.1 m.
    for delta_m in (2.1, 4.0):
        kp = keypoints.iwe(d, cand, jax.random.PRNGKey(0), delta_m, 400)
        z = cand[jnp.maximum(kp.index, 0)]
        w = graph.build_graph(d, z, kp.mask, delta_m)
        _, n = graph.components(w, kp.mask)
        print(f'{maze}: delta {delta_m} m (~{delta_m / 0.14:.0f} steps) -> {int(kp.count)} keypoints, {int(n)} component(s)')
        assert not bool(kp.overflow) and int(n) == regions


def test_pad_and_trim_are_inverse_and_padding_is_inert():
    w = jnp.array([[0.0, 2.0, jnp.inf], [1.0, 0.0, 3.0], [jnp.inf, jnp.inf, 0.0]])
    g = graph.Graph(z=jnp.arange(6.0).reshape(3, 2), obs=jnp.ones((3, 4)), mask=jnp.array([True, True, False]), w=w,
                    tau=jnp.float32(2.0))
    p = graph.pad(g, 5)
    assert p.mask.tolist() == [True, True, False, False, False] and p.z.shape == (5, 2) and p.obs.shape == (5, 4)
    np.testing.assert_array_equal(p.w[:3, :3], w)
    assert not np.isfinite(np.asarray(p.w[3:])).any() and not np.isfinite(np.asarray(p.w[:, 3:])).any()
    # shortest paths among the original slots do not change
    np.testing.assert_array_equal(plan.floyd_warshall(p.w)[0][:3, :3], plan.floyd_warshall(w)[0])
    back = graph.trim(p, 3)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(g)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match='cannot pad'):
        graph.pad(g, 2)


def test_map_stage_selects_with_every_selector_including_the_papers_batches():
    from aqm_mjx.mapping.build import MapConfig, keypoint_graph

    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 20, (3000, 2)).astype(np.float32)
    d = lambda x, y: jnp.linalg.norm(x - y)  # noqa: E731
    lat = jnp.asarray(pts)
    for sel in ('iwe', 'iwe-batches', 'fps', 'random'):
        cfg = MapConfig(delta=3.0, max_keypoints=128, selector=sel, iwe_batches=4, iwe_batch_size=256)
        g, kp = jax.jit(lambda l, k: keypoint_graph(d, l, l, k, cfg))(lat, jax.random.PRNGKey(1))
        k = int(kp.count)
        assert 1 < k <= 128 and float(g.tau) == 6.0
        # keypoints are candidates (indices into the latents), joined under tau = 2 delta
        np.testing.assert_array_equal(np.asarray(g.z)[:k], pts[np.asarray(kp.index)[:k]])
        if sel == 'iwe-batches':  # the paper's procedure: the best of 4 IWE runs on 256-state batches
            want = keypoints.iwe_best_of_batches(d, lat, jax.random.PRNGKey(1), 3.0, 128, 4, 256)
            assert int(want.count) == k and np.array_equal(want.index, kp.index)


def test_node_count_joins_earlier_rows_only_when_they_evaluated_the_same_episodes(tmp_path):
    import importlib.util  # pylint: disable=import-outside-toplevel
    import json  # pylint: disable=import-outside-toplevel
    import os  # pylint: disable=import-outside-toplevel

    spec = importlib.util.spec_from_file_location('node_count', os.path.join(
        os.path.dirname(__file__), '..', 'benchmarks', 'experiments', 'node_count.py'))
    nc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(nc)
    args = dict(episodes=10, split='report', backend='ogbench', seed=0, deltas=[12.0])
    row = dict(method='aqm', nodes=193, success=0.7, ci95=[0.56, 0.81], fw_s=0.0026, bytes_per_env=483_000)
    path = tmp_path / 'node_count.json'
    path.write_text(json.dumps(dict(rows=[row], args=dict(args, deltas=[8.0, 12.0]))))
    (got,) = nc.earlier_rows(str(path), dict(args, deltas=[]))  # other settings are fine
    assert got == dict(row, from_file=str(path))
    with pytest.raises(ValueError, match="split 'dev' there, 'report' here"):
        path.write_text(json.dumps(dict(rows=[row], args=dict(args, split='dev'))))
        nc.earlier_rows(str(path), args)
    with pytest.raises(ValueError, match='not a node_count.json'):
        path.write_text(json.dumps(dict(rows=[], args=args)))
        nc.earlier_rows(str(path), args)


def test_pairwise_in_row_chunks_equals_the_whole_matrix_and_holds_a_chunk_of_activations():
    """A distance that runs a network on each pair (as GCIVL's value on raw states does) gives the same
    [K, M] matrix row-chunked as all at once, with K not a multiple of the chunk, and its compiled
    program's temporary memory is a chunk's activations, not the K x M pairs' (at K = 2,048 and
    a 1,536-wide layer the whole matrix at once asked for 25 GB)."""
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
    width = 512
    w1 = jax.random.normal(k1, (2 * 6, width)) / 4.0
    w2 = jax.random.normal(k2, (width,)) / 20.0

    def d(x, y):
        return jnp.abs(jnp.tanh(jnp.concatenate([x, y]) @ w1) @ w2)

    a = jax.random.normal(k3, (37, 6))
    b = a[::-1][:29]
    whole = jax.vmap(lambda x: jax.vmap(lambda y: d(x, y))(b))(a)
    got = graph.pairwise(d, a, b, rows=8)
    assert got.shape == (37, 29)
    np.testing.assert_allclose(np.asarray(got), np.asarray(whole), rtol=1e-6, atol=1e-6)
    assert np.array_equal(np.asarray(graph.pairwise(d, a, b, rows=100)), np.asarray(graph.pairwise(d, a, b, rows=37)))

    big = jax.random.normal(k3, (256, 6))
    mem = {}
    for name, fn in (('whole', lambda z: jax.vmap(lambda x: jax.vmap(lambda y: d(x, y))(z))(z)),
                     ('rows', lambda z: graph.pairwise(d, z, z, rows=16))):
        analysis = jax.jit(fn).lower(big).compile().memory_analysis()
        if analysis is None:
            pytest.skip('this backend reports no memory analysis')
        mem[name] = analysis.temp_size_in_bytes
    pairs_activations = 256 * 256 * width * 4  # the whole matrix's hidden layer, float32
    assert mem['whole'] >= pairs_activations / 2, mem  # the reference does hold the K x M activations
    assert mem['rows'] <= pairs_activations / 8, mem  # 16 rows of 256: 1/16 of them, with room


def test_trimmed_map_says_how_many_candidates_the_slots_left_uncovered():
    """The info an evaluation prints when IWE runs out of slots: ``uncovered`` of ``candidates`` states,
    recomputed from the keypoints' candidates by hand; 0 once the slots suffice."""
    from aqm_mjx.interface import Agent
    from aqm_mjx.mapping.build import MapConfig, candidate_rows, trimmed_map

    pts, d = directed_grid_quasimetric()
    agent = Agent(lambda aux, o: o, lambda aux, x, y: d(x, y), None, None)
    key = jax.random.PRNGKey(3)
    cfg = MapConfig(delta=1.5, max_keypoints=16, candidates=100)
    g, info = trimmed_map(agent, jnp.asarray(pts), cfg, key)
    assert info['overflow'] and info['keypoints'] == 16 and info['candidates'] == 100
    cand = pts[np.asarray(candidate_rows(len(pts), cfg, key))]
    dm = np.asarray(graph.pairwise(d, jnp.asarray(cand), jnp.asarray(np.asarray(g.obs)[np.asarray(g.mask)])))
    dt = np.asarray(graph.pairwise(d, jnp.asarray(np.asarray(g.obs)[np.asarray(g.mask)]), jnp.asarray(cand)))
    near = np.maximum(dm, dt.T).min(axis=1)
    left = (near >= 1.5) & (near > 0)  # a keypoint's own candidate is at distance 0
    assert info['uncovered'] == int(left.sum()) > 0
    _, enough = trimmed_map(agent, jnp.asarray(pts), MapConfig(delta=1.5, max_keypoints=144, candidates=100), key)
    assert not enough['overflow'] and enough['uncovered'] == 0 and enough['keypoints'] <= 100
