"""Scripted expert pieces that need no physics: the BFS waypoint table and the gait's geometry."""

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import ogbench  # noqa: F401
import pytest

from aqm_mjx.data import expert
from aqm_mjx.envs import mazes


@pytest.mark.parametrize('maze', ['medium', 'large', 'giant', 'teleport'])
def test_bfs_table_matches_ogbench_oracle(maze):
    ref = gymnasium.make(f'antmaze-{maze}-v0').unwrapped
    grid = mazes.layout(maze)
    table = expert.bfs_next_cell(grid)
    h, w = grid.shape
    free = np.argwhere(grid == 0)
    rng = np.random.default_rng(0)
    for _ in range(150):
        s, g = free[rng.integers(len(free))], free[rng.integers(len(free))]
        sub_xy, _ = ref.get_oracle_subgoal(mazes.ij_to_xy(s), mazes.ij_to_xy(g))
        nxt = table[s[0] * w + s[1], g[0] * w + g[1]]
        np.testing.assert_allclose(mazes.ij_to_xy(divmod(int(nxt), w)), sub_xy)


def test_waypoint_command_points_to_next_cell_then_goal():
    grid = mazes.layout('medium')
    table = jnp.asarray(expert.bfs_next_cell(grid))
    xy = jnp.array([0.3, -0.2])  # cell (1, 1); goal in cell (1, 2) east of it
    goal = jnp.asarray(mazes.ij_to_xy((1, 2)), jnp.float32) + 0.5
    np.testing.assert_allclose(expert.waypoint_command(xy, goal, table, grid.shape), np.array([4.0, 0.0]) - xy, atol=1e-6)
    inside = goal - 1.0
    np.testing.assert_allclose(expert.waypoint_command(inside, goal, table, grid.shape), goal - inside, atol=1e-6)


def test_gait_is_rotation_equivariant_and_bounded():
    rng = np.random.default_rng(0)
    qpos = jnp.asarray(np.r_[0, 0, 0.6, 1, 0, 0, 0, rng.normal(0, 0.3, 8)], jnp.float32)
    qvel = jnp.asarray(rng.normal(0, 0.5, 14), jnp.float32)
    a = jax.jit(expert.gait_action)(qpos, qvel, jnp.array([1.0, 0.0]), 3)
    assert a.shape == (8,) and np.all(np.abs(np.asarray(a)) <= 1.0)
    # Turning the torso by 90 degrees and the command with it gives the same joint commands.
    half = np.pi / 4
    turned = qpos.at[3:7].set(jnp.array([np.cos(half), 0, 0, np.sin(half)]))
    b = expert.gait_action(turned, qvel, jnp.array([0.0, 1.0]), 3)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)
    np.testing.assert_allclose(float(expert.yaw(turned[3:7])), np.pi / 2, atol=1e-6)
