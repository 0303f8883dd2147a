"""On-device collection: OGBench's recipe (cells, goals, directions), file format, CLI."""

import dataclasses
import os

import jax
import numpy as np
import pytest
from ogbench.utils import load_dataset
from scipy.sparse.csgraph import shortest_path

from aqm_mjx import cli, envs
from aqm_mjx.data import collect
from aqm_mjx.data import dataset as dsm
from aqm_mjx.envs import mazes


def _grid_distances(grid):
    g = np.asarray(grid)
    h, w = g.shape
    adj = np.zeros((h * w, h * w))
    for i in range(h):
        for j in range(w):
            if g[i, j]:
                continue
            for di, dj in ((1, 0), (0, 1)):
                ni, nj = i + di, j + dj
                if ni < h and nj < w and not g[ni, nj]:
                    adj[i * w + j, ni * w + nj] = adj[ni * w + nj, i * w + j] = 1
    return shortest_path(adj, unweighted=True)


def test_junction_cells_on_a_hand_drawn_maze():
    grid = np.array([[1, 1, 1, 1, 1],
                     [1, 0, 0, 0, 1],
                     [1, 0, 1, 1, 1],
                     [1, 0, 1, 1, 1],
                     [1, 1, 1, 1, 1]])
    # (1,2) is a horizontal corridor cell and (2,1) a vertical one; (1,1) is a corner and (1,3),
    # (3,1) dead ends: all three are junction cells in OGBench's sense.
    got = {tuple(c) for c in mazes.junction_cells(grid)}
    assert got == {(1, 1), (1, 3), (3, 1)}
    assert len(mazes.free_cells(grid)) == 5


@pytest.mark.parametrize('maze', ['medium', 'large', 'teleport'])
def test_stitch_goal_cells_are_exactly_four_bfs_steps_away(maze):
    grid = mazes.layout(maze)
    free = mazes.free_cells(grid)
    cells, count = mazes.cells_at_bfs_distance(grid, 4)
    dist = _grid_distances(grid)
    w = grid.shape[1]
    for f, (i, j) in enumerate(free):
        want = {tuple(divmod(int(c), w)) for c in np.flatnonzero(dist[i * w + j] == 4)}
        got = {tuple(c) for c in cells[f, :count[f]]}
        assert got == (want or {(i, j)}), (maze, i, j)
        assert (cells[f, count[f]:] == cells[f, 0]).all()  # padding repeats a valid entry


def test_recipe_defaults_and_errors():
    assert collect.recipe('medium', 'navigate') == collect.Recipe(1000, 1001, 0.2)
    assert collect.recipe('giant', 'navigate') == collect.Recipe(500, 2001, 0.2)
    assert collect.recipe('large', 'stitch') == collect.Recipe(5000, 201, 0.2)
    assert collect.recipe('medium', 'explore') == collect.Recipe(10000, 501, 1.0)
    with pytest.raises(ValueError, match='unknown collection style'):
        collect.CollectConfig(style='wander').resolved()
    with pytest.raises(ValueError, match='unknown environment'):
        collect.CollectConfig(env='antmaze-huge').resolved()
    with pytest.raises(ValueError, match='episodes must be >= 1'):
        collect.CollectConfig(episodes=0).resolved()
    with pytest.raises(ValueError, match='noise'):
        collect.CollectConfig(noise=float('nan')).resolved()
    env = envs.make('pointmaze-medium')
    with pytest.raises(ValueError, match='terminate_at_goal=False'):
        collect.episode_fn(env, 'navigate', 10, 0.2)


def test_point_collection_file_format_and_ogbench_loader(tmp_path):
    cfg = collect.CollectConfig(env='pointmaze-medium', style='navigate', episodes=10, steps=120, batch=4, seed=3)
    res = collect.collect(cfg, progress=False)
    tr, va = res.train, res.val
    # the bar's host callbacks: after steps 50, 100 and 120 of each of the 3 chunks (11 episodes, 4 at a time)
    assert res.stats['progress_callbacks'] == 3 * 3
    assert tr['observations'].shape == (10 * 120, 2) and va['observations'].shape == (1 * 120, 2)
    assert tr['actions'].shape == (1200, 2) and tr['qpos'].shape == (1200, 2) and tr['qvel'].shape == (1200, 2)
    np.testing.assert_array_equal(np.flatnonzero(tr['terminals']), np.arange(119, 1200, 120))
    np.testing.assert_array_equal(tr['observations'], tr['qpos'])  # the point's observation is its qpos
    assert np.abs(tr['actions']).max() <= 1.0
    # consecutive states of an episode differ by 0.2 * action (OGBench's point), away from walls
    step = (tr['observations'][1:] - tr['observations'][:-1])[~tr['terminals'][:-1]]
    moved = np.linalg.norm(step - 0.2 * tr['actions'][:-1][~tr['terminals'][:-1]], axis=1)
    assert np.median(moved) < 1e-4
    assert res.stats['goals_reached_mean'] > 0.5  # the oracle reaches junction goals within 120 steps
    path = str(tmp_path / 'pointmaze-medium-navigate-v0.npz')
    collect.write(res, path)
    with pytest.raises(FileExistsError, match='exists'):
        collect.write(res, path)
    ref = load_dataset(path, add_info=True)  # OGBench's loader, unchanged
    assert ref['observations'].shape == (10 * 119, 2)
    back = dsm.read_ogbench(path, obs_size=2, action_size=2)
    for k in tr:
        assert back[k].dtype == tr[k].dtype and np.array_equal(back[k], tr[k]), k
    assert dsm.read_ogbench(dsm.val_path(path))['observations'].shape == (120, 2)


@pytest.mark.slow  # two more compilations (about 40 s)
def test_episodes_do_not_depend_on_the_batch():
    a = collect.collect(collect.CollectConfig(env='pointmaze-medium', style='stitch', episodes=5, steps=30, batch=2),
                        progress=False)
    b = collect.collect(collect.CollectConfig(env='pointmaze-medium', style='stitch', episodes=5, steps=30, batch=6),
                        progress=False)
    for k in a.train:
        np.testing.assert_allclose(a.train[k], b.train[k], atol=1e-5, err_msg=k)


def test_explore_directions_hold_for_ten_steps_and_stitch_reaches_its_goal():
    env = envs.make('pointmaze-large', max_episode_steps=40, terminate_at_goal=False)
    run = jax.jit(jax.vmap(collect.episode_fn(env, 'explore', 40, 0.0)))
    out = jax.device_get(run(jax.random.split(jax.random.PRNGKey(0), 3)))
    act = out['actions']  # noise 0: the point's action is the unit direction itself
    np.testing.assert_allclose(np.linalg.norm(act, axis=-1), 1.0, atol=1e-4)
    blocks = act.reshape(3, 4, 10, 2)
    np.testing.assert_allclose(blocks, np.broadcast_to(blocks[:, :, :1], blocks.shape), atol=1e-6)
    assert np.abs(blocks[:, 1:, 0] - blocks[:, :-1, 0]).max() > 0.1  # and change between blocks
    env = envs.make('pointmaze-large', max_episode_steps=201, terminate_at_goal=False)
    run = jax.jit(jax.vmap(collect.episode_fn(env, 'stitch', 201, 0.2)))
    out = jax.device_get(run(jax.random.split(jax.random.PRNGKey(1), 16)))
    assert out['goals_reached'].mean() >= 0.9  # 4 cells = 16 m in 201 steps of <= 0.2 m


def _cells_visited(qpos):
    """``(i, j)`` grid cells of the positions ``qpos [..., 2+]``."""
    xy = np.asarray(qpos)[..., :2].reshape(-1, 2)
    ij = np.rint((xy + mazes.MAZE_OFFSET) / mazes.MAZE_UNIT).astype(int)[:, ::-1]
    return {tuple(c) for c in ij}


def test_collection_on_a_shifted_layout_stays_out_of_the_closed_cell():
    base = collect.CollectConfig(env='pointmaze-medium', episodes=16, steps=150, batch=17, seed=2)
    closed = collect.CollectConfig(env='pointmaze-medium', episodes=16, steps=150, batch=17, seed=2, layout='close-3-3')
    assert closed.grid()[3, 3] == 1 and base.grid()[3, 3] == 0
    a, b = (collect.collect(c, progress=False) for c in (base, closed))
    assert (3, 3) in _cells_visited(a.train['qpos'])  # on the base layout the data go through it
    seen = _cells_visited(b.train['qpos'])
    assert (3, 3) not in seen and all(closed.grid()[c] == 0 for c in seen)  # walls and waypoints are the variant's
    assert b.stats['layout'] == 'close-3-3' and b.stats['goals_reached_mean'] > 0.5
    with pytest.raises(ValueError, match="unknown shift 'close-0-0'"):
        collect.CollectConfig(env='pointmaze-medium', layout='close-0-0').resolved()


def test_ant_collection_is_upright_and_moves():
    env = envs.make('antmaze-medium', max_episode_steps=60, terminate_at_goal=False)
    run = jax.jit(jax.vmap(collect.episode_fn(env, 'stitch', 60, 0.2)))
    out = jax.device_get(run(jax.random.split(jax.random.PRNGKey(0), 4)))
    assert out['observations'].shape == (4, 60, 29) and out['actions'].shape == (4, 60, 8)
    np.testing.assert_array_equal(out['observations'][..., :15], out['qpos'])
    np.testing.assert_array_equal(out['observations'][..., 15:], out['qvel'])
    assert out['upright'].all()
    travelled = np.linalg.norm(out['qpos'][:, -1, :2] - out['qpos'][:, 0, :2], axis=-1)
    assert travelled.min() > 1.5  # 6 s of trotting at >= 1 m/s, minus turns


def test_host_physics_starts_each_episode_where_mjx_does_and_follows_the_same_expert():
    env = envs.make('pointmaze-medium', max_episode_steps=30, terminate_at_goal=False)
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    mjx_out = jax.device_get(jax.jit(jax.vmap(collect.episode_fn(env, 'stitch', 30, 0.2)))(keys))
    host = collect.HostEpisodes(env, 'stitch', 30, 0.2)(keys)
    for k in ('observations', 'actions', 'qpos', 'qvel', 'upright'):
        assert host[k].shape == mjx_out[k].shape, k
    # the same start, goal, noise and first action; the point's physics then agrees closely (no spin, one body)
    np.testing.assert_allclose(host['qpos'][:, 0], mjx_out['qpos'][:, 0], atol=1e-6)
    np.testing.assert_allclose(host['actions'][:, 0], mjx_out['actions'][:, 0], atol=1e-5)
    np.testing.assert_allclose(host['qpos'][:, 10], mjx_out['qpos'][:, 10], atol=1e-2)
    ant = envs.make('antmaze-medium', max_episode_steps=60, terminate_at_goal=False)
    out = collect.HostEpisodes(ant, 'stitch', 60, 0.2)(jax.random.split(jax.random.PRNGKey(0), 4))
    np.testing.assert_array_equal(out['observations'], np.concatenate([out['qpos'], out['qvel']], -1))
    assert out['upright'].all()
    travelled = np.linalg.norm(out['qpos'][:, -1, :2] - out['qpos'][:, 0, :2], axis=-1)
    assert travelled.min() > 1.5  # the scripted trot walks in OGBench's physics too
    with pytest.raises(ValueError, match='teleport'):
        collect.HostEpisodes(envs.make('antmaze-teleport', terminate_at_goal=False), 'navigate', 30, 0.2)
    with pytest.raises(ValueError, match="unknown collection physics 'warp'"):
        collect.CollectConfig(physics='warp').resolved()


def test_host_threads_step_the_same_episodes_bit_for_bit(monkeypatch):
    """The host's episodes of a batch stepped by several threads (each MjData in one thread's slice) are
    the single thread's exactly, for the ant with its contacts; an odd batch over more threads than
    episodes still steps every one; a thread's exception reaches the caller; threads < 0 is refused."""
    ant = envs.make('antmaze-medium', max_episode_steps=40, terminate_at_goal=False)
    keys = jax.random.split(jax.random.PRNGKey(1), 5)
    one = collect.HostEpisodes(ant, 'navigate', 40, 0.2, threads=1)(keys)
    for threads in (2, 3, 8):
        many = collect.HostEpisodes(ant, 'navigate', 40, 0.2, threads=threads)(keys)
        for k in ('observations', 'actions', 'qpos', 'qvel', 'upright', 'goals_reached'):
            np.testing.assert_array_equal(many[k], one[k], err_msg=f'{k}, {threads} threads')
    assert np.abs(one['qpos'][:, -1, :2] - one['qpos'][:, 0, :2]).max() > 1.0  # the ants did walk
    assert collect.HostEpisodes(ant, 'navigate', 40, 0.2).threads == collect.host_cores() >= 1
    host = collect.HostEpisodes(ant, 'navigate', 40, 0.2, threads=2)

    def broken(d, a):
        raise RuntimeError('mj_step failed')

    monkeypatch.setattr(host, '_step', broken)
    with pytest.raises(RuntimeError, match='mj_step failed'):
        host(keys)
    with pytest.raises(ValueError, match='threads must be >= 0'):
        collect.CollectConfig(threads=-1).resolved()


def test_host_collection_writes_the_file_mjx_would_and_records_its_physics(tmp_path):
    cfg = collect.CollectConfig(env='pointmaze-medium', style='stitch', episodes=10, steps=100, batch=4, physics='mujoco')
    res = collect.collect(cfg, progress=False)
    assert res.train['observations'].shape == (1000, 2) and res.val['observations'].shape == (100, 2)
    assert res.train['terminals'].sum() == 10 and res.train['terminals'][99]
    assert res.stats['physics'] == 'mujoco' and res.stats['goals_reached_mean'] > 0.5
    a = collect.collect(dataclasses.replace(cfg, batch=11), progress=False)  # chunking does not change episodes
    np.testing.assert_array_equal(a.train['qpos'], res.train['qpos'])


def test_cli_collect(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(['collect', '--help'])
    help_text = capsys.readouterr().out
    for opt in ('--env', '--style', '--episodes', '--steps', '--noise', '--batch', '--seed', '--layout', '--out',
                '--overwrite', '--physics'):
        assert opt in help_text
    out = str(tmp_path / 'pm.npz')
    assert cli.main(['collect', '--env', 'pointmaze-medium', '--style', 'explore', '--episodes', '10', '--steps', '30',
                     '--out', out]) == 0
    assert os.path.exists(out) and os.path.exists(str(tmp_path / 'pm-val.npz')) and os.path.exists(str(tmp_path / 'pm.png'))
    assert load_dataset(out)['observations'].shape == (10 * 29, 2)
    before = open(out, 'rb').read()
    assert cli.main(['collect', '--env', 'pointmaze-medium', '--episodes', '2', '--steps', '5', '--out', out]) == 2
    assert 'exists' in capsys.readouterr().err
    assert open(out, 'rb').read() == before  # nothing already written is lost
    assert cli.main(['collect', '--env', 'antmaze-medium', '--out', str(tmp_path / 'x.txt')]) == 2
