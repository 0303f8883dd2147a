"""HILP's test-time planning (Park et al., 2024, section 5.2; ``hilp_gcrl/jaxrl_m/evaluation.py``,
``goal_skill_planning``), batched: every control step, ``recursions`` times, the waypoint becomes
the mean ``phi`` of the ``knns`` dataset states that minimise ``max(||phi(x) - phi(s)||, ||phi(x) -
phi(w)||)`` (``w``: the goal, then the last waypoint), a midpoint between the state and it; the
latent policy then steers toward ``(phi(w) - phi(s)) / ||phi(w) - phi(s)||``. The dataset states
(the "map") are drawn once per evaluation (:class:`~aqm_mjx.mapping.states.PlanningStates`).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx.interface import Decide
from aqm_mjx.mapping.states import PlanningStates


@struct.dataclass
class HILPState:
    """The batch's planners: ``goal [B, L]`` phi(goal), ``node [B]`` -1 (no keypoints, for the traces)."""

    goal: jax.Array
    node: jax.Array


def waypoint(z: jax.Array, phi_s: jax.Array, phi_g: jax.Array, recursions: int, knns: int) -> jax.Array:
    """``[L]``: the waypoint after ``recursions`` midpoint steps from goal ``phi_g`` (``z [N, L]``)."""
    for _ in range(recursions):
        d = jnp.maximum(jnp.linalg.norm(z - phi_s, axis=-1), jnp.linalg.norm(z - phi_g, axis=-1))
        phi_g = jnp.mean(z[jax.lax.top_k(-d, knns)[1]], axis=0)
    return phi_g


def make_decide(encode: Callable, act: Callable, recursions: int, knns: int):
    """HILP's :class:`~aqm_mjx.interface.Decide` half of a control step (rows with ``use_graph``
    False head for the goal, as HILP without planning).

    Args:
        encode: ``(aux, obs [D]) -> phi [L]``; act: ``(aux, obs [D], phi_obs [L], target [L]) -> action
            [A]`` (:attr:`aqm_mjx.interface.Agent.skill`).
    """
    def init(aux, examples: PlanningStates, obs, goal, inputs):
        del obs
        return HILPState(goal=jax.vmap(lambda o: encode(aux, o))(goal), node=jnp.full(inputs.use_graph.shape, -1,
                                                                                          jnp.int32))

    def step(aux, examples: PlanningStates, agents: HILPState, obs, goal, done, t, inputs):
        del goal, done, t
        phi_s = jax.vmap(lambda o: encode(aux, o))(obs)
        way = jax.vmap(lambda s, g: waypoint(examples.z, s, g, recursions, knns))(phi_s, agents.goal)
        target = jnp.where(inputs.use_graph[:, None], way, agents.goal)
        actions = jax.vmap(lambda o, s, k: act(aux, o, s, k))(obs, phi_s, target)
        return jnp.clip(actions, -1.0, 1.0), agents

    return Decide(init, step)
