"""On-device dataset collection in MJX with OGBench's recipe (``navigate``, ``stitch``, ``explore``).

Each episode starts at a uniformly drawn free cell (cell centre + U(-1, 1) m per axis) and runs for
exactly ``steps`` control steps with the episode never ending at a goal (OGBench's
``terminate_at_goal=False``):

- ``navigate``: the goal is a random *junction* cell (a free cell that is not a straight corridor
  cell); each time it is reached a new one is drawn. Action noise 0.2.
- ``stitch``: the goal is a cell exactly 4 BFS steps from the start (the start cell itself when none
  exists), kept for the whole 201-state episode. Noise 0.2.
- ``explore``: a random unit direction redrawn every 10 steps, action noise 1.0.

The expert is fed the unit direction to the next BFS cell (the goal itself inside the goal cell):
for the ant the scripted trot (:func:`aqm_mjx.data.expert.gait_action`), for the point agent the direction
itself, as in OGBench. Actions are ``clip(expert + N(0, noise), -1, 1)``. Recorded per step: the
observation and ``qpos``/``qvel`` before the step, the action, and ``terminals`` True at the last
step of each episode: OGBench's file layout, written by :func:`aqm_mjx.data.dataset.write_ogbench`.

Episode ``e`` uses the key ``fold_in(PRNGKey(seed), e)``, so the data do not depend on how many
episodes run side by side. ``episodes`` training episodes are followed by ``episodes // 10``
validation episodes, OGBench's ``-val`` twin.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import math
import os
import time
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from aqm_mjx import envs, files, processes
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.data import expert
from aqm_mjx.envs import locomaze, mazes, shifts
from aqm_mjx.progress import BAR_FORMAT, EVERY, ChunkBar, tick

STYLES = ('navigate', 'stitch', 'explore')
PHYSICS = ('mjx', 'mujoco')  # CollectConfig.physics: MJX on the device, or MuJoCo's C library on the host
STITCH_CELLS = 4  # BFS steps from the start cell to a stitch goal
EXPLORE_EVERY = 10  # control steps between explore direction draws


@dataclasses.dataclass(frozen=True)
class Recipe:
    """OGBench's numbers for one dataset: training episodes, states per episode, action noise."""

    episodes: int
    steps: int
    noise: float


def recipe(maze: str, style: str) -> Recipe:
    """OGBench's recipe (``shared/reference/ogbench-antmaze.md``) for ``maze`` and ``style``."""
    check_style(style)
    mazes.check_maze_name(maze)
    if style == 'navigate':
        return Recipe(500, 2001, 0.2) if maze == 'giant' else Recipe(1000, 1001, 0.2)
    if style == 'stitch':
        return Recipe(5000, 201, 0.2)
    return Recipe(10000, 501, 1.0)


def check_style(style: str) -> str:
    if style not in STYLES:
        raise ValueError(f'unknown collection style {style!r}; expected one of {", ".join(STYLES)}')
    return style


@dataclasses.dataclass(frozen=True)
class CollectConfig:
    """What to collect. ``None`` fields take OGBench's value from :func:`recipe`.

    Attributes:
        env: environment name, e.g. ``antmaze-medium``.
        style: ``navigate``, ``stitch`` or ``explore``.
        episodes: training episodes (validation adds ``episodes // 10``).
        steps: states per episode (OGBench: 1001 navigate, 201 stitch, 501 explore).
        noise: standard deviation of the Gaussian action noise.
        batch: episodes simulated side by side in one jitted call.
        seed: base seed; episode ``e`` uses ``fold_in(PRNGKey(seed), e)``.
        layout: the walls the data are collected in: ``'base'`` (the maze's layout) or a variant of
            :mod:`aqm_mjx.envs.shifts` (``close-I-J``, ``open-I-J``), for models trained on a shifted
            layout (the training-layout half of the paper's Figure 3).
        physics: ``'mjx'`` (one jitted MJX program) or ``'mujoco'`` (MuJoCo's C library on the host).
        physics_preset: the physics settings of either (:mod:`aqm_mjx.envs.physics`): ``'ogbench'``
            (OGBench's), ``'fast'`` or another row of the fidelity study.
        threads: ``physics='mujoco'``: threads that step the batch's episodes (``0``: one per core this
            process may use). MuJoCo releases Python's lock while it steps, and each episode keeps its
            own ``MjData``, so the data are the same for every count.
    """

    env: str = 'antmaze-medium'
    style: str = 'navigate'
    episodes: Optional[int] = None
    steps: Optional[int] = None
    noise: Optional[float] = None
    batch: int = 64
    seed: int = 0
    layout: str = 'base'
    physics: str = 'mjx'
    physics_preset: str = 'ogbench'
    threads: int = 0

    def resolved(self) -> 'CollectConfig':
        """The config with OGBench's defaults filled in and every field checked."""
        _, maze = envs.parse_name(self.env)
        r = recipe(maze, self.style)
        c = dataclasses.replace(self, episodes=r.episodes if self.episodes is None else int(self.episodes),
                                steps=r.steps if self.steps is None else int(self.steps),
                                noise=r.noise if self.noise is None else float(self.noise))
        if c.episodes < 1:
            raise ValueError(f'episodes must be >= 1; got {c.episodes}')
        if c.steps < 2:
            raise ValueError(f'steps (states per episode) must be >= 2; got {c.steps}')
        if not (math.isfinite(c.noise) and c.noise >= 0):
            raise ValueError(f'noise must be a finite number >= 0; got {c.noise}')
        if int(c.batch) < 1:
            raise ValueError(f'batch must be >= 1; got {c.batch}')
        if int(c.threads) < 0:
            raise ValueError(f'threads must be >= 0 (0: one per core); got {c.threads}')
        shifts.variant(maze, c.layout)  # an unknown layout names the maze's suite
        if c.physics not in PHYSICS:
            raise ValueError(f'unknown collection physics {c.physics!r}; expected one of {", ".join(PHYSICS)}')
        envs.physics_presets.get(c.physics_preset)  # an unknown preset names the study's rows
        return c

    def grid(self) -> np.ndarray:
        """``int8 [H, W]``: the occupancy grid of :attr:`layout`."""
        return shifts.variant(envs.parse_name(self.env)[1], self.layout)

    @property
    def val_episodes(self) -> int:
        return int(self.episodes) // 10


# ----------------------------------------------------------------------------------------- episode
def _noisy_xy(key, ij):
    noise = mazes.START_GOAL_NOISE * mazes.MAZE_UNIT / 4
    xy = ij[::-1].astype(jnp.float32) * mazes.MAZE_UNIT - mazes.MAZE_OFFSET
    return xy + jax.random.uniform(key, (2,), minval=-noise, maxval=noise)


@dataclasses.dataclass(frozen=True)
class ExpertParts:
    """The recipe's pure pieces for one environment, shared by both physics backends (one episode;
    ``vmap`` them):

    - ``start(key) -> (init_xy [2], goal_xy [2], phase [], k_reset, k_loop)``: the start cell and
      first goal with their noise, the gait's phase, the key of the reset noise and of the steps;
    - ``control(qpos, qvel, goal_xy, key, direction, t, phase) -> (action, key, direction, k_new,
      k_newxy)``: the expert's noisy action before step ``t`` and the keys of a goal redraw;
    - ``after(hit, reached, goal_xy, k_new, k_newxy) -> (reached, goal_xy)``: the count of goals
      reached and the goal after the step (navigate draws a new junction where ``hit``).
    """

    start: Callable
    control: Callable
    after: Callable


def expert_parts(env, style: str, noise: float, grid: np.ndarray) -> ExpertParts:
    """:class:`ExpertParts` of ``style`` with action noise ``noise`` in the walls ``grid [H, W]``."""
    check_style(style)
    h, w = grid.shape
    free = jnp.asarray(mazes.free_cells(grid))
    junctions = jnp.asarray(mazes.junction_cells(grid))
    ring_cells, ring_count = (jnp.asarray(a) for a in mazes.cells_at_bfs_distance(grid, STITCH_CELLS))
    table = jnp.asarray(expert.bfs_next_cell(grid))
    ant = env.agent == 'ant'

    def draw_junction(key):
        return junctions[jax.random.randint(key, (), 0, junctions.shape[0])]

    def start(key):
        k_init, k_goal, k_gxy, k_ixy, k_reset, k_phase, k_loop = jax.random.split(key, 7)
        f = jax.random.randint(k_init, (), 0, free.shape[0])
        init_ij = free[f]
        if style == 'stitch':
            goal_ij = ring_cells[f, jax.random.randint(k_goal, (), 0, ring_count[f])]
        else:
            goal_ij = draw_junction(k_goal)
        phase = jax.random.uniform(k_phase, (), maxval=2 * jnp.pi)
        return _noisy_xy(k_ixy, init_ij), _noisy_xy(k_gxy, goal_ij), phase, k_reset, k_loop

    def control(qpos, qvel, goal_xy, key, direction, t, phase):
        key, k_dir, k_noise, k_new, k_newxy = jax.random.split(key, 5)
        if style == 'explore':
            fresh = jax.random.normal(k_dir, (2,))
            fresh = fresh / (jnp.linalg.norm(fresh) + 1e-6)
            direction = jnp.where(t % EXPLORE_EVERY == 0, fresh, direction)
        else:
            d = expert.waypoint_command(qpos[:2], goal_xy, table, (h, w))
            direction = d / (jnp.linalg.norm(d) + 1e-6)
        a = expert.gait_action(qpos, qvel, direction, t, phase) if ant else direction
        a = jnp.clip(a + noise * jax.random.normal(k_noise, a.shape), -1.0, 1.0)
        return a, key, direction, k_new, k_newxy

    def after(hit, reached, goal_xy, k_new, k_newxy):
        if style == 'navigate':
            return reached + hit.astype(jnp.int32), jnp.where(hit, _noisy_xy(k_newxy, draw_junction(k_new)), goal_xy)
        if style == 'stitch':
            return jnp.maximum(reached, hit.astype(jnp.int32)), goal_xy
        return reached, goal_xy

    return ExpertParts(start=start, control=control, after=after)


def _upright(env, qpos, xp=jnp):
    """bool ``[...]``: the ant's torso up axis above the horizon (always True for the point)."""
    if env.agent != 'ant':
        return xp.ones(qpos.shape[:-1], bool)
    return (1 - 2 * (qpos[..., 4] ** 2 + qpos[..., 5] ** 2)) > 0


def episode_fn(env, style: str, steps: int, noise: float, progress: Optional[Callable] = None, grid=None
               ) -> Callable[[jax.Array], dict]:
    """A pure, jittable, vmappable function ``key -> one episode`` of OGBench-style data, in MJX.

    ``env`` must be built with ``terminate_at_goal=False`` and ``max_episode_steps >= steps``.
    ``grid`` (``[H, W]``, default the maze's layout): the walls of every episode; starts, goals and
    the expert's BFS waypoints are drawn in it.
    ``progress``: a host hook given the steps done every :data:`aqm_mjx.progress.EVERY` steps
    (once per call under ``vmap``: the step count is not batched).

    Returns:
        ``f(key) -> dict`` with ``observations [steps, obs_size]``, ``actions [steps, action_size]``,
        ``qpos [steps, nq]``, ``qvel [steps, nv]``, ``goals_reached []`` int32 (navigate: goals
        reached; stitch: 1 if the goal was reached; explore: 0) and ``upright [steps]`` bool (the
        torso's up axis above the horizon; always True for the point).
    """
    check_style(style)
    _check_env(env, steps)
    if grid is None:  # the maze's own walls, which the environment holds already
        walls, grid = None, np.asarray(env.layout)
    else:
        grid = mazes.validate_grid(grid, env.maze)
        walls = jnp.asarray(grid)
    parts = expert_parts(env, style, noise, grid)

    def run(key):
        init_xy, goal_xy, phase, k_reset, k_loop = parts.start(key)
        state = env.reset_to(k_reset, init_xy, goal_xy, grid=walls)

        def body(carry, t):
            state, key, direction, reached = carry
            a, key, direction, k_new, k_newxy = parts.control(state.data.qpos, state.data.qvel, state.goal_xy, key,
                                                              direction, t, phase)
            record = dict(observations=state.obs, actions=a, qpos=state.data.qpos.astype(jnp.float32),
                          qvel=state.data.qvel.astype(jnp.float32))
            state = env.step(state, a)
            reached, goal_xy = parts.after(state.success > 0, reached, state.goal_xy, k_new, k_newxy)
            state = state.replace(goal_xy=goal_xy)
            record['upright'] = _upright(env, state.data.qpos)
            tick(progress, t, steps)
            return (state, key, direction, reached), record

        init = (state, k_loop, jnp.array([1.0, 0.0]), jnp.zeros((), jnp.int32))
        (_, _, _, reached), out = jax.lax.scan(body, init, jnp.arange(steps))
        out['goals_reached'] = reached
        return out

    return run


def host_cores() -> int:
    """The cores this process may run on (its affinity where the platform tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def _check_env(env, steps: int) -> None:
    if env.terminate_at_goal:
        raise ValueError('collection needs an environment built with terminate_at_goal=False')
    if env.max_episode_steps < steps:
        raise ValueError(f'the environment ends episodes after {env.max_episode_steps} steps; collection needs '
                         f'max_episode_steps >= steps ({steps})')


class HostEpisodes:
    """The recipe's episodes with OGBench's physics on the host: MuJoCo's C library stepping a model
    with the maze's static wall boxes (OGBench's own), one ``MjData`` per episode of a chunk, and the
    expert's pieces (:func:`expert_parts`) jitted and vmapped over the chunk once per control step.

    ``HostEpisodes(env, style, steps, noise, grid)(keys, progress) -> dict``: the same keys, records
    and summaries as ``jax.vmap(episode_fn(...))(keys)``, as NumPy arrays. The trajectories are not
    MJX's bit for bit (other contact and solver code, float64), so a dataset says which physics made it.
    On a CPU this is several times faster than MJX, whose collision and solver code is built for
    accelerator batches (``benchmarks/throughput/bench_collect.py``). The teleport maze is MJX's only.
    """

    def __init__(self, env, style: str, steps: int, noise: float, grid=None, threads: int = 0):
        check_style(style)
        _check_env(env, steps)
        if env.teleport:
            raise ValueError('host physics does not model the teleport portals; collect antmaze-teleport in MJX')
        self.grid = np.asarray(env.layout) if grid is None else mazes.validate_grid(grid, env.maze)
        self.env, self.steps = env, int(steps)
        self.model = locomaze.build_mj_model(env.agent, env.physics, static_walls=self.grid)
        parts = expert_parts(env, style, noise, self.grid)

        def start(key):
            init_xy, goal_xy, phase, k_reset, k_loop = parts.start(key)
            return (goal_xy, phase, *env.initial_state(k_reset, init_xy), k_loop)

        self.start = jax.jit(jax.vmap(start))
        self.control = jax.jit(jax.vmap(parts.control, in_axes=(0, 0, 0, 0, 0, None, 0)))
        self.after = jax.jit(jax.vmap(parts.after))
        self.datas: list = []
        self.threads = int(threads) or host_cores()

    def _step(self, d, a) -> None:
        """One control step of one episode: ``frame_skip`` physics steps (OGBench's point moves its
        position by ``POINT_MOVE`` a with the velocity zeroed first, as :meth:`MazeEnv.physics_step`)."""
        if self.env.agent == 'ant':
            d.ctrl[:] = a
        else:
            d.qpos[:] = d.qpos + locomaze.POINT_MOVE * a
            d.qvel[:] = 0.0
        for _ in range(self.env.frame_skip):
            mujoco.mj_step(self.model, d)

    def _step_slice(self, datas, a) -> None:
        for d, a_b in zip(datas, a):
            self._step(d, a_b.astype(np.float64))

    def __call__(self, keys, progress: Optional[Callable] = None) -> dict:
        n = len(keys)
        while len(self.datas) < n:
            self.datas.append(mujoco.MjData(self.model))
        datas = self.datas[:n]
        # contiguous slices of the batch, one per thread; each MjData only ever steps in its own slice
        parts = min(self.threads, n)
        if parts <= 1:
            return self._episodes(keys, datas, lambda a: self._step_slice(datas, a), progress)
        bounds = np.linspace(0, n, parts + 1).astype(int)
        slices = [slice(bounds[i], bounds[i + 1]) for i in range(parts)]
        with concurrent.futures.ThreadPoolExecutor(parts) as pool:
            def step(a):  # list(): an exception in a thread is raised here
                list(pool.map(lambda sl: self._step_slice(datas[sl], a[sl]), slices))
            return self._episodes(keys, datas, step, progress)

    def _episodes(self, keys, datas, step: Callable, progress: Optional[Callable]) -> dict:
        env, n, t_all = self.env, len(keys), self.steps
        goal_xy, phase, qpos0, qvel0, key = self.start(jnp.asarray(keys))
        qpos0, qvel0 = np.asarray(qpos0, np.float64), np.asarray(qvel0, np.float64)
        for b, d in enumerate(datas):
            mujoco.mj_resetData(self.model, d)
            d.qpos[:], d.qvel[:] = qpos0[b], qvel0[b]
            mujoco.mj_forward(self.model, d)
        nq, nv = self.model.nq, self.model.nv
        out = dict(observations=np.empty((n, t_all, env.obs_size), np.float32),
                   actions=np.empty((n, t_all, env.action_size), np.float32),
                   qpos=np.empty((n, t_all, nq), np.float32), qvel=np.empty((n, t_all, nv), np.float32),
                   upright=np.empty((n, t_all), bool))
        direction = jnp.tile(jnp.array([1.0, 0.0]), (n, 1))
        reached = jnp.zeros(n, jnp.int32)
        qpos = np.stack([d.qpos for d in datas])
        qvel = np.stack([d.qvel for d in datas])
        for t in range(t_all):
            a, key, direction, k_new, k_newxy = self.control(jnp.asarray(qpos, jnp.float32),
                                                             jnp.asarray(qvel, jnp.float32), goal_xy, key,
                                                             direction, t, phase)
            a = np.asarray(a)
            out['qpos'][:, t], out['qvel'][:, t], out['actions'][:, t] = qpos, qvel, a
            step(a)
            qpos = np.stack([d.qpos for d in datas])
            qvel = np.stack([d.qvel for d in datas])
            out['upright'][:, t] = _upright(env, qpos, np)
            hit = np.linalg.norm(qpos[:, :2] - np.asarray(goal_xy), axis=-1) <= env.goal_tol
            reached, goal_xy = self.after(jnp.asarray(hit), reached, goal_xy, k_new, k_newxy)
            if progress is not None and ((t + 1) % EVERY == 0 or t + 1 == t_all):
                progress(t + 1)
        out['observations'] = (np.concatenate([out['qpos'], out['qvel']], -1) if env.agent == 'ant'
                               else out['qpos'].copy())
        out['goals_reached'] = np.asarray(reached)
        return out


# ---------------------------------------------------------------------------------------- collect
@dataclasses.dataclass
class CollectResult:
    """Arrays in OGBench's layout for the training and validation splits, plus how it went."""

    train: dict
    val: dict
    config: CollectConfig
    stats: dict


def collect(cfg: CollectConfig, physics: Optional[dict] = None, progress: bool = True) -> CollectResult:
    """Collect ``cfg.episodes`` training and ``cfg.episodes // 10`` validation episodes.

    Episodes run ``cfg.batch`` at a time: in MJX as one jitted, vmapped call (time under
    ``lax.scan``), or with ``cfg.physics == 'mujoco'`` on the host (:class:`HostEpisodes`); the host
    copies each chunk once into preallocated arrays. With several processes (:mod:`aqm_mjx.processes`,
    each calling this with the same ``cfg``), chunk ``i`` runs on process ``i mod N``, on its own
    devices (or host), and every process gathers every chunk: the same arrays, episode for episode,
    as one process collects (episode ``e``'s key is ``fold_in(seed, e)`` and the chunks are the same);
    the bar shows on process 0.

    Args:
        cfg: what to collect (see :class:`CollectConfig`).
        physics: physics overrides for :func:`aqm_mjx.envs.make` (e.g. ``{'iterations': 4}``; the host
            model takes them too).
        progress: show a progress bar over episodes; it moves every few dozen steps within a chunk.
    Returns:
        :class:`CollectResult` with ``train``/``val`` dicts of ``observations``, ``actions``,
        ``terminals``, ``qpos``, ``qvel``, and ``stats`` (timings, goals reached, flips).
    """
    cfg = cfg.resolved()
    env = envs.make(cfg.env, physics=cfg.physics_preset, max_episode_steps=cfg.steps, terminate_at_goal=False,
                    **(physics or {}))
    total = cfg.episodes + cfg.val_episodes
    batch = min(int(cfg.batch), total)
    bar = _progress(total, f'collect {cfg.env} {cfg.style}', progress and processes.writer())
    ticks = ChunkBar(bar)
    grid = None if cfg.layout == shifts.BASE else cfg.grid()
    if cfg.physics == 'mujoco':
        host = HostEpisodes(env, cfg.style, cfg.steps, cfg.noise, grid=grid, threads=cfg.threads)
        run = functools.partial(host, progress=ticks)
    else:
        run = jax.jit(jax.vmap(episode_fn(env, cfg.style, cfg.steps, cfg.noise, progress=ticks, grid=grid)))
    base = jax.random.PRNGKey(cfg.seed)
    n, t = total * cfg.steps, cfg.steps
    nq, nv = env.mj_model.nq, env.mj_model.nv
    buf = dict(observations=np.empty((n, env.obs_size), np.float32), actions=np.empty((n, env.action_size), np.float32),
               qpos=np.empty((n, nq), np.float32), qvel=np.empty((n, nv), np.float32))
    reached = np.empty(total, np.int64)
    flipped = np.empty(total, bool)
    count, me = jax.process_count(), jax.process_index()
    chunks = list(range(0, total, batch))
    rounds = -(-len(chunks) // count)  # several processes: in round r, process p runs chunk r * count + p
    t0 = time.perf_counter()
    first_chunk_s = None  # the first call compiles, then runs one chunk
    try:
        for r in range(rounds):
            firsts = chunks[r * count:(r + 1) * count]
            sizes = [min(batch, total - f) for f in firsts]
            mine = firsts[me] if me < len(firsts) else None
            ticks.start(sum(sizes), t)  # the round's episodes, moved on as this process's chunk runs
            out = _chunk(run, base, mine, batch, total, cfg.physics == 'mjx', env, t)
            ticks.finish()
            if first_chunk_s is None:
                first_chunk_s = time.perf_counter() - t0
            what = f'collecting chunks {r * count + 1}-{r * count + len(firsts)} of {len(chunks)}'
            got = processes.gather(out, what)  # every process's chunk of this round, on every process
            for first, m, o in zip(firsts, sizes, range(len(firsts))):
                rows = slice(first * t, (first + m) * t)
                for k in buf:
                    buf[k][rows] = got[k][o, :m].reshape(m * t, -1)
                reached[first:first + m] = got['goals_reached'][o, :m]
                flipped[first:first + m] = ~got['upright'][o, :m]
            if bar is not None:
                bar.set_postfix(transitions=(firsts[-1] + sizes[-1]) * t)
    finally:  # an error (a partner lost) starts on a line of its own
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - t0
    terminals = np.zeros(n, bool)
    terminals[t - 1::t] = True
    buf['terminals'] = terminals
    cut = cfg.episodes * t
    train = {k: v[:cut] for k, v in buf.items()}
    val = {k: v[cut:] for k, v in buf.items()}
    run_s = wall - first_chunk_s
    steady = (total - min(count * batch, total)) * t  # after the first round, which compiled
    stats = dict(env=cfg.env, style=cfg.style, layout=cfg.layout, episodes=cfg.episodes, val_episodes=cfg.val_episodes,
                 steps=cfg.steps, noise=cfg.noise, batch=batch, seed=cfg.seed, transitions=int(n),
                 wall_s=round(wall, 2), first_chunk_s=round(first_chunk_s, 2),
                 steady_transitions_per_s=round(steady / run_s, 1) if steady and run_s > 0 else None,
                 goals_reached_mean=float(reached.mean()), flipped_episodes=int(flipped.sum()),
                 progress_callbacks=ticks.calls, physics=cfg.physics, processes=count,
                 physics_preset=envs.physics_presets.describe(env.physics),
                 backend=jax.default_backend() if cfg.physics == 'mjx' else 'host')
    return CollectResult(train=train, val=val, config=cfg, stats=stats)


def _chunk(run, base, first: Optional[int], batch: int, total: int, mjx: bool, env, t: int) -> dict:
    """One chunk's records as host arrays, ``batch`` episodes from id ``first`` (the last chunk padded
    with zeros: MJX runs one static shape, the host only the episodes that exist; ``first=None``, a
    process with no chunk in this round, gives zeros alone): ``observations``, ``actions``, ``qpos``,
    ``qvel`` ``[batch, t, ...]``, ``goals_reached [batch]`` and ``upright [batch]`` (after the last
    step)."""
    widths = dict(observations=env.obs_size, actions=env.action_size, qpos=env.mj_model.nq, qvel=env.mj_model.nv)
    if first is None:
        out = {k: np.zeros((0, t, d), np.float32) for k, d in widths.items()}
        out.update(goals_reached=np.zeros(0, np.int32), upright=np.zeros((0, t), bool))
    else:
        keys = jax.vmap(lambda e: jax.random.fold_in(base, e))(jnp.arange(first, first + batch))
        out = jax.device_get(run(keys if mjx else keys[:min(batch, total - first)]))
    kept = {k: np.asarray(out[k], np.float32).reshape(-1, t, d) for k, d in widths.items()}
    kept.update(goals_reached=np.asarray(out['goals_reached'], np.int64), upright=np.asarray(out['upright'])[:, -1])
    return {k: v if len(v) == batch else np.concatenate([v, np.zeros((batch - len(v),) + v.shape[1:], v.dtype)])
            for k, v in kept.items()}


def _row_width(env) -> int:
    """float32 values stored per state: observation, action, qpos, qvel and the terminal flag."""
    return env.obs_size + env.action_size + env.mj_model.nq + env.mj_model.nv + 1


def estimated_bytes(cfg: 'CollectConfig') -> int:
    """Upper bound of the two files' size (float32 observations, actions, qpos and qvel, before compression)."""
    c = cfg.resolved()
    return 4 * _row_width(envs.make(c.env)) * c.steps * (c.episodes + c.val_episodes)


def check_memory(cfg: 'CollectConfig') -> None:
    """Refuse a collection whose data (host: the arrays and their copy on writing) or batch
    (device: ``batch`` environments and their trajectories) cannot fit, naming the option."""
    from aqm_mjx import memory  # pylint: disable=import-outside-toplevel

    c = cfg.resolved()
    memory.check(2 * estimated_bytes(c), f'{c.episodes + c.val_episodes:,} episodes x {c.steps:,} states',
                 '--episodes (or --steps)', (memory.host_available(), 'host'))
    env = envs.make(c.env)
    memory.check(c.batch * (memory.env_state_bytes(env) * memory.FACTOR + 4 * _row_width(env) * c.steps),
                 f'a batch of {c.batch:,} environments', '--batch')


def check_output(path: str, overwrite: bool = False, cfg: Optional['CollectConfig'] = None) -> str:
    """Check an output path before any work: an ``.npz`` whose file and ``-val`` twin do not exist
    (unless ``overwrite``), in a folder that can be written, with room for a collection of ``cfg``
    when it is given. Returns the ``-val`` path."""
    if not path.endswith('.npz'):
        raise ValueError(f'output file must end in .npz (OGBench layout); got {path!r}')
    vpath = ds_io.val_path(path)
    if not overwrite:
        for p in (path, vpath):
            if os.path.exists(p):
                raise FileExistsError(f'{p} exists; pass overwrite=True (--overwrite) to replace it')
    if os.path.isdir(path):
        raise files.OutputError(f'{path} is a folder; give a file name ending in .npz')
    files.check_writable(os.path.dirname(os.path.abspath(path)), 0 if cfg is None else estimated_bytes(cfg),
                         'the collected dataset')
    return vpath


def write(result: CollectResult, path: str, overwrite: bool = False) -> tuple[str, str]:
    """Write ``path`` and its ``-val`` twin (atomically; existing files are kept unless ``overwrite``)."""
    vpath = check_output(path, overwrite)
    ds_io.write_ogbench(path, result.train)
    if result.config.val_episodes:
        ds_io.write_ogbench(vpath, result.val)
    return path, vpath


def plot(result: CollectResult, path: str, n: int = 12) -> None:
    """Trajectories of the first ``n`` training episodes over the maze, as a PNG."""
    from aqm_mjx.envs import render  # pylint: disable=import-outside-toplevel

    t = result.config.steps
    xy = result.train['qpos'][:, :2]
    m = min(n, result.config.episodes)
    trajs = [xy[e * t:(e + 1) * t] for e in range(m)]
    c = result.config
    where = '' if c.layout == shifts.BASE else f' ({c.layout})'
    render.render_maze(c.grid(), path, trajectories=trajs, start_xy=np.stack([tr[0] for tr in trajs]),
                       title=f'{c.env}{where} {c.style}: {m} of {c.episodes} episodes x {t} states')


def _progress(total, desc, enabled):
    if not enabled:
        return None
    from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel

    return tqdm(total=total, desc=desc, unit='ep', bar_format=BAR_FORMAT)
