"""A TTGS-style map (Test-Time Graph Search, arXiv 2510.07257, code ``ktolnos/TTGS``) on any
method's distance: dataset states drawn at random as nodes, every ordered pair joined, the weight
the distance itself up to ``tau`` and a soft penalty past it,

    w(i, j) = d(i, j)                          if d(i, j) <= tau
            = d(i, j) * penalty ** (d / tau)  otherwise (penalty 1000, TTGS's 'dynamic' mode)

floored at 1, no self-loops (``inf`` on the diagonal). A hard cutoff instead of the penalty is what
TTGS found to break giant stitch (78.6 -> 2.2%). The search itself, once per episode, and the
subgoal choice are :mod:`aqm_mjx.agent.ttgs_rule`'s. TTGS's published runs subsample its nodes
after a temporal-efficiency filter and clustering; its ``random_points`` ablation, the one built
here, draws them uniformly (``nodes`` 4,000 in the issue's statement of its settings; the penalty
makes a dense graph, so its cost is ``nodes^2`` distances once per map).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from aqm_mjx.mapping.graph import Graph, pairwise

PENALTY = 1000.0


def soft_weights(d: jax.Array, tau: float, penalty: float = PENALTY) -> jax.Array:
    """TTGS's edge weights of distances ``d [K, K]``: ``d`` up to ``tau``, ``d * penalty^(d / tau)``
    past it, floored at 1, the diagonal ``inf``."""
    w = jnp.where(d > tau, d * jnp.power(penalty, d / tau), d)
    w = jnp.maximum(w, 1.0)
    return jnp.where(jnp.eye(d.shape[0], dtype=bool), jnp.inf, w)


def ttgs_map(encode, dist, aux, observations: jax.Array, key: jax.Array, nodes: int, tau: float,
             penalty: float = PENALTY) -> Graph:
    """``min(nodes, N)`` of ``observations [N, D]`` drawn uniformly without replacement (``key``), as a
    dense :class:`~aqm_mjx.mapping.graph.Graph` with :func:`soft_weights` (jittable; ``nodes``
    static). ``encode(aux, obs [D]) -> z``, ``dist(aux, z, z') -> steps``; the distances are
    computed a row at a time (:func:`~aqm_mjx.mapping.graph.pairwise` with ``rows=1``), so memory
    stays ``O(nodes)`` distance evaluations."""
    n = observations.shape[0]
    k = min(int(nodes), n)
    rows = jax.random.permutation(key, n)[:k]
    obs = observations[rows]
    z = jax.vmap(lambda o: encode(aux, o))(obs)
    d = pairwise(lambda x, y: dist(aux, x, y), z, z, rows=1)
    return Graph(z=z, obs=obs, mask=jnp.ones((k,), bool), w=soft_weights(d, tau, penalty), tau=jnp.float32(tau))
