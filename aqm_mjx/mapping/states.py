"""HILP's map: dataset states drawn with replacement, with their representation (its test-time
planning, :mod:`aqm_mjx.agent.hilp_rule`, looks for midpoints among them)."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct



def map_rows(fn, x: jax.Array, chunk: int = 4096) -> jax.Array:
    """``fn`` over the rows of ``x [N, D]``, ``chunk`` rows per call (``lax.map``, bounded memory):
    ``fn([chunk, D]) -> [chunk, L]`` gives ``[N, L]`` (the last chunk zero-padded)."""
    n, d = x.shape
    pad = (-n) % chunk
    chunks = jnp.concatenate([x, jnp.zeros((pad, d), x.dtype)]).reshape(-1, chunk, d)
    return jax.lax.map(fn, chunks).reshape(n + pad, -1)[:n]


def encode_all(encode: Callable, aux, observations: jax.Array) -> jax.Array:
    """``encode(aux, obs [D]) -> [L]`` of every row of ``observations [N, D]``: ``[N, L]`` (:func:`map_rows`)."""
    return map_rows(jax.vmap(lambda o: encode(aux, o)), observations)


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
