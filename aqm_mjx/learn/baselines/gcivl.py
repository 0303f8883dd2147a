"""GCIVL: a goal-conditioned V learned by implicit V-learning (expectile regression on its own
bootstrap, two heads, target network) and an AWR actor with advantage V(s', g) - V(s, g)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aqm_mjx.learn import distance as to_steps, losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option


@dataclasses.dataclass(frozen=True)
class GCIVLConfig(base.BaselineConfig):
    """OGBench's GCIVL on AntMaze: expectile 0.9, AWR temperature 10."""

    expectile: float = option(0.9, 'IVL expectile')
    alpha: float = option(10.0, 'AWR temperature')


def make(cfg: GCIVLConfig, obs_size: int, action_size: int):
    value = networks.Value(cfg.value_hidden, cfg.layer_norm)
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    x, g, _ = base.example_inputs(obs_size, action_size, cfg)

    def heads(p, obs, goal):
        return value.apply(p['value'], obs, goal)

    def init_params(key):
        k_v, k_a = jax.random.split(key)
        return {'value': value.init(k_v, x, x), 'actor': actor.init(k_a, x, g)}

    def loss(params, target, batch, key):
        del key
        s, s1, ag = batch.observations, batch.next_observations, batch.actor_goals
        l_v, info, v_mean = base.ivl_terms(heads, params, target, batch, cfg.discount, cfg.expectile)
        adv = v_mean(s1, ag) - v_mean(s, ag)
        mean, log_std = actor.apply(params['actor'], s, base.goal_in(cfg, s, ag))
        l_a, a_info = losses.awr_actor_loss(policy.log_prob(mean, log_std, batch.actions), adv, cfg.alpha)
        return l_v + l_a, {**info, **a_info, 'actor/mse': jnp.mean(jnp.square(mean - batch.actions))}

    def controller(p, obs, goal, t, key):
        del t, key
        return actor.apply(p['actor'], obs, base.goal_in(cfg, obs, goal))[0]

    distance = to_steps.of_value(lambda p, s, g: jnp.mean(heads(p, s, g)), cfg.discount,
                                   'log_gamma(1 + (1 - gamma) V), V the mean of its two value heads')
    return base.make_learner(cfg, init_params, ('value',), loss, controller, {'value': value, 'actor': actor},
                             distance=distance)


METHODS = (base.Method('gcivl', GCIVLConfig, make, summary='GCIVL: implicit V-learning value, AWR actor',
                       style_defaults=base.ogbench_styles()),)
