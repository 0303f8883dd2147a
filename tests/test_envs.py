"""MJX maze environments against OGBench's own (plain MuJoCo) environments."""

import gymnasium
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import ogbench  # noqa: F401  (registers OGBench's gymnasium environments)
import pytest

from aqm_mjx import envs
from aqm_mjx.envs import locomaze, mazes
from aqm_mjx.envs.checks import wall_check


def ogb(name):
    return gymnasium.make(f'{name}-v0').unwrapped


wall_distance = mazes.wall_distance


# ---------------------------------------------------------------- static facts, no compilation
@pytest.mark.parametrize('maze', mazes.MAZE_NAMES)
def test_layouts_and_tasks_match_ogbench(maze):
    name = 'antmaze' if maze != 'arena' else None
    if name is None:  # OGBench registers no arena env; build its maze class directly
        from ogbench.locomaze.maze import make_maze_env
        ref = make_maze_env('ant', 'maze', maze_type='arena')
    else:
        ref = ogb(f'antmaze-{maze}')
    np.testing.assert_array_equal(mazes.layout(maze), ref.maze_map)
    ours = mazes.tasks(maze)
    assert len(ours) == len(ref.task_infos)
    for t, r in zip(ours, ref.task_infos):
        assert t.init_ij == tuple(r['init_ij']) and t.goal_ij == tuple(r['goal_ij'])
        np.testing.assert_allclose(t.init_xy, r['init_xy'])
        np.testing.assert_allclose(t.goal_xy, r['goal_xy'])
    if maze == 'teleport':
        np.testing.assert_allclose(mazes.ij_to_xy(mazes.TELEPORT_IN), ref._teleport_info['teleport_in_xys'])
        np.testing.assert_allclose(mazes.ij_to_xy(mazes.TELEPORT_OUT), ref._teleport_info['teleport_out_xys'])


def test_constants_match_ogbench():
    ref = ogb('antmaze-large')
    pref = ogb('pointmaze-large')
    assert ref._goal_tol == 0.5 and pref._goal_tol == 1.0
    assert ref._success_timing == 'post' and ref._terminate_at_goal
    assert gymnasium.spec('antmaze-large-v0').max_episode_steps == 1000
    assert ref.frame_skip == 5 and ref.model.opt.timestep == 0.02
    assert ref.model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert ref._noise * ref._maze_unit / 4 == mazes.START_GOAL_NOISE * mazes.MAZE_UNIT / 4
    # xy_to_ij agrees with OGBench's on cell centres and near cell borders.
    env = envs.make('pointmaze-large')
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5.9, 39.9, size=(500, 2))
    ours = np.asarray(env.xy_to_ij(jnp.asarray(xy)))
    theirs = np.array([ref.xy_to_ij(p) for p in xy])
    np.testing.assert_array_equal(ours, theirs)


def test_bad_names_and_options():
    with pytest.raises(ValueError, match='unknown environment'):
        envs.make('antmaze-huge')
    with pytest.raises(ValueError, match='unknown environment'):
        envs.make('humanoidmaze-medium')
    with pytest.raises(TypeError, match='unknown option'):
        envs.make('antmaze-medium', iterashuns=3)
    with pytest.raises(ValueError, match='unknown integrator'):
        envs.make('antmaze-medium', integrator='verlet')
    with pytest.raises(ValueError, match="unknown MJX implementation"):
        envs.make('antmaze-medium', impl='cuda')
    with pytest.raises(ValueError, match='unknown maze'):
        mazes.layout('tiny')
    assert envs.parse_name('antmaze-large-v0') == ('ant', 'large')
    if not locomaze.warp_available():
        with pytest.raises(RuntimeError, match=r"impl='warp' needs MuJoCo Warp"):
            envs.make('antmaze-medium', impl='warp')
    with pytest.raises(ValueError, match='contact_caps'):
        envs.make('antmaze-medium', contact_caps=(0, 4))


def test_malformed_grids_are_rejected():
    good = mazes.layout('medium')
    assert mazes.validate_grid(good, 'medium').dtype == np.int8
    with pytest.raises(ValueError, match='must have shape'):
        mazes.validate_grid(np.ones((9, 12)), 'medium')
    with pytest.raises(ValueError, match='2-D'):
        mazes.validate_grid(np.ones(64), 'medium')
    bad = good.astype(float)
    bad[2, 2] = np.nan
    with pytest.raises(ValueError, match='NaN'):
        mazes.validate_grid(bad, 'medium')
    bad = good.copy()
    bad[2, 2] = 3
    with pytest.raises(ValueError, match=r'cell \(2, 2\) is 3'):
        mazes.validate_grid(bad, 'medium')
    bad = good.copy()
    bad[0, 3] = 0
    with pytest.raises(ValueError, match='border'):
        mazes.validate_grid(bad, 'medium')
    with pytest.raises(ValueError, match='object'):
        mazes.validate_grid(np.array([[None]], dtype=object), 'medium')


def test_agent_reach_leaves_room_for_three_proxies():
    """R (largest horizontal reach of the ant's geoms from the torso) + step displacement < 2 m."""
    m = locomaze.build_mj_model('ant')
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    ant_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] != 0 and m.body_mocapid[m.geom_bodyid[g]] < 0]
    reach, moved = 0.0, 0.0
    for ep in range(4):
        mujoco.mj_resetData(m, d)
        d.qvel[:] = 0.1 * rng.standard_normal(m.nv)
        for t in range(150):
            xy0 = d.qpos[:2].copy()
            d.ctrl[:] = rng.uniform(-1, 1, m.nu)
            for _ in range(5):
                mujoco.mj_step(m, d)
                for g in ant_geoms:
                    half_len = m.geom_size[g, 1] if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0
                    axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
                    for end in (-1, 1):
                        p = d.geom_xpos[g] + end * half_len * axis
                        reach = max(reach, np.linalg.norm(p[:2] - d.qpos[:2]) + m.geom_size[g, 0] + m.geom_margin[g])
            moved = max(moved, np.linalg.norm(d.qpos[:2] - xy0))
    assert reach < 1.3, reach
    assert reach + moved < 2.0, (reach, moved)


def test_proxies_cover_every_reachable_wall():
    """Every wall block within 2 m of a point is one of the (at most 3) proxied blocks."""
    env = envs.make('pointmaze-giant')
    grid = env.layout
    rng = np.random.default_rng(1)
    free = np.argwhere(grid == 0)
    cells = free[rng.integers(len(free), size=400)]
    xy = mazes.ij_to_xy(cells) + rng.uniform(-2, 2, size=(400, 2))
    pos = np.asarray(jax.jit(jax.vmap(env.proxy_positions, in_axes=(0, None)))(jnp.asarray(xy, jnp.float32), jnp.asarray(grid)))
    walls = mazes.ij_to_xy(np.argwhere(grid == 1))
    n_near = 0
    for p, prox in zip(xy, pos):
        gap = np.linalg.norm(np.maximum(np.abs(p - walls) - mazes.MAZE_UNIT / 2, 0.0), axis=-1)
        placed = {tuple(np.round(q[:2], 3)) for q in prox if q[0] < 500}
        for w in walls[gap < 2.0]:
            n_near += 1
            assert tuple(np.round(w, 3)) in placed, (p, w, placed)
        assert len(placed) <= 3
    assert n_near > 300  # the check saw many walls within reach


# ---------------------------------------------------------------- point agent (cheap physics)
@pytest.fixture(scope='module')
def point():
    env = envs.make('pointmaze-medium', max_episode_steps=50)
    return env, jax.jit(jax.vmap(env.reset_to, in_axes=(0, 0, 0, 0))), jax.jit(jax.vmap(env.step))


def test_point_matches_ogbench_trajectory_and_success_timing():
    """Same start, goal and actions: same positions, success at the same step, as OGBench's env."""
    env = envs.make('pointmaze-medium')
    ref_env = gymnasium.make('pointmaze-medium-v0')
    ref = ref_env.unwrapped
    ref_env.reset(seed=0, options=dict(task_id=1))
    start, goal = np.array([0.3, -0.2]), np.array([4.6, 0.4])
    ref.set_xy(start)
    ref.set_goal(goal_xy=goal)
    state = env.reset_to(jax.random.PRNGKey(0), jnp.asarray(start), jnp.asarray(goal))
    step = jax.jit(env.step)
    actions = np.tile([[1.0, 0.1]], (30, 1))
    for t, a in enumerate(actions):
        _, r, term, _, info = ref_env.step(a)
        state = step(state, jnp.asarray(a, jnp.float32))
        np.testing.assert_allclose(np.asarray(state.data.qpos), ref.data.qpos, atol=1e-4)
        assert float(state.success) == info['success'] == r
        assert bool(state.done) == term
        if term:
            break
    assert term and t == 16  # x: 0.3 + 0.2 k reaches within 1 m of 4.6 at k = 17


def test_episode_limit_and_done_freezes(point):
    env, reset_to, step = point
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    s = reset_to(keys, jnp.zeros((2, 2)), jnp.array([[16.0, 16.0], [16.0, 16.0]]), jnp.broadcast_to(env.layout, (2, 8, 8)))
    for t in range(60):
        s = step(s, jnp.zeros((2, 2)))
        assert bool(s.done.all()) == (t + 1 >= 50)
    assert int(s.steps[0]) == 50  # frozen after the limit
    assert float(s.success.max()) == 0.0


def test_per_environment_walls_block_only_where_closed(point):
    """One compiled program; a corridor closed in half of the batch stops exactly those agents."""
    env, reset_to, step = point
    n = 8
    grid = np.broadcast_to(env.layout, (n, 8, 8)).copy()
    closed = np.arange(n) % 2 == 1
    grid[closed, 1, 2] = 1  # medium maze: close cell (1, 2), the corridor east of the start cell (1, 1)
    keys = jax.random.split(jax.random.PRNGKey(3), n)
    cached = step._cache_size()
    start = jnp.broadcast_to(jnp.asarray(mazes.ij_to_xy((1, 1)), jnp.float32), (n, 2))
    s = reset_to(keys, start, start + 100.0, jnp.asarray(grid))
    for _ in range(20):
        s = step(s, jnp.tile(jnp.array([[1.0, 0.0]]), (n, 1)))
    x = np.asarray(s.data.qpos[:, 0])
    wall_face = mazes.ij_to_xy((1, 2))[0] - mazes.MAZE_UNIT / 2
    assert np.all(x[closed] <= wall_face - 0.7 + 0.05)  # the 0.7 m point sphere stops at the wall
    assert np.all(x[~closed] > wall_face + 1.0)  # the others went through the corridor
    assert step._cache_size() == cached + 1  # one program for the new batch shape, whatever the grids


def test_teleport_portals_are_stochastic_and_match_ogbench():
    env = envs.make('pointmaze-teleport')
    n = 600
    keys = jax.random.split(jax.random.PRNGKey(0), n)
    portal = jnp.asarray(mazes.ij_to_xy(mazes.TELEPORT_IN[0]), jnp.float32)
    s = jax.vmap(env.reset_to, in_axes=(0, None, None))(keys, portal + jnp.array([-0.4, 0.0]), jnp.zeros(2))
    s = jax.jit(jax.vmap(env.step))(s, jnp.zeros((n, 2)))
    xy = np.asarray(s.data.qpos[:, :2])
    outs = mazes.ij_to_xy(mazes.TELEPORT_OUT)
    which = np.argmin(np.linalg.norm(xy[:, None] - outs, axis=-1), axis=-1)
    assert np.allclose(xy, outs[which], atol=1e-5)  # every agent landed exactly on an outbound portal
    counts = np.bincount(which, minlength=3)
    assert np.all(np.abs(counts - n / 3) < 4 * np.sqrt(n * (1 / 3) * (2 / 3))), counts
    # As in OGBench, the observation returned by the step is the one before the teleport.
    assert np.allclose(np.asarray(s.obs), np.asarray(portal + jnp.array([-0.4, 0.0]))[None], atol=1e-4)


# ---------------------------------------------------------------- ant in the large maze
@pytest.fixture(scope='module')
def ant():
    env = envs.make('antmaze-large')
    return env, jax.jit(jax.vmap(env.physics_step))


def test_reset_and_goal_observation(ant):
    env, _ = ant
    keys = jax.random.split(jax.random.PRNGKey(0), 64)
    s = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, 2)
    t = env.tasks[1]
    assert s.obs.shape == (64, 29) and s.goal.shape == (64, 29)
    init = np.asarray(s.obs[:, :2])
    goal = np.asarray(s.goal[:, :2])
    assert np.all(np.abs(init - np.array(t.init_xy)) <= 1.0) and np.all(np.abs(goal - np.array(t.goal_xy)) <= 1.0)
    assert init.std(0).min() > 0.3  # the start noise is U(-1, 1) per axis
    np.testing.assert_allclose(goal, np.asarray(s.goal_xy))
    # Goal posture comes from 5 random actions: it is off the reset pose, standing, and varied.
    assert np.all(np.asarray(s.goal[:, 2]) > 0.2) and np.asarray(s.goal[:, 7:15]).std(0).min() > 0.05
    assert np.all(np.abs(np.asarray(s.obs[:, 15:])) < 0.6)  # qvel ~ 0.1 N(0, 1) at reset
    assert int(s.steps.max()) == 0 and not bool(s.done.any())
    with pytest.raises(ValueError, match=r'task_id must be an integer in \[1, 5\]'):
        env.reset(jax.random.PRNGKey(0), 6)
    with pytest.raises(ValueError, match='task_id'):
        env.reset(jax.random.PRNGKey(0), 0)
    with pytest.raises(ValueError, match='must have shape'):
        env.reset(jax.random.PRNGKey(0), 1, grid=np.ones((8, 8)))


def _states_near_walls(n, seed):
    """``n`` states of OGBench's antmaze-large reached by random actions, many near walls."""
    ref_env = gymnasium.make('antmaze-large-v0')
    ref = ref_env.unwrapped
    ref_env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    grid = ref.maze_map
    free = np.argwhere(grid == 0)
    states, actions, nxt = [], [], []
    while len(states) < n:
        ij = free[rng.integers(len(free))]
        xy = mazes.ij_to_xy(ij) + rng.uniform(-1.3, 1.3, 2)  # torso 0.7 to 3.3 m from the cell's walls
        ref_env.reset(seed=int(rng.integers(1 << 30)))
        ref.set_xy(xy)
        for _ in range(int(rng.integers(3, 20))):
            ref_env.step(rng.uniform(-1, 1, 8))
        ref.data.qacc_warmstart[:] = 0.0  # MJX starts its solver from zero too
        a = rng.uniform(-1, 1, 8)
        states.append((ref.data.qpos.copy(), ref.data.qvel.copy()))
        actions.append(a)
        ref_env.step(a)
        nxt.append(ref.data.qpos.copy())
    return states, np.array(actions), np.array(nxt), grid


def test_one_control_step_parity_with_ogbench(ant):
    """(a) one control step from 300 identical states: qpos within 1e-2 at the 95th percentile."""
    env, pstep = ant
    states, actions, nxt, grid = _states_near_walls(300, seed=0)
    qpos = jnp.asarray(np.array([s[0] for s in states]), jnp.float32)
    qvel = jnp.asarray(np.array([s[1] for s in states]), jnp.float32)
    data = jax.vmap(env.set_state)(qpos, qvel)
    out = pstep(data, jnp.asarray(actions, jnp.float32), jnp.broadcast_to(jnp.asarray(grid, jnp.int8), (300,) + grid.shape))
    err = np.max(np.abs(np.asarray(out.qpos) - nxt), axis=-1)
    near = wall_distance(np.array([s[0][:2] for s in states]), grid) < 1.3
    print(f'parity: qpos max-abs error median {np.median(err):.2e}, p95 {np.percentile(err, 95):.2e}, '
          f'{near.sum()} of 300 states within 1.3 m of a wall (p95 there {np.percentile(err[near], 95):.2e})')
    assert near.sum() >= 50
    assert np.percentile(err, 95) < 1e-2
    # Near walls (ant touching them) float32 contact solving spreads a little more; caps on or off
    # give the same numbers (checked: 9.96e-3 with and without), so this is not the proxies.
    assert np.percentile(err[near], 95) < 2e-2


@pytest.mark.parametrize('steps,seed', [pytest.param(100, 0, marks=pytest.mark.slow),  # 2 minutes of ant compiles
                                        pytest.param(1000, 1, marks=pytest.mark.slow)])
def test_ant_never_enters_walls(ant, steps, seed):
    """(b): 64 envs x ``steps`` random-action steps in the large maze, each ant thrown at its
    nearest wall at 4 m/s first; 1000 steps (as stated) is the slow case, 100 the CPU-sized one."""
    env, _ = ant
    dist, moved = wall_check(env, 64, steps, seed=seed)
    print(f'min torso-wall distance {dist.min():.3f} m, max step displacement {moved:.3f} m')
    assert dist.min() >= 0.25 - 0.03  # the torso sphere's radius, as OGBench's own walls allow
    assert moved < 0.7  # reach (< 1.3 m) + one step's displacement stays under half a cell


def test_ant_blocked_by_corridor_closed_in_half_the_batch(ant):
    """Ants thrown east at 6 m/s from cell (1, 1): through the corridor where it is open, stopped
    at the wall face (x = 2 m, torso radius 0.25) where cell (1, 2) is closed; one program."""
    env, _ = ant
    n = 8
    grid = np.broadcast_to(env.layout, (n,) + env.layout.shape).copy()
    closed = np.arange(n) % 2 == 1
    assert env.layout[1, 2] == 0
    grid[closed, 1, 2] = 1
    start = jnp.broadcast_to(jnp.array([0.9, 0.0]), (n, 2))
    s = jax.jit(jax.vmap(env.reset_to))(jax.random.split(jax.random.PRNGKey(0), n), start, start + 100.0, jnp.asarray(grid))
    s = s.replace(data=s.data.replace(qvel=s.data.qvel.at[:, 0].set(6.0)))
    step = jax.jit(jax.vmap(env.step))
    for _ in range(15):
        s = step(s, jnp.zeros((n, 8)))
    x = np.asarray(s.data.qpos[:, 0])
    print(f'ant x after the throw: open {np.round(x[~closed], 2)}, closed {np.round(x[closed], 2)}')
    assert np.all(x[closed] <= 2.0 - 0.25 + 0.03)
    assert np.all(x[~closed] > 2.5)


@pytest.mark.slow  # 1.5 minutes of ant compiles; the default tier checks one program per batch shape on the point
# (test_per_environment_walls_block_only_where_closed)
def test_step_compiles_once_across_grids_and_calls(ant, no_compile_cache):
    """The timing trap: a step called on its own output, and with another grid, does not retrace."""
    env, _ = ant
    traces, compiles = [], []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiles.append(secs) if name == '/jax/core/compile/backend_compile_duration' else None)

    def counted(state, action):
        traces.append(1)
        return env.step(state, action)

    step = jax.jit(jax.vmap(counted))
    s = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.PRNGKey(0), 4), 1)
    a = jnp.zeros((4, 8))
    s = step(s, a)
    n_compiles = len(compiles)
    assert max(compiles) > 1.0  # the step program itself was compiled (seconds, not milliseconds)
    s = step(s, a)
    g = np.array(s.grid)
    g[:, 1, 2] = 1
    s = step(s.replace(grid=jnp.asarray(g)), a)
    jax.block_until_ready(s)
    assert len(traces) == 1
    # Only millisecond compilations (array conversions) may follow; no second step program.
    assert all(c < 0.5 for c in compiles[n_compiles:]), compiles[n_compiles:]
