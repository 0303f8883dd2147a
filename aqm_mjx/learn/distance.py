"""A method's value as a distance in control steps: what a planner around any method reads
(:class:`~aqm_mjx.interface.Distance`, built by each method and handed out as ``Learner.distance``).

A value learned with OGBench's goal-conditioned rewards (-1 a step until the goal, 0 there; discount
gamma) estimates ``V = -(1 - gamma^d) / (1 - gamma)`` for a goal ``d`` steps away, so

    d = log_gamma(1 + (1 - gamma) V)                  (TTGS, arXiv 2510.07257, eq. 1)

:func:`steps_from_value` inverts it, clipped as TTGS clips it (``V`` kept inside ``(-1 / (1 - gamma),
0)`` by 1e-3, so a value at or past either end reads as 0 steps or about 1,000 steps at gamma 0.99,
never NaN). A Hilbert value ``-||phi(s) - phi(g)||`` (HILP, GAS's TDR) is such a value;
a quasimetric (QRL's, AQM's) is in steps already; CRL's contrastive critic is read by
:func:`steps_from_log_ratio`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from aqm_mjx.interface import Distance

EPS = 1e-3


def steps_from_value(v: jax.Array, discount: float) -> jax.Array:
    """``log_gamma(1 + (1 - gamma) v)`` for values ``v [...]`` on OGBench's -1-a-step rewards,
    ``v`` clipped to ``[-1 / (1 - gamma) + EPS, -EPS]`` first: ``[...] -> [...]`` steps >= 0."""
    g = float(discount)
    v = jnp.clip(v, -1.0 / (1.0 - g) + EPS, -EPS)
    return jnp.maximum(jnp.log1p((1.0 - g) * v) / jnp.log(g), 0.0)


def value_from_steps(d: jax.Array, discount: float) -> jax.Array:
    """The value of a goal ``d`` steps away, ``-(1 - gamma^d) / (1 - gamma)`` (the inverse; tests)."""
    g = float(discount)
    return -(1.0 - jnp.power(g, d)) / (1.0 - g)


def steps_from_log_ratio(at_goal: jax.Array, logit: jax.Array, discount: float) -> jax.Array:
    """CRL: a critic ``f(s, a, g) ~ log p_gamma(g | s, a) / p(g)`` of a discounted occupancy falls by
    ``log(1 / gamma)`` a step, so ``d = (f(s, a, s) - f(s, a, g)) / log(1 / gamma)``, the state itself
    as the zero (``at_goal = f(s, a, s)``, ``logit = f(s, a, g)``), floored at 0."""
    return jnp.maximum((at_goal - logit) / -jnp.log(float(discount)), 0.0)


def identity(aux, obs: jax.Array) -> jax.Array:
    """The encoder of a value that is not factored: a state is its own latent."""
    del aux
    return obs


def of_value(value, discount: float, about: str) -> Distance:
    """The :class:`~aqm_mjx.interface.Distance` of a value ``value(aux, obs [D], goal [D]) -> scalar``
    on OGBench's rewards: states as latents, :func:`steps_from_value` of the value."""
    return Distance(identity, lambda aux, s, g: steps_from_value(value(aux, s, g), discount), about)


def of_hilbert(encode, discount: float, about: str) -> Distance:
    """The distance of a Hilbert value ``-||phi(s) - phi(g)||`` (``encode = phi``)."""
    return Distance(encode, lambda aux, u, v: steps_from_value(-jnp.linalg.norm(u - v), discount), about)
