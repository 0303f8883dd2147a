"""The second backend: OGBench's own MuJoCo environments stepped on the host, the agent jitted and
batched (``protocol.backend='ogbench'``), against the MJX backend on the same episodes."""

import os

import gymnasium
import jax

import numpy as np
import pytest

import ogbench.locomaze  # noqa: F401  (registers OGBench's environments)
from aqm_mjx import envs
from aqm_mjx.agent import oracle
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.envs import mazes
from aqm_mjx.envs.ogbench_env import OGBenchEnvs, make_env
from aqm_mjx.evaluation import evaluate, protocol


def _geoms(model) -> set:
    return {model.geom(i).name for i in range(model.ngeom)}


def test_the_environments_are_ogbench_own_with_the_layout_edited_before_the_build():
    ref = gymnasium.make('antmaze-medium-v0').unwrapped
    ours = make_env('ant', 'medium')
    assert _geoms(ours.model) == _geoms(ref.model)  # OGBench's model: same bodies, 'block_i_j' walls, target
    assert (ours.model.nq, ours.model.nv, ours.model.ngeom) == (ref.model.nq, ref.model.nv, ref.model.ngeom)
    grid = mazes.layout('medium').copy()
    assert grid[5, 3] == 0
    grid[5, 3] = 1
    closed = make_env('ant', 'medium', grid)
    assert _geoms(closed.model) - _geoms(ref.model) == {'block_5_3'}
    np.testing.assert_array_equal(closed.maze_map, grid)
    # from the same state, the same actions give the same observations as OGBench's registered environment
    ob, info = ours.reset(seed=3, options=dict(task_id=2))
    ob_ref, info_ref = ref.reset(seed=3, options=dict(task_id=2))
    assert ob.shape == (29,) and info['goal'].shape == (29,)
    a = np.random.default_rng(0).uniform(-1, 1, (30, 8))
    ref.set_state(ours.data.qpos.copy(), ours.data.qvel.copy())
    for t in range(30):
        o1 = ours.step(a[t])[0]
        o2 = ref.step(a[t])[0]
    np.testing.assert_allclose(o1, o2, atol=1e-12)


def test_batched_environments_seed_step_and_end_episodes():
    layout = np.broadcast_to(mazes.layout('medium'), (4, 8, 8))
    with OGBenchEnvs('pointmaze-medium', max_episode_steps=7) as e:
        obs, goal, goal_xy = e.reset([1, 2, 1, 5], [1, 1, 1, 3], layout)
        assert obs.shape == (4, 2) and goal.shape == (4, 2) and obs.dtype == np.float32
        np.testing.assert_array_equal(obs[0], obs[2])  # an episode depends on its seed alone
        np.testing.assert_array_equal(goal_xy[0], goal_xy[2])
        assert not np.array_equal(obs[0], obs[1])
        # OGBench's task 3 goal cell (4, 2) +- 1 m of noise
        assert np.abs(goal_xy[3] - mazes.ij_to_xy((4, 2))).max() <= 1.0
        for t in range(7):
            obs, xy, success, done = e.step(np.zeros((4, 2)))
            assert done.all() == (t == 6)  # the step limit ends every episode
        # a done environment stands still
        obs2, xy2, *_ = e.step(np.ones((4, 2)))
        np.testing.assert_array_equal(xy, xy2)
        with pytest.raises(ValueError, match=r'task ids \[9\] do not exist'):
            e.reset([0], [9], layout[:1])
        with pytest.raises(ValueError, match='grids'):
            e.reset([0, 1], [1, 1], layout[:1])
    with pytest.raises(ValueError, match='workers'):
        OGBenchEnvs('antmaze-medium', workers=-1)
    with pytest.raises(ValueError, match='unknown environment'):
        OGBenchEnvs('antmaze-huge')


def test_worker_processes_step_the_same_episodes():
    grids = np.broadcast_to(mazes.layout('medium'), (5, 8, 8))
    actions = np.random.default_rng(1).uniform(-1, 1, (20, 5, 8))
    outs = []
    for workers in (0, 2):
        with OGBenchEnvs('antmaze-medium', workers=workers) as e:
            first = e.reset(np.arange(5), np.arange(5) + 1, grids)
            outs.append((first, [e.step(a) for a in actions]))
    (f0, s0), (f1, s1) = outs
    for a, b in zip(f0, f1):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(s0, s1):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def test_a_worker_that_dies_or_fails_ends_the_evaluation_in_one_line_naming_it():
    """A worker killed between two steps, or one whose environments raise: a RuntimeError naming which
    worker of how many and why (no EOFError from the pipe), and close() still ends the others."""
    import signal  # pylint: disable=import-outside-toplevel

    grids = np.broadcast_to(mazes.layout('medium'), (4, 8, 8))
    e = OGBenchEnvs('antmaze-medium', workers=2)
    try:
        e.reset(np.arange(4), np.arange(4) + 1, grids)
        e.step(np.zeros((4, 8)))
        os.kill(e._procs[1].pid, signal.SIGKILL)  # pylint: disable=protected-access
        with pytest.raises(RuntimeError, match=r"OGBench's worker process 2 of 2 \(pid \d+\) ended \(exit code -9\) "
                                               'in the middle of the evaluation; nothing was written'):
            for _ in range(3):
                e.step(np.zeros((4, 8)))
    finally:
        e.close()
    e = OGBenchEnvs('antmaze-medium', workers=2)
    try:
        e.reset(np.arange(4), np.arange(4) + 1, grids)
        with pytest.raises(RuntimeError, match="OGBench's worker process 1 of 2 failed: ValueError"):
            e.step(np.zeros((4, 3)))  # actions of the wrong width reach the workers' environments
    finally:
        e.close()
    assert not any(p.is_alive() for p in e._procs)  # pylint: disable=protected-access


def test_both_backends_reroute_around_a_closed_corridor():
    """The oracle agent (exact maze distance, scripted controller) knows only the training layout;
    on both backends the pruning agent reroutes around the closed corridor and no pruning does not."""
    base = mazes.layout('medium')
    closed = base.copy()
    closed[5, 3] = 1  # the shortest route of task 4
    env = envs.make('pointmaze-medium')
    agent, graph, match = oracle.oracle_agent(env, base, delta=4.0, speed=0.15)
    cfg = AgentConfig(switch_radius=match['switch_radius'], kappa=0.25)
    results = {}
    for backend in protocol.BACKENDS:
        p = protocol.ProtocolConfig(episodes=4, tasks=(4,), horizon=400, ablations=('no-pruning',), backend=backend,
                                    envs=16)
        res = evaluate.evaluate(env, agent, graph, cfg, p, {'base': base, 'close-5-3': closed},
                                key=jax.random.PRNGKey(0), progress=False)
        s = res.summary
        assert s['aqm']['base']['mean'] == 1.0 and s['no-pruning']['base']['mean'] == 1.0, (backend, s)
        assert s['aqm']['close-5-3']['mean'] >= 0.75 and s['aqm']['close-5-3']['pruned_mean'] >= 1, (backend, s)
        assert s['no-pruning']['close-5-3']['mean'] == 0.0 and s['no-pruning']['close-5-3']['pruned_mean'] == 0
        assert res.timing['backend'] == backend
        assert res.timing['progress_callbacks'] == 400 // 50  # the bar moves within the chunk
        results[backend] = res
    # the same episode table on both: same rows, agents and layouts
    np.testing.assert_array_equal(results['mjx'].table.task, results['ogbench'].table.task)
    with pytest.raises(ValueError, match='backend'):
        protocol.ProtocolConfig(backend='brax')
