"""OGBench's locomaze (ant and point) in MJX, with the maze held as per-environment data.

Why the walls are proxies
-------------------------
MJX (JAX implementation) has no broadphase: it reserves contact slots and runs narrow-phase
collision for every geom pair that may touch, every step. OGBench's large maze has 61 static wall
boxes, each paired with the 13 ant geoms, which makes a step ~55x the ant alone. Here the model
holds only ``N_PROXIES = 3`` wall boxes on mocap bodies. At the start of every control step they
are placed, from that environment's own occupancy grid, on the wall blocks that could be reached,
and parked far away otherwise. The physics cost is therefore the same in every maze, and a grid is
an array in the state: changing it (closing a corridor in some environments of a batch) never
recompiles.

Why three proxies are enough
----------------------------
Let ``p`` be the torso's x-y at the start of a control step and ``R`` the largest horizontal
distance from the torso centre to any point of any collision geom of the agent (ant: hip 0.28 +
leg 0.28 + ankle 0.57 + capsule radius 0.08 + margin 0.01 ~= 1.22 m; point: its 0.7 m sphere).
Within the step the torso moves by ``D`` (measured below 0.5 m per 0.1 s control step even for
flipping ants; walking is ~0.15 m), so every point the agent can touch lies within ``R + D < 2 m``
(half a cell) of ``p``. A wall block is a 4 m x 4 m square; a block within distance ``r < 2 m`` of
``p`` must be one of the three cells adjacent to the quadrant of ``p``'s own cell that ``p`` lies
in: the neighbour in x, the neighbour in y, and the diagonal between them. Any other block is at
least 2 m away. The agent's own cell is free (agents start in free cells and cannot enter walls).
``tests/test_envs.py`` checks ``R + D < 2`` on random rollouts and the wall distance over long
random-action runs.

Semantics follow ``ogbench/locomaze/maze.py``: RK4, dt 0.02, 5 substeps per control step, reset
noise 0.1, start and goal at cell centres + U(-1, 1) m per axis, goal observation taken after 5
random actions with the agent moved to the goal x-y, success = torso x-y within 0.5 m (1.0 m for the
point) checked after the step, episode limit 1000 steps, stochastic teleport portals.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import xml.etree.ElementTree as ET
from typing import Any, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from aqm_mjx._mjx import IMPORT_LOG, mjx, warp_available
from aqm_mjx.envs import mazes

N_PROXIES = 3
PARK_XY = 1.0e3  # parked proxies sit this far away, beyond any contact margin
GOAL_WARMUP_STEPS = 5  # OGBench takes the goal observation after 5 random actions
POINT_MOVE = 0.2  # OGBench's point: an action moves its position by this times the action, per control step
INTEGRATORS = {'euler': mujoco.mjtIntegrator.mjINT_EULER, 'rk4': mujoco.mjtIntegrator.mjINT_RK4,
               'implicitfast': mujoco.mjtIntegrator.mjINT_IMPLICITFAST}
SOLVERS = {'newton': mujoco.mjtSolver.mjSOL_NEWTON, 'cg': mujoco.mjtSolver.mjSOL_CG}
OGBENCH_SUBSTEPS = 5  # OGBench's frame skip: 5 physics steps of dt 0.02 make one 0.1 s control step


@dataclasses.dataclass(frozen=True)
class PhysicsOptions:
    """Physics settings. Defaults are OGBench's ``ant.xml`` / ``point.xml`` (MuJoCo's defaults)."""

    integrator: str = 'rk4'  # 'rk4' (OGBench), 'euler' or 'implicitfast'
    solver: str = 'newton'  # constraint solver: 'newton' (OGBench) or 'cg'
    iterations: int = 100  # solver iterations (MuJoCo default; Brax-style ants use 1)
    ls_iterations: int = 50  # line-search iterations (MuJoCo default; Brax-style ants use 4)
    impl: str = 'jax'  # MJX implementation: 'jax' (any device) or 'warp' (MuJoCo Warp, NVIDIA GPUs)
    # physics steps per control step; the control step stays OGBench's 0.1 s, so dt = 0.1 s / substeps
    substeps: int = OGBENCH_SUBSTEPS
    # MJX contact caps (max_geom_pairs per collision-type group, max_contact_points in all), or None
    # for none. 12 keeps every floor-capsule pair of the ant and its 12 nearest proxy-capsule pairs;
    # 24 contacts exceed what a walking ant touching two walls has. Measured: halves the step cost
    # with 3 proxies and matches uncapped physics (tests/test_envs.py parity checks run with caps).
    contact_caps: Optional[tuple[int, int]] = (12, 24)

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise ValueError(f'unknown integrator {self.integrator!r}; expected one of {sorted(INTEGRATORS)}')
        if self.solver not in SOLVERS:
            raise ValueError(f'unknown solver {self.solver!r}; expected one of {sorted(SOLVERS)}')
        if int(self.iterations) < 1 or int(self.ls_iterations) < 1:
            raise ValueError('iterations and ls_iterations must be >= 1')
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, int) or self.substeps < 1:
            raise ValueError(f'substeps must be an integer >= 1; got {self.substeps!r}')
        if self.contact_caps is not None and (len(self.contact_caps) != 2 or min(self.contact_caps) < 1):
            raise ValueError(f'contact_caps must be None or (max_geom_pairs, max_contact_points) >= 1; got {self.contact_caps!r}')
        if self.impl not in ('jax', 'warp'):
            raise ValueError(f"unknown MJX implementation {self.impl!r}; expected 'jax' or 'warp'")


@struct.dataclass
class State:
    """One environment's state (vmap it for a batch; every field then gains a leading ``[B]``).

    Attributes:
        data: ``mjx.Data`` of the physics.
        obs: ``[obs_size]`` observation (ant: qpos ++ qvel, 29; point: qpos, 2).
        goal: ``[obs_size]`` goal observation, made as OGBench makes it.
        goal_xy: ``[2]`` goal x-y (success is measured to it).
        grid: ``[H, W]`` int8 occupancy grid of this environment (1 = wall).
        key: PRNG key for the environment's own randomness (teleport portals).
        steps: int32 control steps taken.
        success: float32, 1.0 when the torso is within the goal tolerance after the last step.
        done: bool, success or the episode limit; a done environment no longer changes.
        reward: float32, equal to ``success`` (OGBench's sparse reward).
        task_id: int32, 1-based evaluation task, 0 for a custom start and goal.
    """

    data: Any
    obs: jax.Array
    goal: jax.Array
    goal_xy: jax.Array
    grid: jax.Array
    key: jax.Array
    steps: jax.Array
    success: jax.Array
    done: jax.Array
    reward: jax.Array
    task_id: jax.Array


def _asset_path(name: str) -> str:
    spec = importlib.util.find_spec('ogbench')
    if spec is None or not spec.submodule_search_locations:
        raise ImportError('the ogbench package (its assets define the agents) is not installed: pip install ogbench')
    return os.path.join(spec.submodule_search_locations[0], 'locomaze', 'assets', name)


def strip_weak_types(tree):
    """Every array leaf of ``tree`` with its dtype made strong (one compiled step for every call)."""
    # A weakly typed leaf (mjx.Data.time) changes type after one step and makes the second call of a
    # jitted step recompile (mujoco issue 2306); fix every dtype once.
    return jax.tree.map(lambda x: jnp.array(x, dtype=jnp.asarray(x).dtype) if isinstance(x, (jax.Array, np.ndarray)) else x, tree)


def build_mj_model(agent: str, physics: PhysicsOptions = PhysicsOptions(), n_proxies: int = N_PROXIES,
                   static_walls: Optional[np.ndarray] = None) -> mujoco.MjModel:
    """The MuJoCo model: OGBench's agent XML plus ``n_proxies`` mocap wall boxes.

    ``static_walls`` (an occupancy grid) instead adds OGBench's static wall boxes; that is the
    reference model for parity tests and benchmarks, not what the environments use.
    """
    tree = ET.parse(_asset_path(f'{agent}.xml'))
    world = tree.find('.//worldbody')
    contact_caps = physics.contact_caps
    if contact_caps is not None:
        # MJX 3.17 reads these numerics by position, not data address: they must come before
        # OGBench's 15-value init_qpos numeric or both read as 0.
        custom = tree.find('.//custom')
        if custom is None:
            custom = ET.Element('custom')
            tree.getroot().insert(0, custom)
        for pos, (name, val) in enumerate((('max_geom_pairs', contact_caps[0]), ('max_contact_points', contact_caps[1]))):
            custom.insert(pos, ET.Element('numeric', name=name, data=str(int(val))))
    half = mazes.MAZE_UNIT / 2
    z_half = mazes.MAZE_HEIGHT / 2 * mazes.MAZE_UNIT
    size = f'{half} {half} {z_half}'
    if static_walls is not None:
        for i, j in zip(*np.nonzero(np.asarray(static_walls))):
            x, y = mazes.ij_to_xy((i, j))
            ET.SubElement(world, 'geom', name=f'block_{i}_{j}', pos=f'{x} {y} {z_half}', size=size, type='box',
                          contype='1', conaffinity='1', material='wall')
    else:
        for k in range(n_proxies):
            body = ET.SubElement(world, 'body', name=f'wall_proxy_{k}', mocap='true',
                                 pos=f'{PARK_XY + 10 * k} {PARK_XY} {z_half}')
            ET.SubElement(body, 'geom', name=f'wall_proxy_geom_{k}', type='box', size=size, contype='1',
                          conaffinity='1', material='wall')
        # A proxy rests on the floor and touches its neighbours (adjacent wall blocks share faces).
        # MJX would solve those static box-plane and box-box contacts every step, and their
        # constraint rows make the ant sink through the floor. Only the agent touches walls.
        contact = tree.find('.//contact')
        if contact is None:
            contact = ET.SubElement(tree.getroot(), 'contact')
        bodies = ['world'] + [f'wall_proxy_{k}' for k in range(n_proxies)]
        for a in range(len(bodies)):
            for b in range(max(a + 1, 1), len(bodies)):
                ET.SubElement(contact, 'exclude', body1=bodies[a], body2=bodies[b])
    m = mujoco.MjModel.from_xml_string(ET.tostring(tree.getroot(), encoding='unicode'))
    m.opt.integrator = INTEGRATORS[physics.integrator]
    m.opt.solver = SOLVERS[physics.solver]
    m.opt.iterations = int(physics.iterations)
    m.opt.ls_iterations = int(physics.ls_iterations)
    # the XML's dt is OGBench's (0.02 s, 5 to a control step); other substeps keep the control step
    if int(physics.substeps) != OGBENCH_SUBSTEPS:  # (OGBench's own dt stays bit for bit the XML's)
        m.opt.timestep = m.opt.timestep * OGBENCH_SUBSTEPS / int(physics.substeps)
    return m


class MazeEnv:
    """An OGBench locomaze task in MJX. Build it with :func:`aqm_mjx.envs.make`.

    ``reset(key, task_id=None, grid=None) -> State`` and ``step(state, action) -> State`` are pure,
    jittable and vmappable. Static facts (layout, tasks, sizes) are plain attributes.
    """

    def __init__(self, agent: str, maze: str, physics: PhysicsOptions = PhysicsOptions(),
                 max_episode_steps: int = 1000, terminate_at_goal: bool = True):
        if agent not in ('ant', 'point'):
            raise ValueError(f"unknown agent {agent!r}; expected 'ant' or 'point'")
        if int(max_episode_steps) < 1:
            raise ValueError('max_episode_steps must be >= 1')
        self.agent = agent
        self.maze = mazes.check_maze_name(maze)
        self.name = f'{agent}maze-{maze}'
        self.physics = physics
        self.max_episode_steps = int(max_episode_steps)
        self.terminate_at_goal = bool(terminate_at_goal)  # False: OGBench's data-collection setting
        self.frame_skip = int(physics.substeps)
        self.goal_tol = 1.0 if agent == 'point' else 0.5
        self.reset_noise = 0.1
        self.layout = mazes.layout(maze)
        self.tasks = mazes.tasks(maze)
        self.num_tasks = len(self.tasks)
        self.teleport = maze == 'teleport'

        if physics.impl == 'warp' and not warp_available():
            raise RuntimeError("impl='warp' needs MuJoCo Warp on an NVIDIA GPU: pip install 'mujoco-mjx[warp]' "
                               f'(importing it said: {IMPORT_LOG.strip() or "nothing"})')
        self.mj_model = build_mj_model(agent, physics)
        local = jax.local_devices()[0]  # this process's: with several processes, devices()[0] may be another's
        self.mjx_model = mjx.put_model(self.mj_model, device=local, impl=physics.impl)
        self.obs_size = self.mj_model.nq + self.mj_model.nv if agent == 'ant' else self.mj_model.nq
        self.action_size = self.mj_model.nu
        self._qpos0 = jnp.asarray(self.mj_model.qpos0, jnp.float32)
        self.template = strip_weak_types(mjx.make_data(self.mjx_model, device=local))
        self._layout = jnp.asarray(self.layout)
        self._task_init_xy = jnp.asarray([t.init_xy for t in self.tasks], jnp.float32)
        self._task_goal_xy = jnp.asarray([t.goal_xy for t in self.tasks], jnp.float32)
        z_half = mazes.MAZE_HEIGHT / 2 * mazes.MAZE_UNIT
        self._park = jnp.asarray([[PARK_XY + 10 * k, PARK_XY, z_half] for k in range(N_PROXIES)], jnp.float32)
        self._tp_in = jnp.asarray(mazes.ij_to_xy(mazes.TELEPORT_IN), jnp.float32)
        self._tp_out = jnp.asarray(mazes.ij_to_xy(mazes.TELEPORT_OUT), jnp.float32)

    # ------------------------------------------------------------------ geometry
    def xy_to_ij(self, xy: jax.Array) -> jax.Array:
        """Cell index of positions: ``xy [..., 2]`` -> int32 ``ij [..., 2]`` (row i from y, column j from x)."""
        return mazes.xy_to_ij(xy)

    def proxy_positions(self, xy: jax.Array, grid: jax.Array) -> jax.Array:
        """Where the wall proxies go for an agent at ``xy [2]`` in ``grid [H, W]``: ``[N_PROXIES, 3]``.

        The three cells adjacent to the quadrant of the agent's cell that holds ``xy``; a cell that
        is a wall (or outside the grid) gets a box at its centre, a free cell a parked box.
        """
        ij = self.xy_to_ij(xy)
        centre = ij[::-1].astype(jnp.float32) * mazes.MAZE_UNIT - mazes.MAZE_OFFSET  # (x, y) of own cell
        s = jnp.where(xy >= centre, 1, -1)  # (sx, sy)
        di = jnp.array([0, s[1], s[1]])
        dj = jnp.array([s[0], 0, s[0]])
        ci, cj = ij[0] + di, ij[1] + dj
        h, w = grid.shape
        inside = (ci >= 0) & (ci < h) & (cj >= 0) & (cj < w)
        wall = jnp.where(inside, grid[jnp.clip(ci, 0, h - 1), jnp.clip(cj, 0, w - 1)] > 0, True)
        z = self._park[:, 2]
        pos = jnp.stack([cj * mazes.MAZE_UNIT - mazes.MAZE_OFFSET, ci * mazes.MAZE_UNIT - mazes.MAZE_OFFSET, z], -1)
        return jnp.where(wall[:, None], pos.astype(jnp.float32), self._park)

    # ------------------------------------------------------------------ physics
    def _obs(self, data) -> jax.Array:
        if self.agent == 'ant':
            return jnp.concatenate([data.qpos, data.qvel]).astype(jnp.float32)
        return data.qpos.astype(jnp.float32)

    def physics_step(self, data, action: jax.Array, grid: jax.Array):
        """One control step (``frame_skip`` physics steps) of ``data`` under ``action [action_size]``."""
        action = jnp.clip(action, -1.0, 1.0)
        data = data.replace(mocap_pos=self.proxy_positions(data.qpos[:2], grid))
        if self.agent == 'ant':
            data = data.replace(ctrl=action.astype(data.ctrl.dtype))
        else:
            # OGBench's point: the action moves the position directly, velocity is zeroed, ctrl stays 0.
            data = data.replace(qpos=data.qpos + POINT_MOVE * action.astype(data.qpos.dtype),
                                qvel=jnp.zeros_like(data.qvel))

        def substep(d, _):
            return mjx.step(self.mjx_model, d), None

        data, _ = jax.lax.scan(substep, data, None, length=self.frame_skip)
        return data

    def _noisy_state(self, key):
        k_pos, k_vel = jax.random.split(key)
        qpos = self._qpos0 + jax.random.uniform(k_pos, self._qpos0.shape, minval=-self.reset_noise, maxval=self.reset_noise)
        qvel = self.reset_noise * jax.random.normal(k_vel, (self.mj_model.nv,))
        return qpos, qvel

    def set_state(self, qpos, qvel):
        """``mjx.Data`` at ``qpos [nq]``, ``qvel [nv]`` (the rest from the model's template)."""
        t = self.template
        return t.replace(qpos=qpos.astype(t.qpos.dtype), qvel=qvel.astype(t.qvel.dtype))

    def goal_observation(self, key: jax.Array, goal_xy: jax.Array) -> jax.Array:
        """OGBench's goal observation ``[obs_size]``: reset, 5 random actions, agent moved to ``goal_xy``."""
        k_state, k_act = jax.random.split(key)
        data = self.set_state(*self._noisy_state(k_state))
        if self.agent == 'ant':
            # OGBench takes these steps at the origin, a cell centre 2 m from any wall, which the ant
            # cannot reach in 5 steps: with the proxies parked the physics is the same.
            actions = jax.random.uniform(k_act, (GOAL_WARMUP_STEPS, self.action_size), minval=-1.0, maxval=1.0)
            empty = jnp.zeros_like(self._layout)

            def warm(d, a):
                return self.physics_step(d, a, empty), None

            data, _ = jax.lax.scan(warm, data, actions)
        # (For the point the observation is qpos alone, which set_xy overwrites: no steps needed.)
        qpos = data.qpos.at[:2].set(goal_xy.astype(data.qpos.dtype))
        return self._obs(data.replace(qpos=qpos))

    # ------------------------------------------------------------------ API
    def _check_task_id(self, task_id):
        if isinstance(task_id, jax.core.Tracer):
            return jnp.clip(jnp.asarray(task_id, jnp.int32), 1, self.num_tasks)
        tid = np.asarray(task_id)
        if tid.dtype.kind not in 'iu' or np.any(tid < 1) or np.any(tid > self.num_tasks):
            raise ValueError(f'task_id must be an integer in [1, {self.num_tasks}] for {self.name}; got {task_id!r}')
        return jnp.asarray(tid, jnp.int32)

    def _grid(self, grid):
        if grid is None:
            return self._layout
        if not isinstance(grid, jax.core.Tracer):
            grid = mazes.validate_grid(grid, self.maze)
        elif tuple(grid.shape) != self.layout.shape:
            raise ValueError(f'grid for maze {self.maze!r} must have shape {self.layout.shape}; got {tuple(grid.shape)}')
        return jnp.asarray(grid, jnp.int8)

    def reset(self, key: jax.Array, task_id=None, grid=None, cells=None) -> State:
        """Start an evaluation episode.

        Args:
            key: PRNG key.
            task_id: 1-based task (int or int array, traced allowed); None draws one uniformly. With
                ``cells``, a task id of 0 starts and ends in those cells instead.
            grid: ``[H, W]`` occupancy grid for this environment; None is the maze's layout.
            cells: optional int ``[4]`` (init i, init j, goal i, goal j): the start and goal cells of a
                task-0 episode (calibration episodes), with the tasks' start and goal noise.
        Returns:
            State with ``steps == 0``.
        """
        k_task, k_init, k_goal, k_rest = jax.random.split(key, 4)
        if task_id is None:
            tid = jax.random.randint(k_task, (), 1, self.num_tasks + 1)
        elif cells is not None:
            tid = jnp.clip(jnp.asarray(task_id, jnp.int32), 0, self.num_tasks)
        else:
            tid = self._check_task_id(task_id)
        init_c, goal_c = self._task_init_xy[jnp.maximum(tid, 1) - 1], self._task_goal_xy[jnp.maximum(tid, 1) - 1]
        if cells is not None:
            c = mazes.ij_to_xy(jnp.reshape(jnp.asarray(cells), (2, 2)), xp=jnp)  # [start, goal] cell centres
            init_c = jnp.where(tid > 0, init_c, c[0])
            goal_c = jnp.where(tid > 0, goal_c, c[1])
        noise = mazes.START_GOAL_NOISE * mazes.MAZE_UNIT / 4
        init_xy = init_c + jax.random.uniform(k_init, (2,), minval=-noise, maxval=noise)
        goal_xy = goal_c + jax.random.uniform(k_goal, (2,), minval=-noise, maxval=noise)
        return self.reset_to(k_rest, init_xy, goal_xy, grid=grid, task_id=tid)

    def reset_to(self, key: jax.Array, init_xy: jax.Array, goal_xy: jax.Array, grid=None, task_id=0) -> State:
        """Start an episode at ``init_xy [2]`` with goal ``goal_xy [2]`` (no further noise on either)."""
        k_goal, _, k_env = jax.random.split(key, 3)
        grid = self._grid(grid)
        goal_xy = jnp.asarray(goal_xy, jnp.float32)
        goal = self.goal_observation(k_goal, goal_xy)
        data = self.set_state(*self.initial_state(key, init_xy))
        f32 = jnp.float32
        return State(data=data, obs=self._obs(data), goal=goal, goal_xy=goal_xy, grid=grid, key=k_env,
                     steps=jnp.zeros((), jnp.int32), success=jnp.zeros((), f32), done=jnp.zeros((), bool),
                     reward=jnp.zeros((), f32), task_id=jnp.asarray(task_id, jnp.int32))

    def initial_state(self, key: jax.Array, init_xy: jax.Array) -> tuple:
        """``(qpos [nq], qvel [nv])`` that :meth:`reset_to` starts from with the same ``key``: the reset
        noise, the torso moved to ``init_xy [2]`` (host-physics collection starts its episodes here)."""
        qpos, qvel = self._noisy_state(jax.random.split(key, 3)[1])
        return qpos.at[:2].set(jnp.asarray(init_xy, jnp.float32)), qvel

    def step(self, state: State, action: jax.Array) -> State:
        """Advance one control step with ``action [action_size]`` (clipped to [-1, 1]).

        Success is checked after the step, then (teleport maze) portals fire; as in OGBench the
        returned observation is the one before a teleport. The episode is done at the goal (unless
        ``terminate_at_goal=False``) or at ``max_episode_steps``; a done state is returned unchanged.
        """
        data = self.physics_step(state.data, action, state.grid)
        obs = self._obs(data)
        xy = data.qpos[:2]
        success = (jnp.linalg.norm(xy - state.goal_xy) <= self.goal_tol).astype(jnp.float32)
        key = state.key
        if self.teleport:
            key, k_out = jax.random.split(key)
            near = jnp.linalg.norm(xy[None] - self._tp_in, axis=-1) <= mazes.TELEPORT_RADIUS * 1.5
            out = self._tp_out[jax.random.randint(k_out, (), 0, self._tp_out.shape[0])]
            data = data.replace(qpos=data.qpos.at[:2].set(jnp.where(near.any(), out, xy).astype(data.qpos.dtype)))
        steps = state.steps + 1
        done = ((success > 0) & self.terminate_at_goal) | (steps >= self.max_episode_steps)
        new = state.replace(data=data, obs=obs, key=key, steps=steps, success=success, done=done, reward=success)
        return jax.tree.map(lambda old, nw: jnp.where(state.done, old, nw), state, new)

    def __repr__(self):
        p = self.physics
        return (f'MazeEnv({self.name}, obs {self.obs_size}, action {self.action_size}, tasks {self.num_tasks}, '
                f'{p.integrator} x{p.substeps}/{p.solver} {p.iterations}x{p.ls_iterations}, caps {p.contact_caps}, '
                f'impl={p.impl})')
