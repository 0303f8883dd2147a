"""OGBench's own locomaze environments (plain MuJoCo, on the host), B of them in lockstep.

The second backend of the evaluation (``aqm-mjx evaluate --backend ogbench``): the physics, the
task ids, the goal observation and the success rule are OGBench's own (``ogbench.locomaze.maze``),
not our MJX copy's. Only the physics runs here; the agent stays one jitted, batched program
(:func:`aqm_mjx.agent.rollout.make_host_rollout`).

    envs = OGBenchEnvs('antmaze-medium')
    obs, goal, goal_xy = envs.reset(seeds, task_ids, grids)      # [B] ints, [B] ids, [B, H, W]
    obs, xy, success, done = envs.step(actions)                  # actions [B, A] in [-1, 1]

Layouts (the shift suite's closed corridors and opened walls) are applied to OGBench's model by
editing its maze map before the model is built; environments are kept per layout and reused.
Each episode is seeded from its own integer (gymnasium's ``reset(seed=)`` for the reset noise, the
action space's seed for the goal's 5 warm-up actions, numpy's global generator, restored afterwards,
for OGBench's start and goal noise), so an episode depends on its seed alone.

``workers > 0`` spreads the environments over that many processes (``multiprocessing``, spawn),
each stepping its slice; the main process keeps the agent.
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import weakref
from typing import Optional

import numpy as np

from aqm_mjx.envs import mazes


@functools.lru_cache(maxsize=None)
def _ogbench_class(agent: str, maze: str):
    """OGBench's maze environment class for ``agent`` ('ant' or 'point') and ``maze``."""
    try:
        from ogbench.locomaze.maze import make_maze_env  # pylint: disable=import-outside-toplevel
    except ImportError as e:  # pragma: no cover - ogbench is a dependency
        raise ImportError('the ogbench backend needs the ogbench package: pip install ogbench') from e
    env = make_maze_env(agent, 'maze', maze_type=maze)
    cls = type(env)
    _drop_xml(env)
    env.close()
    return cls


def _drop_xml(env) -> None:
    """OGBench writes each maze model to a temporary XML file (``tempfile.mkstemp``) and keeps it;
    remove it once the model is built, so that thousands of environments leave no files behind."""
    path = getattr(env, 'fullpath', None)
    if path and os.path.basename(path).startswith('tmp') and path.endswith('.xml') and os.path.exists(path):
        os.remove(path)


def make_env(agent: str, maze: str, grid: Optional[np.ndarray] = None):
    """One OGBench environment (unwrapped: no time limit) whose walls are ``grid`` (default: the
    maze's own layout). The grid replaces OGBench's maze map before its model is built."""
    base = _ogbench_class(agent, maze)
    if grid is None:
        env = base(maze_type=maze)
    else:
        grid = mazes.validate_grid(grid, maze)
        layout = np.asarray(grid, dtype=np.int64)

        def update_tree(self, tree):
            self.maze_map = layout.copy()
            base.update_tree(self, tree)

        env = type(base.__name__, (base,), {'update_tree': update_tree})(maze_type=maze)
    _drop_xml(env)
    return env


def _reset_one(env, seed: int, task_id: int, cells=None):
    """One episode: OGBench's task ``task_id``, or (task 0) the start and goal cells ``cells`` (i, j, i, j)
    through OGBench's own ``task_info`` option."""
    if task_id == 0:
        c = [int(x) for x in cells]
        options = dict(task_info=dict(init_ij=(c[0], c[1]), goal_ij=(c[2], c[3])))
    else:
        options = dict(task_id=int(task_id))
    state = np.random.get_state()  # OGBench's start and goal noise draws from numpy's global generator
    try:
        np.random.seed(seed)
        env.action_space.seed(seed)
        ob, info = env.reset(seed=seed, options=options)
    finally:
        np.random.set_state(state)
    return ob, info['goal'], np.asarray(env.cur_goal_xy, np.float64)


class _Slice:
    """Environments of one process: a pool per layout, the episodes' environments in batch order."""

    def __init__(self, agent: str, maze: str):
        self.agent, self.maze = agent, maze
        self.pool: dict[bytes, list] = {}
        self.active: list = []

    def reset(self, seeds, task_ids, grids, cells):
        taken: dict[bytes, int] = {}
        self.active = []
        obs, goals, goal_xy = [], [], []
        for seed, task, grid, cell in zip(seeds, task_ids, grids, cells):
            key = np.asarray(grid, np.int8).tobytes()
            envs = self.pool.setdefault(key, [])
            k = taken.get(key, 0)
            taken[key] = k + 1
            if k == len(envs):
                envs.append(make_env(self.agent, self.maze, grid))
            env = envs[k]
            o, g, gxy = _reset_one(env, int(seed), int(task), cell)
            self.active.append(env)
            obs.append(o)
            goals.append(g)
            goal_xy.append(gxy)
        return np.stack(obs), np.stack(goals), np.stack(goal_xy)

    def step(self, actions, live):
        n = len(self.active)
        obs = np.empty((n,) + self.active[0].observation_space.shape) if n else np.zeros((0, 0))
        xy, success = np.empty((n, 2)), np.zeros(n, bool)
        for i, env in enumerate(self.active):
            if live[i]:
                ob, _, _, _, info = env.step(actions[i])
                success[i] = info['success'] > 0
                obs[i] = ob
            else:  # a finished episode stands still, as a done MJX environment does
                obs[i] = env.get_ob()
            xy[i] = env.get_xy()
        return obs, xy, success

    def close(self):
        for envs in self.pool.values():
            for env in envs:
                env.close()
        self.pool, self.active = {}, []


WORKER_ERROR = '__worker_error__'  # the first item of a reply that carries a worker's exception


def _worker(conn, agent, maze):
    envs = _Slice(agent, maze)
    try:
        while True:
            msg = conn.recv()
            try:
                if msg[0] == 'reset':
                    reply = envs.reset(*msg[1:])
                elif msg[0] == 'step':
                    reply = envs.step(*msg[1:])
                else:
                    break
            except Exception as e:  # pylint: disable=broad-except  (handed to the parent, named there)
                reply = (WORKER_ERROR, f'{type(e).__name__}: {" ".join(str(e).split())}')
            conn.send(reply)
    except (EOFError, OSError):
        pass
    finally:
        envs.close()


def _shutdown(conns: list, procs: list) -> None:
    for c in conns:
        try:
            c.send(('close',))
        except (BrokenPipeError, OSError):
            pass
    for p in procs:
        p.join(timeout=5)
        if p.is_alive():
            p.terminate()
    conns.clear()
    procs.clear()


class OGBenchEnvs:
    """``B`` OGBench environments of ``name`` (``'antmaze-medium'``, ...) stepped in lockstep.

    ``reset(seeds [B], task_ids [B], grids [B, H, W], cells=None) -> (obs [B, O], goal [B, O], goal_xy
    [B, 2])`` (float32) starts one episode per environment (task 0: from and to ``cells [B, 4]``, as
    :meth:`aqm_mjx.envs.locomaze.MazeEnv.reset`); ``step(actions [B, A]) -> (obs [B, O], xy [B, 2],
    success [B], done [B])`` steps those not done. An episode is done at success (OGBench terminates
    at the goal) or after ``max_episode_steps``; a done environment no longer moves.
    """

    def __init__(self, name: str, max_episode_steps: int = 1000, workers: int = 0):
        from aqm_mjx import envs  # pylint: disable=import-outside-toplevel

        self.agent, self.maze = envs.parse_name(name)
        self.name = f'{self.agent}maze-{self.maze}'
        if int(max_episode_steps) < 1:
            raise ValueError('max_episode_steps must be >= 1')
        if isinstance(workers, bool) or int(workers) < 0:
            raise ValueError(f'workers must be an integer >= 0; got {workers!r}')
        self.max_episode_steps, self.workers = int(max_episode_steps), int(workers)
        probe = make_env(self.agent, self.maze)
        self.obs_size, self.action_size = probe.observation_space.shape[0], probe.action_space.shape[0]
        probe.close()
        self._local = _Slice(self.agent, self.maze) if self.workers == 0 else None
        self._procs, self._conns = [], []
        if self.workers:
            ctx = mp.get_context('spawn')  # a fork of a process running JAX may deadlock
            for _ in range(self.workers):
                parent, child = ctx.Pipe()
                p = ctx.Process(target=_worker, args=(child, self.agent, self.maze), daemon=True)
                p.start()
                child.close()
                self._procs.append(p)
                self._conns.append(parent)
        # workers end with close(), or when this object is collected, or at exit
        self._finalizer = weakref.finalize(self, _shutdown, self._conns, self._procs)
        self._slices: list = []
        self.steps = 0
        self.live_steps = 0  # environment steps taken (episodes that were not done), over the object's life
        self.success = self.done = np.zeros(0, bool)

    def _gather(self) -> list:
        """Every worker's reply to the message just sent; a worker that died or failed ends the
        evaluation with one line naming it (the caller writes nothing: results are written at the end)."""
        parts = []
        for i, c in enumerate(self._conns):
            try:
                reply = c.recv()
            except (EOFError, OSError):
                raise self._dead(i) from None
            if isinstance(reply, tuple) and len(reply) == 2 and isinstance(reply[0], str) and reply[0] == WORKER_ERROR:
                raise RuntimeError(f"OGBench's worker process {i + 1} of {self.workers} failed: {reply[1]}")
            parts.append(reply)
        return parts

    def _dead(self, i: int) -> RuntimeError:
        p = self._procs[i]
        p.join(timeout=2)
        return RuntimeError(f"OGBench's worker process {i + 1} of {self.workers} (pid {p.pid}) ended (exit code "
                            f'{p.exitcode}) in the middle of the evaluation; nothing was written: run the same '
                            'command again')

    def _send(self, messages) -> None:
        for i, (c, m) in enumerate(zip(self._conns, messages)):
            try:
                c.send(m)
            except (BrokenPipeError, OSError):
                raise self._dead(i) from None

    def _split(self, n: int) -> list:
        bounds = np.linspace(0, n, self.workers + 1).round().astype(int)
        return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]

    def reset(self, seeds, task_ids, grids, cells=None):
        seeds, task_ids = np.asarray(seeds, np.int64), np.asarray(task_ids, np.int64)
        grids = np.asarray(grids, np.int8)
        n = len(seeds)
        cells = np.zeros((n, 4), np.int64) if cells is None else np.asarray(cells, np.int64)
        if task_ids.shape != (n,) or grids.ndim != 3 or grids.shape[0] != n or cells.shape != (n, 4):
            raise ValueError(f'reset needs seeds [B], task_ids [B], grids [B, H, W] and cells [B, 4]; got '
                             f'{seeds.shape}, {task_ids.shape}, {grids.shape}, {cells.shape}')
        valid = {t.task_id for t in mazes.tasks(self.maze)} | {0}
        bad = sorted(set(task_ids.tolist()) - valid)
        if bad:
            raise ValueError(f'task ids {bad} do not exist in maze {self.maze!r} (it has {sorted(valid)})')
        if self._local is not None:
            out = self._local.reset(seeds, task_ids, grids, cells)
        else:
            self._slices = self._split(n)
            self._send([('reset', seeds[s], task_ids[s], grids[s], cells[s]) for s in self._slices])
            parts = self._gather()
            out = tuple(np.concatenate([p[k] for p in parts]) for k in range(3))
        self.steps = 0
        self.success, self.done = np.zeros(n, bool), np.zeros(n, bool)
        return tuple(np.asarray(x, np.float32) for x in out)

    def step(self, actions):
        actions = np.asarray(actions, np.float64)
        live = ~self.done
        if self._local is not None:
            obs, xy, success = self._local.step(actions, live)
        else:
            self._send([('step', actions[s], live[s]) for s in self._slices])
            parts = self._gather()
            obs, xy, success = (np.concatenate([p[k] for p in parts]) for k in range(3))
        self.steps += 1
        self.live_steps += int(live.sum())
        self.success = np.where(live, success, self.success)
        self.done = self.done | self.success | (self.steps >= self.max_episode_steps)
        return np.asarray(obs, np.float32), np.asarray(xy, np.float32), self.success.copy(), self.done.copy()

    def close(self) -> None:
        if self._local is not None:
            self._local.close()
        self._finalizer()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
