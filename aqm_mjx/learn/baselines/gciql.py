"""GCIQL: IQL's Q(s, a, g) (two heads, target network) and V(s, g) by expectile regression on
Q - V, with a DDPG+BC actor (Q at the actor's own action, normalised by mean |Q|, plus alpha times
the dataset actions' log-likelihood)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aqm_mjx.learn import distance as to_steps, losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option


@dataclasses.dataclass(frozen=True)
class GCIQLConfig(base.BaselineConfig):
    """OGBench's GCIQL on AntMaze: expectile 0.9, DDPG+BC with alpha 0.3."""

    expectile: float = option(0.9, 'IQL expectile')
    alpha: float = option(0.3, 'BC coefficient of DDPG+BC')


def make(cfg: GCIQLConfig, obs_size: int, action_size: int):
    critic = networks.Value(cfg.value_hidden, cfg.layer_norm)
    value = networks.Value(cfg.value_hidden, cfg.layer_norm, heads=1)
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    x, g, a = base.example_inputs(obs_size, action_size, cfg)

    def init_params(key):
        k_q, k_v, k_a = jax.random.split(key, 3)
        return {'critic': critic.init(k_q, x, x, a), 'value': value.init(k_v, x, x), 'actor': actor.init(k_a, x, g)}

    def loss(params, target, batch, key):
        del key
        s, s1, vg, ag, act = batch.observations, batch.next_observations, batch.value_goals, batch.actor_goals, \
            batch.actions
        l_v, v_info = losses.iql_value_loss(critic.apply(target['critic'], s, vg, act),
                                            value.apply(params['value'], s, vg), cfg.expectile)
        next_v = value.apply(jax.lax.stop_gradient(params['value']), s1, vg)
        l_q, q_info = losses.iql_critic_loss(critic.apply(params['critic'], s, vg, act), next_v, batch.rewards,
                                             batch.masks, cfg.discount)
        mean, log_std = actor.apply(params['actor'], s, base.goal_in(cfg, s, ag))
        q = critic.apply(jax.lax.stop_gradient(params['critic']), s, ag, jnp.clip(mean, -1.0, 1.0))
        l_a, a_info = losses.ddpgbc_actor_loss(q, policy.log_prob(mean, log_std, act), cfg.alpha)
        return l_v + l_q + l_a, {**v_info, **q_info, **a_info, 'actor/mse': jnp.mean(jnp.square(mean - act))}

    def controller(p, obs, goal, t, key):
        del t, key
        return actor.apply(p['actor'], obs, base.goal_in(cfg, obs, goal))[0]

    distance = to_steps.of_value(lambda p, s, g: value.apply(p['value'], s, g), cfg.discount,
                                   'log_gamma(1 + (1 - gamma) V), V its state value')
    return base.make_learner(cfg, init_params, ('critic',), loss, controller,
                             {'critic': critic, 'value': value, 'actor': actor}, distance=distance)


METHODS = (base.Method('gciql', GCIQLConfig, make, summary='GCIQL: IQL Q and V, DDPG+BC actor',
                       style_defaults=base.ogbench_styles(alpha=0.01)),)
