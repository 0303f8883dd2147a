"""Goal-conditioned Gaussian policies (paper section 4.4, Appendix 10.1): the network, what it sees
of the goal, and the Gaussian's log-density and KL.

Policies are MLPs (GELU, no LayerNorm; paper Appendix 10.1) from ``[state, goal input]`` to the mean
of a diagonal Gaussian. As in OGBench's actors the standard deviation is a constant 1 by default
(``const_std``), in which case the KL between two policies is half the squared distance of their
means; a learned state-independent log-std is the option.

The goal input is the raw goal observation (the paper's choice), the unit direction from the agent's
x-y to the goal's x-y (Appendix 10.3), or ``egocentric``: the goal observation together with that unit
direction turned into the agent's own frame. For the ant, whose torso yaw is read from the
quaternion ``obs[3:7]``, the egocentric direction is what a walking gait needs: a policy that must
learn the rotation from the quaternion itself mostly ignores the goal at CPU scale (measured: 3.2 m
of progress and 8.0 m of drift against 8.6 m and 1.1 m towards an 8 m goal in 100 steps, and 1%
success against 84%; RESULTS.md section 5.1). Observations without a quaternion (the
point mass, 2-d) keep the world frame.

The objectives that train these policies are in :mod:`aqm_mjx.learn.objectives`.
"""

from __future__ import annotations

import math
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from aqm_mjx.data.expert import yaw
from aqm_mjx.learn.networks import kernel_init

CONDITIONING = ('goal', 'direction', 'egocentric')
MEAN_SCALE = 1e-2  # of the mean layer's initialisation under initializer='ogbench' (OGBench's final_fc_init_scale)
QUAT = slice(3, 7)  # torso quaternion (w, x, y, z) in an ant observation (qpos[3:7])


def goal_input_size(obs_size: int, conditioning: str) -> int:
    """G, the width of :func:`goal_input` for observations of width ``obs_size``."""
    sizes = {'goal': obs_size, 'direction': 2, 'egocentric': obs_size + 2}
    if conditioning not in sizes:
        raise ValueError(f'unknown goal conditioning {conditioning!r}; expected one of {CONDITIONING}')
    return sizes[conditioning]


def body_frame(obs: jax.Array, v: jax.Array) -> jax.Array:
    """World-frame x-y vectors ``v [..., 2]`` in the torso frame of ``obs [..., D]``.

    Rotation by minus the torso yaw read from ``obs[..., 3:7]`` when ``D >= 7``; ``v`` unchanged for
    observations without a quaternion (D < 7, e.g. the point mass).
    """
    if obs.shape[-1] < QUAT.stop:
        return v
    psi = yaw(obs[..., QUAT])
    c, s = jnp.cos(psi), jnp.sin(psi)
    return jnp.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], -1)


def unit_direction(obs: jax.Array, goal: jax.Array) -> jax.Array:
    """``[..., 2]`` the world-frame unit vector from the agent's x-y to the goal's."""
    delta = goal[..., :2] - obs[..., :2]
    return delta / (jnp.linalg.norm(delta, axis=-1, keepdims=True) + 1e-6)


def direction_input(obs: jax.Array, unit: jax.Array, conditioning: str) -> jax.Array:
    """The direction part of :func:`goal_input` for a world-frame unit vector ``unit [..., 2]``: the
    vector itself (``'direction'``) or in the torso frame (``'egocentric'``); ``[..., 0]`` for ``'goal'``."""
    if conditioning == 'goal':
        return unit[..., :0]
    return unit if conditioning == 'direction' else body_frame(obs, unit)


def goal_input(obs: jax.Array, goal: jax.Array, conditioning: str) -> jax.Array:
    """What the policy sees of the goal: ``obs, goal [..., D]`` -> ``[..., G]`` (:func:`goal_input_size`)."""
    if conditioning == 'goal':
        return goal
    if conditioning not in CONDITIONING:
        raise ValueError(f'unknown goal conditioning {conditioning!r}; expected one of {CONDITIONING}')
    unit = unit_direction(obs, goal)
    if conditioning == 'direction':
        return unit
    return jnp.concatenate([goal, direction_input(obs, unit, conditioning)], axis=-1)


class GaussianPolicy(nn.Module):
    """``(obs [..., D], goal_in [..., G]) -> (mean [..., A], log_std [..., A])``.

    Attributes:
        action_size: A.
        hidden: MLP widths (paper: 3 x 512).
        const_std: a fixed unit standard deviation (OGBench's actors) instead of a learned log-std.
        initializer: ``'ogbench'`` (variance scaling fan_avg uniform, the mean layer at 1e-2 scale, as
            OGBench's actors) or ``'lecun'`` (flax's default); :func:`~aqm_mjx.learn.networks.kernel_init`.
    """

    action_size: int
    hidden: Sequence[int] = (512, 512, 512)
    const_std: bool = True
    initializer: str = 'ogbench'

    @nn.compact
    def __call__(self, obs, goal_in):
        x = jnp.concatenate([obs, goal_in], axis=-1)
        for h in self.hidden:
            x = nn.gelu(nn.Dense(h, kernel_init=kernel_init(self.initializer))(x))
        mean = nn.Dense(self.action_size, kernel_init=kernel_init(self.initializer, MEAN_SCALE))(x)
        if self.const_std:
            log_std = jnp.zeros_like(mean)
        else:
            log_std = jnp.broadcast_to(self.param('log_std', nn.initializers.zeros, (self.action_size,)), mean.shape)
        return mean, log_std


def log_prob(mean: jax.Array, log_std: jax.Array, action: jax.Array) -> jax.Array:
    """Diagonal Gaussian log-density: ``[..., A]`` -> ``[...]``."""
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z ** 2 - log_std - 0.5 * math.log(2 * math.pi), axis=-1)


def kl(mean_p, log_std_p, mean_q, log_std_q) -> jax.Array:
    """``KL(p || q)`` of diagonal Gaussians: ``[..., A]`` -> ``[...]``."""
    var_p, var_q = jnp.exp(2 * log_std_p), jnp.exp(2 * log_std_q)
    return jnp.sum(log_std_q - log_std_p + (var_p + (mean_p - mean_q) ** 2) / (2 * var_q) - 0.5, axis=-1)
