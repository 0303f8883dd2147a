"""Keypoint selection (paper section 4.3, Algorithm 2): Iterative Wavefront Expansion and baselines.

Every selector works on *encoded* candidates: encode the dataset once with the quasimetric's
encoder, then pass the latents ``[N, D]`` and a pairwise latent distance ``dist(x [D], y [D]) ->
scalar``. ``d_sym(x, y) = max(d(x, y), d(y, x))``. Shapes are static: at most ``max_keypoints``
are returned with a validity mask, and ``Keypoints.overflow`` says when candidates were left
uncovered because that maximum was reached (``Keypoints.uncovered``: how many).

The distance from all N candidates to one new keypoint is the only O(N) work per iteration; it is
computed in chunks of ``chunk`` candidates (``lax.map``), so N can be millions.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

Dist = Callable[[jax.Array, jax.Array], jax.Array]


@struct.dataclass
class Keypoints:
    """Selected keypoints.

    Attributes:
        index: int32 ``[K]`` candidate index of each keypoint (-1 where not valid).
        mask: bool ``[K]`` validity.
        count: int32 number of valid keypoints.
        parent: int32 ``[K]`` the keypoint each one attached to when it was added (-1 for the first
            and for selectors without a wavefront), for the optional parent edges.
        attach: float32 ``[K]`` d_sym to that parent (the paper's rho).
        overflow: bool, True when candidates remained uncovered at ``max_keypoints``.
        left: int32 ``[K]``, how many valid candidates were still neither a keypoint nor within delta of
            one once keypoint ``i`` was added (the coverage curve; 0 past ``count`` and for selectors
            without a radius): one run with many slots says what every smaller slot count would have left.
    """

    index: jax.Array
    mask: jax.Array
    count: jax.Array
    parent: jax.Array
    attach: jax.Array
    overflow: jax.Array
    left: jax.Array

    @property
    def uncovered(self) -> jax.Array:
        """int32: the candidates left uncovered when the selector stopped (``left[count - 1]``; 0 without
        overflow): how far ``max_keypoints`` fell short."""
        return self.left[self.count - 1]


def sym(dist: Dist) -> Dist:
    """``d_sym(x, y) = max(d(x, y), d(y, x))``."""
    return lambda x, y: jnp.maximum(dist(x, y), dist(y, x))


def in_batches(fn: Callable, xs: jax.Array, size: int) -> jax.Array:
    """``fn`` over the leading axis of ``xs``, ``size`` rows at a time (``lax.map`` with ``batch_size``,
    clamped to ``[1, len(xs)]``): memory of one batch's evaluations, not all of them. The mapping's
    chunked loops (keypoints, the graph's pairs, encoding, GAS's per-state searches) all run on it."""
    return jax.lax.map(fn, xs, batch_size=max(1, min(size, xs.shape[0])))


def _to_one(dist_sym: Dist, latents: jax.Array, valid: jax.Array, z: jax.Array, chunk: int) -> jax.Array:
    """d_sym from every candidate to ``z``: ``[N]`` (inf where not valid), ``chunk`` at a time."""
    d = in_batches(lambda x: dist_sym(x, z), latents, chunk)
    return jnp.where(valid, d, jnp.inf)


def _greedy(dist: Dist, latents, key, delta, max_keypoints, valid, chunk, pick_farthest):
    n = latents.shape[0]
    dist_sym = sym(dist)
    valid = jnp.ones((n,), bool) if valid is None else valid
    # The first keypoint is a uniformly sampled valid candidate.
    # Gumbel-argmax, not random.choice: choice's cumsum over a constant mask would be constant-folded
    # by XLA at compile time (seconds at 10^6 candidates).
    first = jnp.argmax(jnp.where(valid, jax.random.gumbel(key, (n,)), -jnp.inf))
    d0 = _to_one(dist_sym, latents, valid, latents[first], chunk)
    k = max_keypoints
    init = dict(
        index=jnp.full((k,), -1, jnp.int32).at[0].set(first),
        parent=jnp.full((k,), -1, jnp.int32),
        attach=jnp.zeros((k,), jnp.float32),
        near=jnp.zeros((n,), jnp.int32),  # which keypoint is nearest to each candidate
        mind=d0,  # min over keypoints of d_sym(s, z)
        alive=(valid & (d0 >= delta)).at[first].set(False),  # candidates not yet covered
        count=jnp.ones((), jnp.int32),
    )
    init['left'] = jnp.zeros((k,), jnp.int32).at[0].set(init['alive'].sum())

    def cond(c):
        return c['alive'].any() & (c['count'] < k)

    def body(c):
        # A candidate unreachable from every keypoint (another region) has mind = inf; it must still
        # rank before the removed ones, so those get +inf and the unreachable a large finite score.
        m = jnp.where(jnp.isfinite(c['mind']), c['mind'], 3.0e38)
        score = jnp.where(c['alive'], -m if pick_farthest else m, jnp.inf)
        new = jnp.argmin(score).astype(jnp.int32)
        d = _to_one(dist_sym, latents, valid, latents[new], chunk)
        i = c['count']
        closer = d < c['mind']
        alive = (c['alive'] & (d >= delta)).at[new].set(False)
        return dict(
            index=c['index'].at[i].set(new),
            parent=c['parent'].at[i].set(c['near'][new]),
            attach=c['attach'].at[i].set(c['mind'][new]),
            near=jnp.where(closer, i, c['near']),
            mind=jnp.minimum(c['mind'], d),
            # The new keypoint always leaves the candidates, even if a learned d(z, z) is not exactly 0.
            alive=alive,
            left=c['left'].at[i].set(alive.sum()),
            count=i + 1,
        )

    c = jax.lax.while_loop(cond, body, init)
    mask = jnp.arange(k) < c['count']
    return Keypoints(index=c['index'], mask=mask, count=c['count'], parent=jnp.where(mask, c['parent'], -1),
                     attach=jnp.where(mask, c['attach'], 0.0), overflow=c['alive'].any(), left=c['left'])


def iwe(dist: Dist, latents: jax.Array, key: jax.Array, delta: float, max_keypoints: int,
        valid: jax.Array | None = None, chunk: int = 65536) -> Keypoints:
    """Iterative Wavefront Expansion (Algorithm 2).

    Start from a sampled candidate; repeatedly add the remaining candidate *closest* to the current
    set under d_sym, then drop every candidate within ``delta`` of it (d_sym < delta); stop when
    none remain (or at ``max_keypoints``: ``overflow`` is then True).

    Args:
        dist: pairwise latent quasimetric ``d(x [D], y [D]) -> scalar``.
        latents: ``[N, D]`` encoded candidates (any trailing shape).
        key: PRNG key for the first keypoint.
        delta: repel radius.
        max_keypoints: static maximum K.
        valid: optional bool ``[N]`` mask of real candidates (padding is False).
        chunk: candidates per distance chunk.
    Returns:
        :class:`Keypoints` with ``[K]`` arrays; keypoints are pairwise delta-separated under d_sym
        and (without overflow) every valid candidate is within delta of one.
    """
    return _greedy(dist, latents, key, delta, max_keypoints, valid, chunk, pick_farthest=False)


def farthest_point(dist: Dist, latents: jax.Array, key: jax.Array, delta: float, max_keypoints: int,
                   valid: jax.Array | None = None, chunk: int = 65536) -> Keypoints:
    """Farthest point sampling with the same stopping radius: add the candidate *farthest* from the
    set until every candidate is within ``delta`` (the paper's FPS baseline, Table 3)."""
    return _greedy(dist, latents, key, delta, max_keypoints, valid, chunk, pick_farthest=True)


def uniform_random(latents: jax.Array, key: jax.Array, budget: int, valid: jax.Array | None = None) -> Keypoints:
    """``budget`` candidates uniformly at random without replacement (the paper's RND baseline)."""
    n = latents.shape[0]
    valid = jnp.ones((n,), bool) if valid is None else valid
    # Gumbel top-k over valid candidates = sampling without replacement.
    g = jnp.where(valid, jax.random.gumbel(key, (n,)), -jnp.inf)
    _, idx = jax.lax.top_k(g, budget)
    mask = jnp.isfinite(g[idx])
    k = budget
    return Keypoints(index=jnp.where(mask, idx, -1).astype(jnp.int32), mask=mask, count=mask.sum().astype(jnp.int32),
                     parent=jnp.full((k,), -1, jnp.int32), attach=jnp.zeros((k,), jnp.float32),
                     overflow=jnp.zeros((), bool), left=jnp.zeros((k,), jnp.int32))


def iwe_best_of_batches(dist: Dist, latents: jax.Array, key: jax.Array, delta: float, max_keypoints: int,
                        n_batches: int = 8, batch_size: int = 1024) -> Keypoints:
    """The paper's variant (Appendix 11.7): IWE on ``n_batches`` random subsets of ``batch_size``
    candidates, keeping the one with the most keypoints. Indices refer to ``latents``."""
    n = latents.shape[0]
    k_sub, k_iwe = jax.random.split(key)
    subsets = jax.vmap(lambda k: jax.random.choice(k, n, (batch_size,), replace=batch_size > n))(
        jax.random.split(k_sub, n_batches))
    res = jax.vmap(lambda idx, k: iwe(dist, latents[idx], k, delta, max_keypoints))(subsets, jax.random.split(k_iwe, n_batches))
    best = jnp.argmax(res.count)
    r = jax.tree.map(lambda x: x[best], res)
    return r.replace(index=jnp.where(r.mask, subsets[best][jnp.maximum(r.index, 0)], -1))
