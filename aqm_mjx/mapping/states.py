"""HILP's map: dataset states drawn with replacement, with their representation (its test-time
planning, :mod:`aqm_mjx.agent.hilp_rule`, looks for midpoints among them)."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx.mapping.keypoints import in_batches


def encode_all(encode: Callable, aux, observations: jax.Array, chunk: int = 4096) -> jax.Array:
    """``encode(aux, obs [D]) -> [L]`` of every row of ``observations [N, D]``: ``[N, L]``, ``chunk``
    rows at a time (:func:`~aqm_mjx.mapping.keypoints.in_batches`: bounded memory)."""
    return in_batches(lambda o: encode(aux, o), observations, chunk)


@struct.dataclass
class PlanningStates:
    """``z [N, L]`` the states' representation, ``obs [N, D]`` the states."""

    z: jax.Array
    obs: jax.Array


def planning_states(encode: Callable, aux, observations: jax.Array, key: jax.Array, states: int) -> PlanningStates:
    """``states`` rows of ``observations [M, D]`` drawn uniformly with replacement (HILP's
    ``dataset.sample``) and encoded (jittable; ``encode(aux, obs [D]) -> [L]``)."""
    obs = observations[jax.random.randint(key, (states,), 0, observations.shape[0])]
    return PlanningStates(z=encode_all(encode, aux, obs), obs=obs)
