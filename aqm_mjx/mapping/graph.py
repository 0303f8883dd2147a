"""The keypoint graph (paper section 4.3 and Appendix 11.5-11.7).

Keypoints z_i, z_j are joined when ``d_sym(z_i, z_j) < tau``, with *both* directed edges weighted
by their own time-to-reach ``d(z_i, z_j)`` and ``d(z_j, z_i)``. ``tau = 2 delta`` by default (the
paper's proxy for ``2 (delta + eps)``) unless ``tau`` is given. Optional parent edges (each
keypoint to the one it attached to during IWE) make the graph connected by construction.
Weights are a dense ``[K, K]`` matrix, ``inf`` where there is no edge, 0 on the valid diagonal.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx.mapping.keypoints import Dist, Keypoints, in_batches


@struct.dataclass
class Graph:
    """The keypoint graph an agent plans on.

    Attributes:
        z: ``[K, L]`` keypoints as inputs of the quasimetric (latents).
        obs: ``[K, D]`` keypoint observations (what the controller is given as a subgoal).
        mask: bool ``[K]`` valid keypoints.
        w: ``[K, K]`` edge weights (``inf``: no edge).
        tau: float32 ``[]`` the edge radius it was built with, also the radius within which an agent
            attaches its state and goal to it.
    """

    z: jax.Array
    obs: jax.Array
    mask: jax.Array
    w: jax.Array
    tau: jax.Array


def pairwise(dist: Dist, a: jax.Array, b: jax.Array, rows: int = 64) -> jax.Array:
    """``d(a_i, b_j)``: ``a [K, D]``, ``b [M, D]`` -> ``[K, M]``, ``rows`` rows of ``a`` at a time
    (``lax.map``): a distance that runs a network on each pair (GCIVL's value on raw states) holds
    ``rows x M`` evaluations' activations, not ``K x M`` (at K = 2,048 the whole matrix at once
    asked for 25 GB)."""
    return in_batches(lambda x: jax.vmap(lambda y: dist(x, y))(b), a, rows)


def build_graph(dist: Dist, z: jax.Array, mask: jax.Array, delta: float,
                tau: float | None = None, keypoints: Keypoints | None = None) -> jax.Array:
    """Directed weight matrix of the keypoint graph.

    Args:
        dist: pairwise latent quasimetric.
        z: ``[K, D]`` keypoint latents; mask: bool ``[K]`` which are valid.
        delta: the IWE repel radius; ``tau = 2 delta`` unless ``tau`` is given.
        keypoints: if given, its parent edges are added in both directions whatever tau says.
    Returns:
        ``[K, K]`` float32 weights (``inf`` = no edge; invalid rows and columns all ``inf``).
    """
    tau = 2.0 * delta if tau is None else tau
    d = pairwise(dist, z, z)
    dsym = jnp.maximum(d, d.T)
    both = mask[:, None] & mask[None, :]
    edge = both & (dsym < tau)
    if keypoints is not None:
        k = z.shape[0]
        p = keypoints.parent
        has = keypoints.mask & (p >= 0)
        par = jnp.zeros((k, k), bool).at[jnp.arange(k), jnp.maximum(p, 0)].set(has)
        edge = edge | (both & (par | par.T))
    w = jnp.where(edge, d, jnp.inf)
    eye = jnp.eye(z.shape[0], dtype=bool)
    return jnp.where(eye & both, 0.0, jnp.where(eye, jnp.inf, w)).astype(jnp.float32)


def components(weights: jax.Array, mask: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Connected components of the underlying undirected graph.

    Args:
        weights: ``[K, K]`` (finite = edge); mask: bool ``[K]``.
    Returns:
        (labels int32 ``[K]``, the smallest valid node index of each node's component, -1 where
        invalid; number of components among valid nodes).
    """
    k = weights.shape[0]
    adj = (jnp.isfinite(weights) | jnp.isfinite(weights.T)) & mask[:, None] & mask[None, :]
    labels0 = jnp.where(mask, jnp.arange(k), k)

    def step(c):
        labels, _ = c
        new = jnp.minimum(labels, jnp.min(jnp.where(adj, labels[None, :], k), axis=1))
        return new, jnp.any(new != labels)

    labels, _ = jax.lax.while_loop(lambda c: c[1], step, (labels0, jnp.ones((), bool)))
    labels = jnp.where(mask, labels, -1).astype(jnp.int32)
    n = jnp.sum(mask & (labels == jnp.arange(k)))
    return labels, n.astype(jnp.int32)


def edge_list(weights, mask=None):
    """Host helper for plots: ``[E, 2]`` numpy index pairs of finite off-diagonal edges."""
    import numpy as np  # pylint: disable=import-outside-toplevel

    w = np.asarray(weights)
    e = np.isfinite(w) & ~np.eye(w.shape[0], dtype=bool)
    if mask is not None:
        m = np.asarray(mask)
        e &= m[:, None] & m[None, :]
    return np.argwhere(e)


def trim(graph: Graph, size: int) -> Graph:
    """The first ``size`` keypoint slots of a graph (host side, outside jit): selectors fill slots
    in order, so trimming a padded ``[K, ...]`` graph to its count (rounded up to a multiple of 8,
    say) keeps every keypoint and makes Floyd-Warshall ``(K / size)^3`` times cheaper."""
    count = int(jnp.sum(graph.mask))
    if not count <= size <= graph.mask.shape[0] or bool(jnp.any(graph.mask[size:])):
        raise ValueError(f'cannot trim a graph with {count} keypoints (valid slots not first?) to {size} slots')
    return Graph(z=graph.z[:size], obs=graph.obs[:size], mask=graph.mask[:size], w=graph.w[:size, :size],
                 tau=graph.tau)


def pad(graph: Graph, size: int) -> Graph:
    """The inverse of :func:`trim`: ``size`` slots, the new ones masked out with infinite edges, so
    that graphs of different counts share one static K (one compiled rollout program)."""
    k = graph.mask.shape[0]
    if size < k:
        raise ValueError(f'cannot pad a graph of {k} slots to {size}')
    extra = size - k
    return Graph(z=jnp.pad(graph.z, ((0, extra), (0, 0))), obs=jnp.pad(graph.obs, ((0, extra), (0, 0))),
                 mask=jnp.pad(graph.mask, (0, extra)),
                 w=jnp.pad(graph.w, ((0, extra), (0, extra)), constant_values=jnp.inf), tau=graph.tau)
