"""OGBench's flat QRL: an IQE quasimetric d(s, g) trained by the QRL dual objective (random goals
pushed apart through ``100 softplus(5 - d / 100)``, transitions held within one step by a learned
multiplier), a latent dynamics model z' = z + f(z, a) trained to be d-close to the next latent,
and a DDPG+BC actor on Q(s, a, g) = -d(z + f(z, a), z_g).

Our IQE (:class:`aqm_mjx.learn.quasimetric.IQE`) has OGBench's encoder (GELU, LayerNorm, variance
scaling fan_avg uniform initialisation; flax's LeCun normal before 2026-11-24) and components; it names the max-mean weights the other way round, which at their common initial
value 0.5 is the same function. The quasimetric is also handed to evaluation, so a QRL model can
be run by the AQM agent as well as flat.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aqm_mjx.learn import losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option
from aqm_mjx.learn.quasimetric import IQE


@dataclasses.dataclass(frozen=True)
class QRLConfig(base.BaselineConfig):
    """OGBench's QRL on AntMaze: IQE 64 x 8 (latent 512), eps 0.05, DDPG+BC alpha 0.003, random value goals."""

    latent: int = option(512, 'IQE latent width (components x component size)')
    component_size: int = option(8, 'IQE component size M')
    eps: float = option(0.05, 'margin of the multiplier: mean(relu(d(s, s\') - 1)^2) <= eps')
    alpha: float = option(0.003, 'BC coefficient of DDPG+BC')
    value_p_current: float = option(0.0, 'value goals: P(the state itself)')
    value_p_trajectory: float = option(0.0, 'value goals: P(a later state of the trajectory)')
    value_p_random: float = option(1.0, 'value goals: P(a random dataset state)')

    PRESET_OVERRIDES = {'cpu': {'latent': 256}, 'ci': {'latent': 16}}

    def __post_init__(self):
        super().__post_init__()
        if self.latent % self.component_size:
            raise ValueError(f'latent ({self.latent}) must be a multiple of component_size ({self.component_size})')


def make(cfg: QRLConfig, obs_size: int, action_size: int):
    iqe = IQE(hidden=tuple(cfg.value_hidden), n_components=cfg.latent // cfg.component_size,
              component_size=cfg.component_size)
    dynamics = networks.MLP((*cfg.value_hidden, cfg.latent), layer_norm=cfg.layer_norm)
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    x, g, a = base.example_inputs(obs_size, action_size, cfg)

    def enc(p, o):
        return iqe.apply(p, o, method=IQE.encode)

    def d(p, zx, zy):
        return iqe.apply(p, zx, zy, method=IQE.distance)

    def init_params(key):
        k_v, k_d, k_a = jax.random.split(key, 3)
        return {'value': iqe.init(k_v, x, x), 'dynamics': dynamics.init(k_d, jnp.zeros((1, cfg.latent + a.shape[1]))),
                'actor': actor.init(k_a, x, g), 'log_lambda': jnp.zeros((), jnp.float32)}

    def loss(params, target, batch, key):
        del target, key
        s, s1, ag, act = batch.observations, batch.next_observations, batch.actor_goals, batch.actions
        pv = params['value']
        zs, zs1, zg = jnp.split(enc(pv, jnp.concatenate([s, s1, batch.value_goals])), 3)
        l_v, v_info = losses.qrl_value_loss(d(pv, zs, zg), d(pv, zs, zs1), jnp.exp(params['log_lambda']), cfg.eps)
        z_hat = zs + dynamics.apply(params['dynamics'], jnp.concatenate([zs, act], axis=-1))
        l_d, d_info = losses.dynamics_loss(d(pv, zs1, z_hat), d(pv, z_hat, zs1))
        mean, log_std = actor.apply(params['actor'], s, base.goal_in(cfg, s, ag))
        fixed = jax.lax.stop_gradient(params)
        z, z_goal = jnp.split(enc(fixed['value'], jnp.concatenate([s, ag])), 2)
        z_next = z + dynamics.apply(fixed['dynamics'], jnp.concatenate([z, jnp.clip(mean, -1.0, 1.0)], axis=-1))
        q = -d(fixed['value'], z_next, z_goal)
        l_a, a_info = losses.ddpgbc_actor_loss(q, policy.log_prob(mean, log_std, act), cfg.alpha)
        return l_v + l_d + l_a, {**v_info, **d_info, **a_info, 'actor/mse': jnp.mean(jnp.square(mean - act))}

    def controller(p, obs, goal, t, key):
        del t, key
        return actor.apply(p['actor'], obs, base.goal_in(cfg, obs, goal))[0]

    def encode(p, obs):
        return enc(p['value'], obs)

    def dist(p, zx, zy):
        return d(p['value'], zx, zy)

    return base.make_learner(cfg, init_params, (), loss, controller,
                             {'quasimetric': iqe, 'dynamics': dynamics, 'actor': actor}, encode=encode, dist=dist)


METHODS = (base.Method('qrl', QRLConfig, make, summary="QRL (OGBench's): IQE quasimetric, latent dynamics, DDPG+BC",
                       style_defaults=base.ogbench_styles(alpha=0.001)),)
