"""CRL: a contrastive critic phi(s, a) . psi(g) trained by InfoNCE in its binary cross-entropy form
(future states of the same trajectory are the positives, the batch's other goals the negatives),
and a DDPG+BC actor on the critic's logits."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aqm_mjx.interface import Distance
from aqm_mjx.learn import distance as to_steps, losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option


@dataclasses.dataclass(frozen=True)
class CRLConfig(base.BaselineConfig):
    """OGBench's CRL on AntMaze: latent 512, DDPG+BC with alpha 0.1, value goals from the trajectory."""

    latent: int = option(512, 'phi and psi width')
    alpha: float = option(0.1, 'BC coefficient of DDPG+BC')
    value_p_current: float = option(0.0, 'value goals: P(the state itself)')
    value_p_trajectory: float = option(1.0, 'value goals: P(a later state of the trajectory)')
    value_p_random: float = option(0.0, 'value goals: P(a random dataset state)')

    PRESET_OVERRIDES = {'cpu': {'latent': 256}, 'ci': {'latent': 16}}


def make(cfg: CRLConfig, obs_size: int, action_size: int):
    critic = networks.Bilinear(cfg.value_hidden, cfg.latent, cfg.layer_norm)
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    x, g, a = base.example_inputs(obs_size, action_size, cfg)

    def init_params(key):
        k_q, k_a = jax.random.split(key)
        return {'critic': critic.init(k_q, x, x, a), 'actor': actor.init(k_a, x, g)}

    def loss(params, target, batch, key):
        del target, key
        s, ag, act = batch.observations, batch.actor_goals, batch.actions
        _, phi, psi = critic.apply(params['critic'], s, batch.value_goals, act)
        l_q, q_info = losses.infonce_loss(phi, psi)
        mean, log_std = actor.apply(params['actor'], s, base.goal_in(cfg, s, ag))
        q = critic.apply(jax.lax.stop_gradient(params['critic']), s, ag, jnp.clip(mean, -1.0, 1.0))[0]
        l_a, a_info = losses.ddpgbc_actor_loss(q, policy.log_prob(mean, log_std, act), cfg.alpha)
        return l_q + l_a, {**q_info, **a_info, 'actor/mse': jnp.mean(jnp.square(mean - act))}

    def controller(p, obs, goal, t, key):
        del t, key
        return actor.apply(p['actor'], obs, base.goal_in(cfg, obs, goal))[0]

    def dist(p, s, g):
        a = jnp.clip(controller(p, s, g, 0, None), -1.0, 1.0)[None]  # the action its actor takes toward g
        f = critic.apply(p['critic'], jnp.stack([s, s]), jnp.stack([s, g]), jnp.concatenate([a, a]))[0]  # [2 heads, 2]
        return to_steps.steps_from_log_ratio(jnp.mean(f[:, 0]), jnp.mean(f[:, 1]), cfg.discount)

    distance = Distance(to_steps.identity, dist, '(f(s, a, s) - f(s, a, g)) / log(1 / gamma) of its critic f, a '
                        "its actor's action toward g, the two heads averaged")
    return base.make_learner(cfg, init_params, (), loss, controller, {'critic': critic, 'actor': actor},
                             distance=distance)


METHODS = (base.Method('crl', CRLConfig, make, summary='CRL: contrastive critic (InfoNCE), DDPG+BC actor',
                       style_defaults=base.ogbench_styles(alpha=0.003)),)
