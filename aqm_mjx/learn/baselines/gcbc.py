"""GCBC: goal-conditioned behaviour cloning on future states of the same trajectory."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from aqm_mjx.learn import networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option


@dataclasses.dataclass(frozen=True)
class GCBCConfig(base.BaselineConfig):
    """GCBC: only actor goals matter (trajectory, uniform)."""

    value_p_current: float = option(0.0, 'unused by GCBC')
    value_p_trajectory: float = option(1.0, 'unused by GCBC')
    value_p_random: float = option(0.0, 'unused by GCBC')


def make(cfg: GCBCConfig, obs_size: int, action_size: int):
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    x, g, _ = base.example_inputs(obs_size, action_size, cfg)

    def init_params(key):
        return {'actor': actor.init(key, x, g)}

    def loss(params, target, batch, key):
        del target, key
        s = batch.observations
        mean, log_std = actor.apply(params['actor'], s, base.goal_in(cfg, s, batch.actor_goals))
        logp = policy.log_prob(mean, log_std, batch.actions)
        l = -jnp.mean(logp)
        return l, {'actor/loss': l, 'actor/mse': jnp.mean(jnp.square(mean - batch.actions))}

    def controller(p, obs, goal, t, key):
        del t, key
        return actor.apply(p['actor'], obs, base.goal_in(cfg, obs, goal))[0]

    return base.make_learner(cfg, init_params, (), loss, controller, {'actor': actor})


METHODS = (base.Method('gcbc', GCBCConfig, make, summary='GCBC: goal-conditioned behaviour cloning'),)
