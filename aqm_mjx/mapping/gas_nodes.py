"""GAS's graph (Graph-Assisted Stitching): temporal-efficiency (TE) filtering of dataset states,
then TD-aware clustering of the states kept, both in the temporal distance representation (TDR)
``f``, where ``||f(s) - f(s')||`` estimates the steps between s and s'.

- TE filtering: a state ``s_i`` whose trajectory runs on for at least ``H`` (``way_steps``) more
  states is kept when the trajectory's direction over those ``H`` steps, ``f_{i+H} - f_i``, points
  where the trajectory first gets ``H`` away, ``f_j - f_i`` with ``j`` the first later state of the
  trajectory at ``||f_j - f_i|| >= H`` (its last state when none is): cosine >= ``threshold``.
  States in a trajectory's last ``H`` are kept. A state that loops or dithers points elsewhere.
- TD-aware clustering: the kept states in dataset order, each joining the nearest leader when it is
  within ``H / 2`` and founding a new one otherwise; a node is the mean of its members.
- Edges (:func:`gas_edges`): nodes within ``H`` joined both ways, weighted by their distance; the
  components then joined by their closest pairs. Shortest paths on the weights are the planner's
  (:mod:`aqm_mjx.agent.plan`).
- Waystep subgoals (:func:`waystep_indices`): per state, the first later state of its trajectory
  ``H`` away, the goal GAS's low-level policy is trained towards.

The functions are pure and jittable with static shapes: ``max_len`` (the longest trajectory) bounds
the search for ``j``, ``max_nodes`` the leaders (``overflow`` says when a state that needed a new
leader joined the nearest one instead).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from aqm_mjx.mapping.graph import Graph, components
from aqm_mjx.mapping.keypoints import in_batches
from aqm_mjx.mapping.states import encode_all


def _cosine(u: jax.Array, v: jax.Array) -> jax.Array:
    """Cosine of ``u, v [..., D]`` with GAS's 1e-10 guard on each norm."""
    u = u / (jnp.linalg.norm(u, axis=-1, keepdims=True) + 1e-10)
    v = v / (jnp.linalg.norm(v, axis=-1, keepdims=True) + 1e-10)
    return jnp.sum(u * v, axis=-1)


def _first_far(f: jax.Array, traj_end: jax.Array, i: jax.Array, way_steps, offsets: jax.Array) -> jax.Array:
    """The first state ``j = i + offsets[k]`` of ``i``'s trajectory with ``||f_j - f_i|| >= way_steps``,
    else the trajectory's last state."""
    end = traj_end[i]
    far = (jnp.linalg.norm(f[jnp.minimum(i + offsets, end)] - f[i], axis=-1) >= way_steps) & (i + offsets <= end)
    return jnp.where(jnp.any(far), i + offsets[jnp.argmax(far)], end).astype(jnp.int32)


def _per_state(fn, n: int, chunk: int) -> jax.Array:
    """``fn(i)`` for every state index, ``chunk`` at a time (:func:`~aqm_mjx.mapping.keypoints.in_batches`)."""
    return in_batches(fn, jnp.arange(n, dtype=jnp.int32), chunk)


def efficient_states(f: jax.Array, traj_end: jax.Array, way_steps: int, threshold: float, max_len: int,
                     chunk: int = 1024) -> jax.Array:
    """TE filtering: bool ``[N]``, the states kept.

    Args:
        f: ``[N, D]`` TDR embeddings of the dataset's states, trajectories stored one after another.
        traj_end: int32 ``[N]`` index of the last state of each state's trajectory
            (:class:`aqm_mjx.data.dataset.Dataset`'s ``traj_end``).
        way_steps: ``H``; threshold: the cosine below which a state is dropped.
        max_len: static, at least the longest trajectory's length (the forward search's window).
    """
    traj_end = jnp.asarray(traj_end, jnp.int32)
    offsets = jnp.arange(1, max_len, dtype=jnp.int32)  # j = i + 1 .. i + max_len - 1

    def one(i):
        end = traj_end[i]
        first = _first_far(f, traj_end, i, way_steps, offsets)
        cos = _cosine(f[jnp.minimum(i + way_steps, end)] - f[i], f[first] - f[i])
        return (i + way_steps > end) | (cos >= threshold)

    return _per_state(one, f.shape[0], chunk)


def waystep_indices(f: jax.Array, traj_end: jax.Array, way_steps: float, max_len: int, chunk: int = 1024) -> jax.Array:
    """GAS's subgoal for each state: int32 ``[N]``, the first state ``j >= i`` of its trajectory at
    ``||f_j - f_i|| >= way_steps``, else the trajectory's last. Its policy's goal for state ``i`` is
    ``min(i + Geometric(1 - discount), waystep[i])``. Shapes as :func:`efficient_states`."""
    traj_end = jnp.asarray(traj_end, jnp.int32)
    offsets = jnp.arange(0, max_len, dtype=jnp.int32)
    return _per_state(lambda i: _first_far(f, traj_end, i, way_steps, offsets), f.shape[0], chunk)


@struct.dataclass
class Nodes:
    """GAS's nodes.

    Attributes:
        centers: float32 ``[M, D]`` each node's mean TDR embedding (zeros where not valid).
        mask: bool ``[M]`` validity; count: int32 nodes.
        assign: int32 ``[N]`` the node each state joined (-1: filtered out).
        overflow: bool, a state that needed a new node joined the nearest one (``max_nodes`` reached).
    """

    centers: jax.Array
    mask: jax.Array
    count: jax.Array
    assign: jax.Array
    overflow: jax.Array


def td_aware_clustering(f: jax.Array, keep: jax.Array, way_steps: int, max_nodes: int) -> Nodes:
    """TD-aware clustering of the states ``keep [N]`` marks (in dataset order) at radius ``H / 2``.

    Args:
        f: ``[N, D]`` TDR embeddings; keep: bool ``[N]`` (:func:`efficient_states`).
        way_steps: ``H``; max_nodes: static bound on the nodes.
    """
    n, dim = f.shape
    radius = way_steps / 2

    def body(i, c):
        leaders, count, assign, overflow = c
        d = jnp.where(jnp.arange(max_nodes) < count, jnp.linalg.norm(f[i] - leaders, axis=-1), jnp.inf)
        near = jnp.argmin(d).astype(jnp.int32)
        new = keep[i] & (d[near] > radius)
        room = count < max_nodes
        founds = new & room
        leaders = jnp.where(founds, leaders.at[jnp.minimum(count, max_nodes - 1)].set(f[i]), leaders)
        node = jnp.where(founds, count, near)
        assign = assign.at[i].set(jnp.where(keep[i], node, -1))
        return leaders, count + founds.astype(jnp.int32), assign, overflow | (new & ~room)

    init = (jnp.zeros((max_nodes, dim), f.dtype), jnp.int32(0), jnp.full((n,), -1, jnp.int32), jnp.bool_(False))
    _, count, assign, overflow = jax.lax.fori_loop(0, n, body, init)
    members = jax.ops.segment_sum(jnp.ones((n,), f.dtype), jnp.where(assign >= 0, assign, max_nodes),
                                  num_segments=max_nodes + 1)[:max_nodes]
    sums = jax.ops.segment_sum(f, jnp.where(assign >= 0, assign, max_nodes), num_segments=max_nodes + 1)[:max_nodes]
    mask = jnp.arange(max_nodes) < count
    centers = jnp.where(mask[:, None], sums / jnp.maximum(members, 1.0)[:, None], 0.0)
    return Nodes(centers=centers, mask=mask, count=count, assign=assign, overflow=overflow)


def gas_edges(centers: jax.Array, mask: jax.Array, way_steps: float) -> jax.Array:
    """GAS's graph on its nodes: weights ``[M, M]`` (``inf``: no edge, 0 on the valid diagonal).

    Nodes within ``way_steps`` of each other (Euclidean distance of their centres) are joined both ways,
    weighted by that distance. Then, while the graph falls apart, the component of the first node
    is joined to the nearest node outside it by one edge each way (the closest pair), so that every
    node reaches every other, as GAS connects its components.
    """
    m = centers.shape[0]
    d = jnp.linalg.norm(centers[:, None, :] - centers[None, :, :], axis=-1)
    pair = mask[:, None] & mask[None, :]
    off = ~jnp.eye(m, dtype=bool)
    adj = pair & off & (d <= way_steps)
    first = jnp.argmax(mask)

    def labelled(adj):
        return (adj,) + components(jnp.where(adj, 0.0, jnp.inf), mask)  # (adj, labels, number of components)

    def join(c):
        adj, labels, _ = c
        main = labels == labels[first]
        gap = jnp.where(main[:, None] & ~main[None, :] & pair, d, jnp.inf)
        i, j = jnp.unravel_index(jnp.argmin(gap), gap.shape)
        return labelled(adj.at[i, j].set(True).at[j, i].set(True))

    adj = jax.lax.while_loop(lambda c: c[2] > 1, join, labelled(adj))[0]
    return jnp.where(adj, d, jnp.where(pair & ~off, 0.0, jnp.inf)).astype(jnp.float32)


def representatives(f: jax.Array, nodes: Nodes) -> jax.Array:
    """int32 ``[M]``: per node, its member state nearest its centre (the lowest index on ties; 0 for
    an empty slot), the observation a picture draws for it."""
    m = nodes.centers.shape[0]
    member = nodes.assign >= 0
    seg = jnp.where(member, nodes.assign, m)
    d = jnp.where(member, jnp.linalg.norm(f - nodes.centers[jnp.maximum(nodes.assign, 0)], axis=-1), jnp.inf)
    best = jax.ops.segment_min(d, seg, num_segments=m + 1)
    idx = jnp.arange(f.shape[0], dtype=jnp.int32)
    first = jax.ops.segment_min(jnp.where(member & (d <= best[seg]), idx, f.shape[0]), seg, num_segments=m + 1)[:m]
    return jnp.where(nodes.mask, jnp.minimum(first, f.shape[0] - 1), 0).astype(jnp.int32)


def gas_graph(f: jax.Array, observations: jax.Array, traj_end: jax.Array, way_steps: float, threshold: float,
              max_nodes: int, max_len: int) -> tuple[Graph, Nodes]:
    """GAS's whole map from TDR embeddings: TE filtering, TD-aware clustering, edges (pure, jittable).

    Args:
        f: ``[N, L]`` TDR embeddings of ``observations [N, D]``; traj_end: int32 ``[N]``.
        way_steps: ``H``; threshold: TE filtering's cosine; max_nodes, max_len: static bounds.
    Returns:
        (:class:`~aqm_mjx.mapping.graph.Graph` with ``[max_nodes, ...]`` arrays: ``z`` the node
        centres, ``obs`` each node's :func:`representatives` state, ``w`` :func:`gas_edges`, ``tau``
        ``H``; the :class:`Nodes`).
    """
    keep = efficient_states(f, traj_end, way_steps, threshold, max_len)
    nodes = td_aware_clustering(f, keep, way_steps, max_nodes)
    w = gas_edges(nodes.centers, nodes.mask, way_steps)
    obs = jnp.where(nodes.mask[:, None], observations[representatives(f, nodes)], 0.0)
    return Graph(z=nodes.centers, obs=obs, mask=nodes.mask, w=w, tau=jnp.float32(way_steps)), nodes


def gas_map(encode, aux, observations: jax.Array, traj_end: jax.Array, max_len: int, way_steps: int,
            te_threshold: float, max_nodes: int) -> tuple[Graph, jax.Array, jax.Array]:
    """:func:`gas_graph` of every state, encoded by ``encode(aux, obs [D]) -> [L]`` (GAS's TDR):
    ``(Graph [max_nodes], count, overflow)`` (jittable; ``max_len`` static)."""
    f = encode_all(encode, aux, observations)
    graph, nodes = gas_graph(f, observations, traj_end, way_steps, te_threshold, max_nodes, max_len)
    return graph, nodes.count, nodes.overflow
