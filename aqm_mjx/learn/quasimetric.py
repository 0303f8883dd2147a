"""Interval Quasimetric Embeddings with the maxmean reduction (paper eq. 1-2; Wang & Isola 2022).

A state is encoded by an MLP into a latent of N components of M numbers each. For component i, the
distance from x to y is the length of the union of the intervals ``[x_ij, max(x_ij, y_ij)]`` over
j = 1..M; the quasimetric is ``alpha * max_i d_i + (1 - alpha) * mean_i d_i`` (eq. 2 as the paper
writes it; OGBench names the weights the other way round) with a trainable ``alpha = sigmoid(p)``.
Every ``d_i`` is a quasimetric (0 on the diagonal, non-negative, triangle inequality), and the mean
and the max of quasimetrics are quasimetrics.
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from aqm_mjx.learn.networks import kernel_init


def interval_union_length(x: jax.Array, y: jax.Array) -> jax.Array:
    """Length of ``union_j [x_j, max(x_j, y_j)]`` over the last axis: ``x, y [..., M]`` -> ``[...]``.

    A sweep in order of the intervals' starts without sorting: interval i adds what reaches past
    its start and past the furthest end of every interval before it (earlier start, or the same
    start and a lower index), ``relu(hi_i - max(x_i, max_{j before i} hi_j))``. That is M^2
    comparisons per component instead of a sort of 2M endpoints: on XLA's CPU the sort was 7x
    slower for OGBench's components of 8 (``benchmarks/throughput/bench_iqe.py``). An empty interval
    (``y_j <= x_j``) ends at its start, so it adds nothing and never covers a later start.
    """
    if x.shape[-1] == 1:  # one interval: its length (the paper's 512 x 1 latent takes this path)
        return jax.nn.relu(y[..., 0] - x[..., 0])
    hi = jnp.maximum(x, y)
    idx = jnp.arange(x.shape[-1])
    xi, xj = x[..., :, None], x[..., None, :]  # [..., M (i), M (j)]
    before = (xj < xi) | ((xj == xi) & (idx[None, :] < idx[:, None]))
    reach = jnp.max(jnp.where(before, hi[..., None, :], -jnp.inf), axis=-1)  # -inf: nothing before i
    return jnp.sum(jax.nn.relu(hi - jnp.maximum(x, reach)), axis=-1)


def interval_union_length_sorted(x: jax.Array, y: jax.Array) -> jax.Array:
    """The same length by sorting the 2M endpoints (the reference for tests and the benchmark).

    Coverage between consecutive endpoints is the running count of interval starts minus ends, and
    a gap counts when that coverage is positive. ``x, y [..., M]`` -> ``[...]``.
    """
    valid = (x < y).astype(x.dtype)
    ends = jnp.concatenate([x, jnp.maximum(x, y)], axis=-1)  # [..., 2M]
    inc = jnp.concatenate([valid, -valid], axis=-1)  # +1 at a start, -1 at an end (0 for empty intervals)
    order = jnp.argsort(ends, axis=-1)
    s = jnp.take_along_axis(ends, order, axis=-1)
    cover = jnp.cumsum(jnp.take_along_axis(inc, order, axis=-1), axis=-1)[..., :-1]
    return jnp.sum(jnp.where(cover > 0.5, s[..., 1:] - s[..., :-1], 0.0), axis=-1)


def iqe_components(zx: jax.Array, zy: jax.Array, n_components: int) -> jax.Array:
    """Per-component IQE distances: latents ``[..., N*M]`` -> ``[..., N]``."""
    full = jnp.broadcast_shapes(zx.shape, zy.shape)  # e.g. [N, 1, L] against [1, K, L] for all pairs
    shape = full[:-1] + (n_components, full[-1] // n_components)
    return interval_union_length(jnp.broadcast_to(zx, full).reshape(shape), jnp.broadcast_to(zy, full).reshape(shape))


def maxmean(components: jax.Array, alpha: jax.Array) -> jax.Array:
    """``alpha * max + (1 - alpha) * mean`` over the last axis (paper eq. 2)."""
    return alpha * jnp.max(components, axis=-1) + (1.0 - alpha) * jnp.mean(components, axis=-1)


def iqe_distance(zx: jax.Array, zy: jax.Array, n_components: int, alpha: jax.Array) -> jax.Array:
    """IQE-maxmean distance from latents ``zx [..., N*M]`` to ``zy [..., N*M]``: ``[...]``."""
    return maxmean(iqe_components(zx, zy, n_components), alpha)


class Encoder(nn.Module):
    """MLP with GELU then LayerNorm after every hidden layer: ``[..., D] -> [..., N*M]``."""

    hidden: Sequence[int] = (512, 512, 512)
    latent: int = 512
    initializer: str = 'ogbench'

    @nn.compact
    def __call__(self, x):
        for h in self.hidden:
            x = nn.LayerNorm()(nn.gelu(nn.Dense(h, kernel_init=kernel_init(self.initializer))(x)))
        return nn.Dense(self.latent, kernel_init=kernel_init(self.initializer))(x)


class IQE(nn.Module):
    """Encoder + IQE-maxmean head. ``__call__(x, y) -> d(x, y)``; ``encode`` and ``distance``
    let callers encode once and compare latents (keypoint selection, planning).

    Attributes:
        hidden: encoder widths (paper: 3 x 512).
        n_components, component_size: N and M (paper: 512 x 1; OGBench's QRL: 64 x 8).
        initializer: the encoder's kernel initialiser (:data:`aqm_mjx.learn.networks.INITS`).
    """

    hidden: Sequence[int] = (512, 512, 512)
    n_components: int = 512
    component_size: int = 1
    initializer: str = 'ogbench'

    def setup(self):
        self.encoder = Encoder(self.hidden, self.n_components * self.component_size, self.initializer)
        self.alpha_logit = self.param('alpha_logit', nn.initializers.zeros, ())

    def encode(self, x):
        return self.encoder(x)

    def alpha(self):
        return jax.nn.sigmoid(self.alpha_logit)

    def distance(self, zx, zy):
        return iqe_distance(zx, zy, self.n_components, self.alpha())

    def __call__(self, x, y):
        return self.distance(self.encode(x), self.encode(y))
