"""The evaluation protocol: shift suites, the episode table, chunk- and device-invariance, the CLI."""

import dataclasses
import io
import os
import json
import time
import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tqdm import tqdm

from aqm_mjx import cli, envs, pipeline
from aqm_mjx.agent import oracle
from aqm_mjx.agent.rules import MAX_CUTS, AgentConfig
from aqm_mjx.data import synthetic
from aqm_mjx.envs import mazes, shifts
from aqm_mjx.evaluation import calibration, evaluate, protocol
from aqm_mjx.learn import fit
from aqm_mjx.mapping.build import MapConfig, build_map
from aqm_mjx.progress import ChunkBar, tick


# ------------------------------------------------------------------------------------------ shifts
@pytest.mark.parametrize('maze', ['medium', 'large', 'giant'])
def test_shift_suite_keeps_tasks_solvable_and_changes_routes(maze):
    base = mazes.layout(maze)
    ref = shifts.route_lengths(base, maze)
    suite = shifts.suite(maze)
    closes = [k for k in suite if k.startswith('close')]
    opens = [k for k in suite if k.startswith('open')]
    assert list(suite)[0] == 'base' and np.array_equal(suite['base'], base)
    assert len(closes) >= 1 and len(opens) >= 1
    for name in closes + opens:
        g = suite[name]
        _, i, j = name.split('-')
        diff = np.argwhere(g != base)
        assert diff.tolist() == [[int(i), int(j)]]  # exactly one cell changed, the one named
        mazes.validate_grid(g, maze)
        lengths = shifts.route_lengths(g, maze)
        assert (lengths > 0).all()  # every task stays solvable: an alternative route exists
        if name.startswith('close'):
            assert base[int(i), int(j)] == 0 and (lengths >= ref).all() and (lengths > ref).any()
            free = np.argwhere(g == 0)
            assert (mazes.bfs_from(g, tuple(free[0])) >= 0).sum() == len(free)  # nothing cut off
        else:
            assert base[int(i), int(j)] == 1 and (lengths <= ref).all() and (lengths < ref).any()


def test_medium_shift_by_hand():
    # medium task 1 runs (1,1) -> (6,6) in 10 BFS steps; closing corridor cell (3, 3) forces a detour
    assert shifts.route_lengths(mazes.layout('medium'), 'medium').tolist() == [10, 10, 6, 10, 8]
    g = shifts.variant('medium', 'close-3-3')
    assert g[3, 3] == 1 and shifts.route_lengths(g, 'medium')[0] > 10
    with pytest.raises(ValueError, match="unknown shift 'close-1-1'.*its suite is: base, close-"):
        shifts.variant('medium', 'close-1-1')  # a task's start cell
    with pytest.raises(ValueError, match='teleport'):
        shifts.suite('teleport')


def test_shift_names_pick_layouts():
    """--shift: 'closures' is the training layout and the suite's closed corridors; a comma list
    picks layouts in its order; repeats, empty and unknown names are refused by name."""
    from aqm_mjx import assess
    assert list(assess.variants_for('medium', 'closures')) == ['base', 'close-3-3', 'close-5-4', 'close-6-2']
    v = assess.variants_for('medium', 'close-6-2, base')
    assert list(v) == ['close-6-2', 'base'] and v['close-6-2'][6, 2] == 1 and v['base'][6, 2] == 0
    assert list(assess.variants_for('medium', 'all')) == list(shifts.suite('medium'))
    with pytest.raises(ValueError, match=r"\['base'\] named twice"):
        assess.variants_for('medium', 'base,base')
    with pytest.raises(ValueError, match='an empty name'):
        assess.variants_for('medium', 'base,')
    with pytest.raises(ValueError, match="unknown shift 'close-1-1'"):
        assess.variants_for('medium', 'base,close-1-1')


def test_curve_setup_is_the_development_split_without_pruning():
    """A learning-curve point (and benchmarks/experiments/map_key.py, which re-runs it): development
    episodes, no ablations or calibration, the curve's backend, kappa infinite and patience 0, and the
    key split in two (map, episodes); everything else as the run's config."""
    import math
    from aqm_mjx import assess
    cfg = pipeline.RunConfig()
    cfg = dataclasses.replace(cfg, protocol=dataclasses.replace(
        cfg.protocol, curve_episodes=3, episodes=50, ablations=('no-pruning',), calibrate='stall', split='report',
        backend='mjx', curve_backend='ogbench'))
    key = jax.random.PRNGKey(7)
    proto, agent_cfg, k_map, k_eval = assess.curve_setup(cfg, key)
    assert (proto.episodes, proto.ablations, proto.calibrate, proto.split, proto.backend) == (
        3, (), 'none', 'dev', 'ogbench')
    assert proto.horizon == cfg.protocol.horizon and proto.tasks == cfg.protocol.tasks
    assert agent_cfg.kappa == math.inf and agent_cfg.patience == 0.0
    assert agent_cfg.switch_radius == cfg.agent.switch_radius
    want = jax.random.split(key)
    assert (np.asarray(k_map) == np.asarray(want[0])).all() and (np.asarray(k_eval) == np.asarray(want[1])).all()
    assert assess.curve_setup(cfg, key, episodes=8)[0].episodes == 8
    no_curve_backend = dataclasses.replace(cfg, protocol=dataclasses.replace(cfg.protocol, curve_backend=''))
    assert assess.curve_setup(no_curve_backend, key)[0].backend == 'mjx'


# ------------------------------------------------------------------------------------ the table
def test_steps_per_s_counts_every_chunk_and_step_over_the_whole_evaluation():
    # 2 chunks x 50 environments x 1,000 steps in 25 s; one chunk in 20 s
    assert evaluate.steps_per_s(dict(chunks=2, envs_per_chunk=50, steps=1000, total_s=25.0)) == 4000.0
    assert evaluate.steps_per_s(dict(chunks=1, envs_per_chunk=50, steps=1000, total_s=20.0)) == 2500.0


def test_config_and_episode_table():
    specs = protocol.agent_specs(0.5, ('no-pruning', 'flat', 'kappa=1'))
    assert [s[0] for s in specs] == ['aqm', 'no-pruning', 'flat', 'kappa=1']
    assert specs[0][1] == 0.5 and specs[1][1] == np.inf and specs[2][2] is False and specs[3][1] == 1.0
    t = protocol.episode_table(specs, 2, [1, 3], 5)
    assert len(t.task) == 4 * 2 * 2 * 5
    # every agent gets the same episodes (same key ids), and (variant, task, episode) ids are distinct
    ids = t.seed_id.reshape(4, -1)
    assert (ids == ids[0]).all() and len(set(ids[0].tolist())) == 2 * 2 * 5
    # groups are the cells of the [agents, layouts, tasks] rate table, 5 episodes each
    assert np.bincount(t.group).tolist() == [5] * (4 * 2 * 2) and t.group[5 * 3] == 3
    assert t.patience.tolist() == [0.0] * len(t.task)  # the fixed rule unless asked
    stall = protocol.agent_specs(0.5, ('stall=40', 'no-pruning'), patience=25.0)
    assert [s[:4] for s in stall] == [('aqm', 0.5, True, 25.0), ('stall=40', 0.5, True, 40.0),
                                      ('no-pruning', np.inf, True, 0.0)]
    assert protocol.episode_table(stall, 1, [1], 2).patience.tolist() == [25, 25, 40, 40, 0, 0]
    # the paper's rule: keypoint edges alone, one cut, at a fixed kappa or the one calibrated on edges;
    # the AQM row's parallel cuts go to its own ablations (kappa=, stall=) but never to the paper's
    rows = protocol.agent_specs(1.0, ('paper=0.25', 'paper=cal', 'kappa=2', 'no-pruning'), patience=30.0,
                                cut_slack=0.6)
    assert [(r.name, r.kappa, r.patience, r.edges_only, r.cut_slack, r.calibrated) for r in rows] == [
        ('aqm', 1.0, 30.0, False, 0.6, ''), ('paper=0.25', 0.25, 0.0, True, 0.0, ''),
        ('paper=cal', 1.0, 0.0, True, 0.0, 'paper'), ('kappa=2', 2.0, 0.0, False, 0.6, ''),
        ('no-pruning', np.inf, 0.0, False, 0.0, '')]
    t = protocol.episode_table(rows, 1, [1], 1)
    assert t.edges_only.tolist() == [False, True, True, False, False]
    assert t.calibrated.tolist() == [0, 0, protocol.CALIBRATED.index('paper'), 0, 0]
    eps = protocol.Episodes({'base': mazes.layout('medium')}, mazes.layout('medium')[None], [1], rows, t, 10)
    inputs = protocol.table_inputs(eps, jax.random.PRNGKey(0), budgets=dict(paper=(3.5, 0.0), stall=(9.0, 9.0)))
    np.testing.assert_allclose(inputs.kappa, [1.0, 0.25, 3.5, 2.0, np.inf])  # only the paper=cal row takes it
    np.testing.assert_allclose(inputs.cut_slack, [0.6, 0, 0, 0.6, 0])
    assert protocol.needs_calibration(protocol.ProtocolConfig(ablations=('paper=cal',)))
    assert not protocol.needs_calibration(protocol.ProtocolConfig(ablations=('paper=1',)))
    for bad, msg in ((dict(ablations=('greedy',)), 'unknown ablation'), (dict(ablations=('kappa=x',)), 'number'),
                     (dict(episodes=0), 'episodes'), (dict(ablations=('flat', 'flat')), 'repeat'),
                     (dict(horizon=-1), 'horizon'), (dict(ablations=('stall=0',)), 'patience must be > 0'),
                     (dict(ablations=('stall=inf',)), 'finite')):
        with pytest.raises(ValueError, match=msg):
            protocol.ProtocolConfig(**bad)
    with pytest.raises(ValueError, match='selector'):
        MapConfig(selector='kmeans')


def test_the_bar_moves_inside_a_1000_step_chunk():
    """A jitted 1000-step scan over 8 vmapped environments (a few matmuls a step) with the hook of
    the rollouts: it fires after every 50 steps, once per step and not once per environment, the
    bar only moves forward, its updates are spread over the call, and it ends 8 episodes further.
    (The evaluation programs' own counts: test_protocol_results_do_not_depend_on_chunking.)"""
    bar = types.SimpleNamespace(n=0.0, seen=[])

    def update(k):
        bar.n += k
        bar.seen.append((time.perf_counter(), bar.n))

    bar.update = update
    ticks = ChunkBar(bar)

    def episode(x):
        def body(x, t):
            x = jnp.tanh(x @ x.T @ x / x.shape[0])
            tick(ticks, t, 1000)
            return x, None
        return jax.lax.scan(body, x, jnp.arange(1000))[0]

    run = jax.jit(jax.vmap(episode))
    x = jax.random.normal(jax.random.PRNGKey(0), (8, 96, 96))
    jax.block_until_ready(run(x))  # compile (its calls reach the bar too; start afresh)
    bar.seen.clear()
    ticks.calls, ticks.shown, bar.n = 0, 0.0, 0.0
    ticks.start(8, 1000)
    t0 = time.perf_counter()
    jax.block_until_ready(run(x))
    t1 = time.perf_counter()
    during = list(bar.seen)
    ticks.finish()
    assert ticks.calls == 20 and len(during) >= 10
    ns = [n for _, n in bar.seen]
    assert ns == sorted(ns) and ns[-1] == pytest.approx(8.0) and during[0][1] == pytest.approx(8 * 50 / 1000)
    assert during[-1][0] - during[0][0] > 0.5 * (t1 - t0), (during[0][0] - t0, during[-1][0] - t0, t1 - t0)


def test_the_bar_ends_exactly_at_its_total_after_many_chunks():
    """Ten chunks of 160 episodes, ticks every 20 of 1,000 steps: fractional steps that used to add up
    to 1600.0000000000143 and make tqdm warn 'clamping frac to range [0, 1]'. The bar must end on
    exactly 1,600, never pass it, and stand on a whole episode count after every chunk."""
    bar = tqdm(total=1600, file=io.StringIO(), mininterval=0)
    ticks = ChunkBar(bar)
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # the TqdmWarning would fail the test
        for chunk in range(10):
            ticks.start(160, 1000)
            for done in range(20, 1001, 20):
                ticks(done)
                assert bar.n <= 1600
            ticks.finish()
            assert bar.n == 160 * (chunk + 1)
        bar.close()
    assert ticks.calls == 500


def test_the_bar_says_the_first_chunk_compiles_until_it_runs():
    """Before the first chunk's first callback the bar's postfix names the compile; the first reported
    steps clear it, and later chunks never show it."""
    out = io.StringIO()
    bar = tqdm(total=20, file=out, mininterval=0)
    ticks = ChunkBar(bar)
    ticks.start(10, 100)
    assert bar.postfix == ChunkBar.COMPILING and ChunkBar.COMPILING in out.getvalue()
    ticks(50)
    assert not bar.postfix
    ticks.finish()
    ticks.start(10, 100)
    assert not bar.postfix
    ticks.finish()
    bar.close()


def test_chunking_by_hand():
    """250 episodes at 125 environments: 2 chunks of 125; at 250: one; 8 episodes at 4 on 8 devices:
    the chunk rounds up to 8, one chunk; 10 at 3 on 2 devices: chunks of 4, three of them."""
    assert evaluate.chunking(250, 125) == (125, 2)
    assert evaluate.chunking(250, 250) == (250, 1)
    assert evaluate.chunking(250, 1000) == (250, 1)
    assert evaluate.chunking(8, 4, 8) == (8, 1)
    assert evaluate.chunking(10, 3, 2) == (4, 3)


def test_calibration_by_hand():
    """Legs (d, steps, longest stall): the fixed rule's kappa is the (1 - q) quantile of steps / d
    minus 1, the stall rule's patience the (1 - q) quantile of the longest stall; padding, zero-length
    legs and masked rows are left out; the same numbers under jit."""
    rng = np.random.default_rng(0)
    d = rng.uniform(5, 30, 400).astype(np.float32)
    ratio = rng.uniform(1.0, 3.0, 400).astype(np.float32)
    stall = rng.integers(0, 60, 400).astype(np.float32)
    legs = np.stack([d, d * ratio, stall], -1).reshape(20, 20, 3)
    legs[:, 15:] = -1.0  # 5 unused slots per episode
    legs[0, 0, 0] = 0.0  # a zero-length leg
    used = legs.reshape(-1, 3)[np.asarray(calibration.valid(legs)).reshape(-1)]
    assert len(used) == 20 * 15 - 1
    c = calibration.calibrate(legs, 0.05)
    assert int(c['legs']) == 299
    r = used[:, 1] / used[:, 0]
    assert float(c['kappa']) == pytest.approx(np.quantile(r, 0.95) - 1, rel=1e-5)
    assert float(c['patience']) == pytest.approx(np.quantile(used[:, 2], 0.95), rel=1e-5)
    np.testing.assert_allclose(c['ratio_q'], np.quantile(r, calibration.QUANTILES), rtol=1e-5)
    # a row mask keeps only those episodes; jit gives the same
    rows = np.arange(20) < 10
    cj = jax.jit(lambda x, m: calibration.calibrate(x, 0.05, m))(legs, rows)
    sub = legs[:10, :15].reshape(-1, 3)[1:]
    assert int(cj['legs']) == 149
    assert float(cj['kappa']) == pytest.approx(np.quantile(sub[:, 1] / sub[:, 0], 0.95) - 1, rel=1e-5)
    with pytest.raises(ValueError, match='false_alarm'):
        calibration.calibrate(legs, 0.0)
    # no leg at all (an agent that completed none): NaN settings and 0 legs, not an indexing error
    for empty in (np.zeros((0, 3), np.float32), np.full((4, 3), -1.0, np.float32)):
        e = calibration.calibrate(empty, 0.02)
        assert int(e['legs']) == 0 and np.isnan(float(e['kappa'])) and np.isnan(float(e['patience']))


def test_stall_scale_sets_patience_to_a_multiple_of_the_90th_percentile():
    """With a stall scale C the stall rule's patience is C x the 90th percentile of the longest
    stall (by hand on a recomputable log), the kappas still read the false-alarm quantile, the same
    under jit, through budget() rounded to a step, and bad scales are refused by name."""
    stall = np.arange(1, 101, dtype=np.float32)  # longest stalls 1..100: q90 = 90.1 (linear interpolation)
    legs = np.stack([np.full(100, 10.0, np.float32), np.linspace(10, 40, 100, dtype=np.float32), stall], -1)
    assert np.quantile(stall, 0.9) == pytest.approx(90.1)
    c = calibration.calibrate(legs, 0.05, stall_scale=2.5)
    assert float(c['patience']) == pytest.approx(2.5 * 90.1, rel=1e-5)
    assert float(c['kappa']) == pytest.approx(np.quantile(legs[:, 1] / 10.0, 0.95) - 1, rel=1e-5)
    assert float(calibration.calibrate(legs, 0.05)['patience']) == pytest.approx(np.quantile(stall, 0.95), rel=1e-5)
    cj = jax.jit(lambda x: calibration.calibrate(x, 0.05, stall_scale=2.5))(legs)
    assert float(cj['patience']) == pytest.approx(225.25, rel=1e-5)
    kappa, patience = calibration.budget(c, 'stall', 1.0, 0.0)
    assert (float(kappa), float(patience)) == (1.0, 225.0)
    # a tiny stall scale still gives a patience of at least one step
    assert float(calibration.calibrate(legs, 0.05, stall_scale=1e-3)['patience']) == 1.0
    for bad in (-1.0, float('nan'), float('inf')):
        with pytest.raises(ValueError, match='stall_scale'):
            calibration.calibrate(legs, 0.05, stall_scale=bad)
        with pytest.raises(ValueError, match='stall_scale'):
            protocol.ProtocolConfig(stall_scale=bad)


def test_calibration_never_draws_an_evaluation_task_or_key(monkeypatch):
    """The calibration pass runs between cells of the training layout that no evaluation task starts
    or ends in, at least MIN_PAIR_CELLS BFS steps apart, on keys that are neither split's; the pass
    hands exactly these episodes and that key to the evaluation (checked on its inputs)."""
    env = envs.make('pointmaze-medium')
    p = protocol.ProtocolConfig(episodes=20, calibrate='stall', calibration_episodes=300)
    cal = protocol.calibration_episodes(env, p)
    key = jax.random.PRNGKey(7)
    inputs = protocol.table_inputs(cal, jax.random.fold_in(key, protocol.CALIBRATION_FOLD))
    assert (np.asarray(inputs.task_ids) == 0).all() and np.isinf(np.asarray(inputs.kappa)).all()
    used = {t.init_ij for t in mazes.tasks('medium')} | {t.goal_ij for t in mazes.tasks('medium')}
    cells = np.asarray(inputs.cells)
    layout = mazes.layout('medium')
    for c in cells:
        a, b = (int(c[0]), int(c[1])), (int(c[2]), int(c[3]))
        assert a not in used and b not in used and layout[a] == 0 and layout[b] == 0
        assert mazes.bfs_from(layout, a)[b] >= protocol.MIN_PAIR_CELLS
    assert len({tuple(c) for c in cells.tolist()}) > 150  # many pairs, not a handful
    # every pair of the maze could be drawn; none is an evaluation task's
    pairs = {tuple(x) for x in protocol.calibration_pairs(layout, 'medium').tolist()}
    assert not pairs & {t.init_ij + t.goal_ij for t in mazes.tasks('medium')}
    # no calibration episode shares a key with an evaluation episode of either split
    ev = protocol.plan_episodes(env, p, 1.0)
    cal_keys = {k.tobytes() for k in np.asarray(inputs.keys)}
    for split in protocol.SPLITS:
        ev_keys = {k.tobytes() for k in np.asarray(protocol.table_inputs(ev._replace(split=split), key).keys)}
        assert not cal_keys & ev_keys
    dev, rep = (np.asarray(protocol.table_inputs(ev._replace(split=s), key).keys) for s in protocol.SPLITS)
    assert not {k.tobytes() for k in dev} & {k.tobytes() for k in rep}  # the two splits are other episodes
    # calibration_pass hands these episodes and this key to the evaluation
    seen = {}

    def fake_evaluate(env_, agent, graph, cfg, proto, variants=None, key=None, episodes=None, **kw):
        seen.update(episodes=episodes, key=key, kappa=cfg.kappa, label=kw.get('label'))
        legs = np.tile(np.array([[10.0, 12.0, 3.0, 1.0]], np.float32), (len(episodes.table.task), 1, 1))
        return types.SimpleNamespace(legs=legs, table=episodes.table)

    monkeypatch.setattr(evaluate, 'evaluate', fake_evaluate)
    out = evaluate.calibration_pass(env, types.SimpleNamespace(plans=True, prunes=True), None, AgentConfig(kappa=1.0), p, key,
                                    progress=False)
    assert np.isinf(seen['kappa']) and (seen['episodes'].table.task == 0).all()
    assert seen['label'] == 'calibration pass'  # its progress bar is not read as a second evaluation
    assert np.asarray(seen['key']).tobytes() == np.asarray(jax.random.fold_in(key, protocol.CALIBRATION_FOLD)).tobytes()
    np.testing.assert_array_equal(protocol.table_inputs(seen['episodes'], seen['key']).cells, inputs.cells)
    assert out['patience'] == 3.0 and out['kappa_edges'] == pytest.approx(0.2) and out['legs'] == 300


def test_reset_from_cells_in_both_backends():
    """Task id 0 starts and ends in the given cells, with the tasks' noise (MJX and OGBench's own env)."""
    env = envs.make('pointmaze-medium')
    s = jax.jit(env.reset)(jax.random.PRNGKey(0), 0, None, jnp.array([1, 1, 5, 6]))
    noise = mazes.START_GOAL_NOISE * mazes.MAZE_UNIT / 4 + 1e-5
    assert np.abs(np.asarray(s.data.qpos[:2]) - mazes.ij_to_xy((1, 1))).max() <= noise
    assert np.abs(np.asarray(s.goal_xy) - mazes.ij_to_xy((5, 6))).max() <= noise
    t = jax.jit(env.reset)(jax.random.PRNGKey(0), 2, None, jnp.array([1, 1, 5, 6]))  # a task id wins over cells
    task = mazes.tasks('medium')[1]
    assert np.abs(np.asarray(t.goal_xy) - mazes.ij_to_xy(task.goal_ij)).max() <= noise
    from aqm_mjx.envs.ogbench_env import OGBenchEnvs  # pylint: disable=import-outside-toplevel

    og = OGBenchEnvs('pointmaze-medium')
    try:
        _, _, goal_xy = og.reset([3, 4], [0, 2], np.stack([mazes.layout('medium')] * 2), [[1, 1, 5, 6], [0, 0, 0, 0]])
    finally:
        og.close()
    assert np.abs(goal_xy[0] - mazes.ij_to_xy((5, 6))).max() <= noise
    assert np.abs(goal_xy[1] - mazes.ij_to_xy(task.goal_ij)).max() <= noise


def test_calibrated_budget_by_hand():
    """The AQM row's budget from a calibration: the fixed rule's kappa rounded to 0.01 (patience 0),
    the stall rule's patience rounded to a step (kappa kept, 1 where it is inf); without a single
    leg (NaN) or with rule 'none', the configured budget; the same under jit; bad settings named."""
    cal = dict(kappa=jnp.float32(0.456), patience=jnp.float32(12.4))
    assert np.allclose(calibration.budget(cal, 'fixed', 1.0, 7.0), (0.46, 0.0))
    assert np.allclose(calibration.budget(cal, 'stall', 1.0, 0.0), (1.0, 12.0))
    assert np.allclose(calibration.budget(cal, 'stall', np.inf, 0.0), (1.0, 12.0))  # inf would unbudget the legs
    assert np.allclose(calibration.budget(cal, 'none', 0.5, 3.0), (0.5, 3.0))
    nan = dict(kappa=jnp.float32(np.nan), patience=jnp.float32(np.nan))
    for rule in ('fixed', 'stall'):
        assert np.allclose(calibration.budget(nan, rule, 0.5, 3.0), (0.5, 3.0))
    jitted = jax.jit(lambda c: calibration.budget(c, 'stall', 2.0, 0.0))(dict(kappa=jnp.float32(3.0),
                                                                          patience=jnp.float32(40.6)))
    assert np.allclose(jitted, (2.0, 41.0))
    with pytest.raises(ValueError, match='unknown calibration rule'):
        calibration.budget(cal, 'median', 1.0, 0.0)
    for bad, match in ((dict(calibrate='median'), 'calibrate'), (dict(false_alarm=0.0), 'false_alarm'),
                       (dict(false_alarm=1.0), 'false_alarm'), (dict(calibration_episodes=0), 'calibration_episodes')):
        with pytest.raises(ValueError, match=match):
            protocol.ProtocolConfig(**bad)
    cal_proto = protocol.calibration_protocol(protocol.ProtocolConfig(episodes=20, ablations=('flat',), tasks=(2, 3),
                                                                      calibrate='stall', calibration_episodes=4))
    assert (cal_proto.episodes, cal_proto.ablations, cal_proto.tasks, cal_proto.calibrate, cal_proto.split) == (
        4, (), (), 'none', 'dev')
    with pytest.raises(ValueError, match="calibrate is 'none'"):  # before any episode is run
        evaluate.calibration_pass(None, types.SimpleNamespace(plans=True, prunes=True), None, None, protocol.ProtocolConfig(),
                                  jax.random.PRNGKey(0))


def test_success_rates_by_hand():
    """The one aggregation (on device): 2 agents x 1 layout x 2 tasks x 2 episodes."""
    env = envs.make('pointmaze-medium')
    eps = protocol.plan_episodes(env, protocol.ProtocolConfig(episodes=2, tasks=(1, 4), ablations=('flat',)), 1.0)
    success = np.array([1, 1, 0, 1, 0, 0, 1, 0], bool)  # aqm task 1, aqm task 4, flat task 1, flat task 4
    pruned = np.array([0, 2, 4, 6, 0, 0, 0, 0])
    rates, prunes = jax.jit(lambda s, p: protocol.success_rates(eps, s, p))(success, pruned)
    np.testing.assert_allclose(rates, [[[1.0, 0.5]], [[0.0, 0.5]]])
    np.testing.assert_allclose(prunes, [[3.0], [0.0]])
    summary = protocol.format_summary(rates, eps.agents, list(eps.variants), eps.task_ids, prunes)
    assert summary['aqm']['base'] == {'task_1': 1.0, 'task_4': 0.5, 'mean': 0.75, 'pruned_mean': 3.0}


# --------------------------------------------------------------- the protocol without learning
def exact_point_agent(base):
    """The exact maze distance and a BFS-steering point controller (no learning)."""
    env = envs.make('pointmaze-medium')
    agent, graph, match = oracle.oracle_agent(env, base, delta=4.0, speed=0.15)
    proto = protocol.ProtocolConfig(episodes=2, tasks=(1, 4), horizon=400, ablations=('no-pruning', 'flat'))
    return env, agent, graph, AgentConfig(**match), proto


def closed_5_3(base):
    # task 4's shortest route runs through (5, 3); not in the suite because task 3 starts there
    g = base.copy()
    g[5, 3] = 1
    return g


@pytest.mark.slow  # 1.3 minutes of compiles (three chunk sizes)
def test_protocol_results_do_not_depend_on_chunking():
    base = mazes.layout('medium')
    env, agent, graph, cfg, proto = exact_point_agent(base)
    variants = {'base': base, 'close-5-3': closed_5_3(base)}
    a = evaluate.evaluate(env, agent, graph, cfg, dataclasses.replace(proto, envs=7), variants, progress=False)
    b = evaluate.evaluate(env, agent, graph, cfg, dataclasses.replace(proto, envs=24), variants, progress=False)
    assert a.timing['chunks'] == 4 and b.timing['chunks'] == 1  # 3 agents x 2 layouts x 2 tasks x 2 = 24
    assert a.timing['progress_callbacks'] == 4 * 8 and b.timing['progress_callbacks'] == 8  # every 50 of 400 steps
    np.testing.assert_array_equal(a.success, b.success)
    np.testing.assert_array_equal(a.pruned, b.pruned)
    # the summary is the per-episode mean, recomputed here
    t = a.table
    for ai, name in enumerate(a.agents):
        for vi, v in enumerate(a.variants):
            for task in (1, 4):
                sel = (t.agent == ai) & (t.variant == vi) & (t.task == task)
                assert a.summary[name][v][f'task_{task}'] == pytest.approx(a.success[sel].mean())
    # the planner with the exact distance solves the open maze; only pruning agents prune
    assert a.summary['aqm']['base']['mean'] == 1.0
    assert a.pruned[t.kappa == np.inf].max() == 0
    # task 4 with (5, 3) closed: the pruning agent reroutes, the non-pruning one does not get there
    assert a.summary['aqm']['close-5-3']['task_4'] == 1.0 and a.summary['no-pruning']['close-5-3']['task_4'] == 0.0
    tr = a.traces[('aqm', 'close-5-3', 4)]
    assert 1 <= len(tr['cuts']) <= min(tr['pruned'], MAX_CUTS) and tr["xy"].shape == (400, 2)


SHARD_SCRIPT = r'''
import os, sys, json
import jax, numpy as np
sys.path.insert(0, os.path.dirname(sys.argv[1]))
from test_evaluate import exact_point_agent, closed_5_3
from aqm_mjx.evaluation import evaluate
from aqm_mjx.envs import mazes, shifts
assert jax.device_count() == 2, jax.devices()
base = mazes.layout('medium')
env, agent, graph, cfg, proto = exact_point_agent(base)
variants = {'base': base, 'close-5-3': closed_5_3(base)}
out = {}
for n in (1, 2):
    mesh = evaluate.device_mesh(jax.devices()[:n])
    r = evaluate.evaluate(env, agent, graph, cfg, proto, variants, mesh=mesh, progress=False)
    xy = np.stack([r.traces[k]['xy'] for k in sorted(r.traces)])
    out[n] = (r.success, r.pruned, xy, r.timing['devices'])
assert out[1][3] == 1 and out[2][3] == 2
for i in range(3):
    assert np.array_equal(out[1][i], out[2][i]), i
print('identical', int(out[1][0].sum()), out[1][2].shape)
'''


@pytest.mark.slow  # 1.5-2 minutes on the 2-core CPU (a second JAX process with two host devices)
def test_sharding_over_two_devices_gives_bit_identical_results(two_device_python):
    assert 'identical' in two_device_python(SHARD_SCRIPT, __file__)


# ------------------------------------------------------------------------------ learned agent, CLI
def tiny_point_run(tmp_path):
    """A tiny model trained on random walks in pointmaze-medium (seconds): the wiring, not the skill."""
    data = synthetic.point_walks()
    obs = data['observations']
    path = tmp_path / 'pointmaze-medium-navigate.npz'
    np.savez(path, **data)
    out = tmp_path / 'run'
    assert cli.main(['train', '--dataset', str(path), '--preset', 'ci', '--steps', '100', '--out', str(out)]) == 0
    return out, path, obs


def test_learned_agent_map_and_cli(tmp_path, capsys):
    out, path, obs = tiny_point_run(tmp_path)
    agent = fit.load(str(out)).agent
    graph, kp = build_map(agent, jnp.asarray(obs), MapConfig(delta=1.0, max_keypoints=16, candidates=500),
                          jax.random.PRNGKey(0))
    k = int(kp.count)
    assert 1 <= k <= 16 and int(graph.mask.sum()) == k
    # keypoint observations are dataset states, their latents the encoder's
    rows = np.asarray(graph.obs)[:k]
    assert all(np.any(np.all(obs == r, axis=1)) for r in rows)
    np.testing.assert_allclose(graph.z[:k], jax.vmap(lambda o: agent.encode(agent.aux, o))(graph.obs[:k]), atol=1e-5)
    # the CLI: base plus the shift suite, every agent, one episode each, 60 steps
    ev = tmp_path / 'eval'
    argv = ['evaluate', '--checkpoint', str(out), '--episodes', '1', '--horizon', '60', '--shift', 'all',
            '--delta', '1', '--max-keypoints', '16', '--envs', '32', '--set', 'agent.kappa=0.5', '--out', str(ev)]
    assert cli.main(argv) == 0
    res = json.loads((ev / 'results.json').read_text())
    assert res['agents'] == ['aqm', 'no-pruning', 'flat'] and res['variants'][0] == 'base'
    assert res['variants'] == list(shifts.suite('medium')) and 1 <= res['keypoints'] <= 16
    assert res['timing']['chunks'] == -(-3 * len(res['variants']) * 5 // 32)
    # options not given take the preset of the checkpoint's training preset (ci); given ones win
    ci = pipeline.RunConfig.preset('ci')
    assert res['config']['agent']['switch_radius'] == ci.agent.switch_radius
    assert res['config']['map']['candidates'] == ci.map.candidates and res['config']['protocol']['ablations'] == [
        'no-pruning', 'flat']
    assert res['config']['map']['delta'] == 1.0 and res['config']['agent']['kappa'] == 0.5
    assert res['method'] == 'aqm' and res['config']['train']['preset'] == 'ci'
    for png in ('success.png', 'trajectories.png', 'heatmap.png'):
        assert (ev / png).read_bytes()[:4] == b'\x89PNG'
    # episodes.npz: one row per episode, no pickle; every rate of the table recomputed from it
    eps = np.load(ev / 'episodes.npz', allow_pickle=False)
    assert len(eps['success']) == 3 * len(res['variants']) * 5 and set(eps['agent']) == set(res['agents'])
    for a in res['agents']:
        for v in res['variants']:
            for t in range(1, 6):
                rows = (eps['agent'] == a) & (eps['layout'] == v) & (eps['task'] == t)
                assert rows.sum() == 1 and eps['success'][rows].mean() == res['summary'][a][v][f'task_{t}'], (a, v, t)
    assert (eps['pruned'][eps['agent'] != 'aqm'] == 0).all() and (eps['legs'] >= 0).all()
    printed = capsys.readouterr().out
    assert 'aqm / base' in printed
    # the leg log: per agent and layout, ordered quantiles; the calibration line for no-pruning / base
    assert set(res['legs']) == set(res['agents'])
    for a, per_layout in res['legs'].items():
        for v, row in per_layout.items():
            q = row['steps_per_d']
            assert row['legs'] >= 1 and q['q50'] <= q['q90'] <= q['q95'] <= q['q99'], (a, v)
            assert ('calibrated' in row) == (a == 'no-pruning')
            if a == 'no-pruning':  # at the protocol's rate (0.5%), not calibrate()'s default
                assert row['calibrated']['false_alarm'] == res['config']['protocol']['false_alarm'] == 0.005
    assert ('legs of no-pruning / base' in printed) == ('base' in res['legs']['no-pruning'])
    assert res['provenance']['version'] and res['provenance']['command'].startswith('aqm-mjx evaluate')
    assert ('Budgets that cut 0.5% of them' in printed) == bool(res['legs']['no-pruning'])
    # protocol.calibrate: a no-pruning pass on other episodes sets the AQM row's stall patience first,
    # which is the same as giving that patience by hand
    # (a switch radius of 3 in d: this 100-update model completed 22 legs in the pass on a 2-core AMD
    # EPYC; at the ci preset's 0.6 it completed 0-1 there, where XLA's code gives it other weights)
    one = ['evaluate', '--checkpoint', str(out), '--episodes', '1', '--horizon', '60', '--delta', '1',
           '--max-keypoints', '16', '--envs', '32', '--ablations', 'no-pruning', '--set', 'agent.switch_radius=3']
    assert cli.main(one + ['--set', 'protocol.calibrate=stall', '--set', 'protocol.false_alarm=0.2',
                           '--out', str(tmp_path / 'cal')]) == 0
    cal = json.loads((tmp_path / 'cal' / 'results.json').read_text())
    c = cal['calibration']
    assert c['rule'] == 'stall' and c['calibrated'] and c['episodes'] == ci.protocol.calibration_episodes == 20
    assert c['legs'] >= 1
    assert c['patience'] >= 1 and c['patience'] == round(c['patience'])
    assert f'AQM row on the stall rule, patience {c["patience"]:g} steps' in capsys.readouterr().out
    assert cli.main(one + ['--set', f'agent.patience={c["patience"]:g}', '--out', str(tmp_path / 'hand')]) == 0
    hand = json.loads((tmp_path / 'hand' / 'results.json').read_text())
    assert 'calibration' not in hand and hand['summary'] == cal['summary']
    # clear errors
    assert cli.main(['evaluate', '--checkpoint', str(out), '--shift', 'close-1-1', '--out', str(ev)]) == 2
    assert "unknown shift 'close-1-1'" in capsys.readouterr().err
    assert cli.main(['evaluate', '--checkpoint', str(out), '--dataset', str(tmp_path / 'nope.npz')]) == 2
    assert 'nope.npz: no such file' in capsys.readouterr().err
    assert cli.main(['evaluate', '--checkpoint', str(tmp_path / 'none')]) == 2
    assert 'no such file' in capsys.readouterr().err
    assert cli.main(['evaluate', '--checkpoint', str(out), '--tasks', '9', '--out', str(ev)]) == 2
    assert 'task ids [9]' in capsys.readouterr().err


def test_an_exported_folder_builds_the_same_map_and_scores_the_same_without_the_data(tmp_path):
    """`aqm-mjx export` keeps the newest checkpoint and the map's candidate states: evaluated from the
    export alone (the dataset moved away), the keypoints, edges and every episode equal the run's own
    evaluation; the record keeps the training data's fingerprint; a non-empty target is refused."""
    from aqm_mjx import assess, cli, run  # pylint: disable=import-outside-toplevel
    ckpt, path = run.demo_run(str(tmp_path / 'demo'), steps=100)
    ship = str(tmp_path / 'ship')
    assert cli.main(['export', '--checkpoint', ckpt, '--out', ship]) == 0
    record = json.load(open(os.path.join(ship, 'data.json')))
    assert record['data_sha256'] == fit.read_meta(ckpt)[2]['data_sha256'] and len(record['data_sha256']) == 64
    assert record['map_states'] == 400 == record['map_candidates']
    assert json.load(open(os.path.join(ship, 'config.json')))['dataset'] == 'map_states.npz'
    assert sorted(os.listdir(os.path.join(ship, 'checkpoints'))) == ['100']
    argv = ['--episodes', '2', '--horizon', '40', '--calibrate', 'none', '--ablations', 'no-pruning']
    assert cli.main(['evaluate', '--checkpoint', ckpt, '--out', str(tmp_path / 'full'), *argv]) == 0
    os.rename(path, path + '.away')  # the export does not need the data
    assert cli.main(['evaluate', '--checkpoint', ship, '--out', str(tmp_path / 'shipped'), *argv]) == 0
    full, shipped = (json.load(open(str(tmp_path / f / 'results.json'))) for f in ('full', 'shipped'))
    assert shipped['keypoints'] == full['keypoints'] >= 2 and shipped['edges'] == full['edges']
    assert shipped['summary'] == full['summary'] and shipped['legs'] == full['legs']
    with pytest.raises(FileExistsError, match='not empty'):
        assess.export_checkpoint(ckpt, ship, dataset=path + '.away')


def test_pictures_carry_legends_intervals_and_readable_labels(tmp_path):
    """Trajectory panels share one legend naming every mark drawn (graph, plan, trajectory, pruned
    edges, closed cell); success bars carry 95% Wilson whiskers when the episode count is known (by
    hand: 5 of 10 -> [23.7, 76.3]) and legends read 'qrl seed 0: aqm', not the table key."""
    from matplotlib.container import ErrorbarContainer  # pylint: disable=import-outside-toplevel

    from aqm_mjx.envs import render  # pylint: disable=import-outside-toplevel
    from aqm_mjx.evaluation import plots  # pylint: disable=import-outside-toplevel

    base = mazes.layout('medium')
    closed = shifts.suite('medium')['close-3-3']
    nodes = np.array([[0.0, 0.0], [4.0, 0.0], [8.0, 0.0]])
    panel = dict(grid=closed, base_grid=base, nodes_xy=nodes, edges=np.array([[0, 1], [1, 2]]),
                 pruned_edges=np.array([[1, 2]]), path_xy=nodes[:2], trajectories=[nodes], start_xy=nodes[0],
                 goal_xy=nodes[2], title='close-3-3: a title long enough that it has to wrap onto a second line')
    fig = render.render_panels(base, [panel, dict(panel, grid=base)])
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert {'closed cell', 'graph edges', 'pruned edges', 'keypoints', 'trajectory', 'plan', 'start',
            'goal'} <= set(labels) and len(labels) == len(set(labels))
    assert '\n' in fig.axes[0].get_title()
    summary = {'qrl:seed_0/aqm': {'base': {'task_1': 0.5, 'task_2': 1.0, 'mean': 0.75}}}
    fig = plots.success_bars(summary, 'base', [1, 2], episodes=10)
    ax = fig.axes[0]
    bars = [c for c in ax.containers if isinstance(c, ErrorbarContainer)]
    assert len(bars) == 1
    segs = bars[0].lines[2][0].get_segments()
    np.testing.assert_allclose([segs[0][0][1], segs[0][1][1]], [23.66, 76.34], atol=0.01)
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ['qrl seed 0: aqm']


def test_render_draws_a_trained_runs_map(tmp_path, capsys):
    from aqm_mjx import run  # pylint: disable=import-outside-toplevel

    ckpt, _ = run.demo_run(str(tmp_path / 'demo'), steps=50)
    out = str(tmp_path / 'map.png')
    assert cli.main(['render', '--checkpoint', ckpt, '--deltas', '0.5', '1.0', '--out', out]) == 0
    titles = [ln for ln in capsys.readouterr().out.splitlines() if 'keypoints' in ln]
    assert len(titles) == 2 and all(t.startswith('aqm step 50, delta ') for t in titles)
    counts = [int(t.split(': ')[1].split()[0]) for t in titles]
    assert counts[0] >= counts[1] >= 1  # a larger repel radius keeps fewer keypoints
    assert os.path.getsize(out) > 10_000
