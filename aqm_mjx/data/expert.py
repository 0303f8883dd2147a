"""Scripted experts for data collection: a directional ant trot and a BFS waypoint oracle.

The ant controller follows ``shared/reference/scripted-gait.md``: a trot whose hip sweep and ankle
lift are steered by the commanded direction in the torso frame, tracked with a PD law. It is a pure
function of (qpos, qvel, command, control step, phase), written in ``jax.numpy`` so that it jits and
vmaps inside MJX rollouts. The waypoint oracle is a table of BFS next cells for every (cell, goal
cell) pair, computed once, so that steering towards the next cell is a lookup.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from aqm_mjx.envs import mazes


@dataclasses.dataclass(frozen=True)
class GaitParams:
    """The trot's 9 numbers (found by a cross-entropy search in plain MuJoCo; see the reference)."""

    period: float = 7.75  # T, control steps per gait cycle (6 walks backwards: timing-sensitive)
    a_hip: float = 0.62  # hip sweep amplitude (rad per unit command)
    a_rad: float = 0.2  # radial ankle modulation
    d0: float = 0.8  # mean ankle "down" angle (rad)
    lift: float = 0.42  # ankle lift L during the swing
    delta: float = -1.0  # lift phase lead (rad); near -1 matters most
    kp: float = 2.5  # PD gains on joint targets
    kd: float = 0.13
    k_yaw: float = 0.035  # yaw-rate damping


_THETA = jnp.deg2rad(jnp.array([45.0, 135.0, 225.0, 315.0]))
_TANGENT = jnp.stack([-jnp.sin(_THETA), jnp.cos(_THETA)], -1)  # [4, 2]
_RADIAL = jnp.stack([jnp.cos(_THETA), jnp.sin(_THETA)], -1)
_PHASE = jnp.array([0.0, jnp.pi, 0.0, jnp.pi])
_ANKLE_SIGN = jnp.array([1.0, -1.0, -1.0, 1.0])
_ACTUATOR_ORDER = jnp.array([6, 7, 0, 1, 2, 3, 4, 5])  # joint vector (qpos order) -> actuators


def yaw(quat: jax.Array) -> jax.Array:
    """Torso yaw from (w, x, y, z) quaternions ``[..., 4]`` -> ``[...]``."""
    w, x, y, z = quat[..., 0], quat[..., 1], quat[..., 2], quat[..., 3]
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def gait_action(qpos: jax.Array, qvel: jax.Array, command: jax.Array, step: jax.Array, phase: jax.Array = 0.0,
                p: GaitParams = GaitParams()) -> jax.Array:
    """Ant action ``[8]`` walking along the world-frame direction ``command [2]``.

    Args:
        qpos: ``[15]``; qvel: ``[14]``; step: control step count (the gait clock);
        phase: extra phase (rad), e.g. random per episode.
    """
    psi = yaw(qpos[3:7])
    c, s = jnp.cos(psi), jnp.sin(psi)
    u = command / jnp.maximum(jnp.linalg.norm(command), 1e-6)
    u_b = jnp.array([c * u[0] + s * u[1], -s * u[0] + c * u[1]])  # R(-psi) u
    a = _TANGENT @ u_b - p.k_yaw * qvel[5]
    b = _RADIAL @ u_b
    phi = 2 * jnp.pi * step / p.period + _PHASE + phase
    hip = jnp.clip(-p.a_hip * a * jnp.cos(phi), -0.52, 0.52)
    down = jnp.clip(p.d0 + p.a_rad * b * jnp.cos(phi) - p.lift * jnp.maximum(0.0, jnp.sin(phi + p.delta)), 0.53, 1.22)
    target = jnp.stack([hip, _ANKLE_SIGN * down], -1).reshape(-1)  # hip_1, ankle_1, ..., hip_4, ankle_4
    u_joint = p.kp * (target - qpos[7:15]) - p.kd * qvel[6:14]
    return jnp.clip(u_joint[_ACTUATOR_ORDER], -1.0, 1.0)


def bfs_next_cell(grid) -> np.ndarray:
    """Next cell on a BFS shortest path for every (cell, goal cell) of a maze.

    Returns:
        int32 ``[H*W, H*W]``: flat index of the neighbour to move to from cell ``c`` towards goal
        ``g``; ``c`` itself when ``c == g``, when either is a wall or when ``g`` is unreachable.
        Ties go to OGBench's neighbour order (up, left, down, right in (i, j)).
    """
    g = np.asarray(grid)
    h, w = g.shape
    n = h * w
    table = np.tile(np.arange(n, dtype=np.int32)[:, None], (1, n))
    steps = mazes.bfs_steps(g)  # symmetric: the distance to the goal is the distance from it
    for goal in np.flatnonzero(g.reshape(-1) == 0):
        dist = steps[goal]
        for cell in np.flatnonzero(dist > 0):
            i, j = divmod(int(cell), w)
            best = cell
            for di, dj in mazes.NEIGHBOURS:
                ni, nj = i + di, j + dj
                if 0 <= ni < h and 0 <= nj < w and 0 <= dist[ni * w + nj] < dist[best]:
                    best = ni * w + nj
            table[cell, goal] = best
    return table


def waypoint_command(xy: jax.Array, goal_xy: jax.Array, next_cell: jax.Array, grid_shape) -> jax.Array:
    """Direction ``[2]`` to the centre of the next BFS cell, or to the goal inside the goal cell."""
    h, w = grid_shape

    def cell(p):
        ij = mazes.xy_to_ij(p)
        return jnp.clip(ij[0], 0, h - 1) * w + jnp.clip(ij[1], 0, w - 1)

    c, g = cell(xy), cell(goal_xy)
    nxt = next_cell[c, g]
    centre = jnp.array([nxt % w, nxt // w], jnp.float32) * mazes.MAZE_UNIT - mazes.MAZE_OFFSET
    return jnp.where(c == g, goal_xy - xy, centre - xy)
