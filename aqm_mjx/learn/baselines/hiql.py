"""HIQL: an IVL value V(s, phi([s; g])) whose goal representation phi (10-d, length-normalised) is
learned through the value, a high policy that predicts phi([s; w]) of the subgoal
w = s_{min(t+k, goal index)} by AWR with advantage V(w, g) - V(s, g), and a low policy acting on
(s, phi([s; w])) by AWR with advantage V(s', w) - V(s, w), w = s_{min(t+k, end)}.

At test time the high policy's mean, length-normalised, is the low policy's goal at every step.
The target value reads the online goal representation (OGBench shares that module).

Goal input. With ``conditioning='goal'`` this is OGBench's HIQL. With ``'direction'`` or
``'egocentric'`` (the ``cpu`` preset, where every other actor sees the goal's direction) both levels
see the direction, as the paper conditions HIQL (its appendix 10.3): the high policy reads the
goal's input like every actor and predicts ``[phi([s; w]), unit(w_xy - s_xy)]``; the low policy acts
on ``[phi([s; w]), direction]`` with the direction in the frame the others use (the torso frame for
``'egocentric'``), from the true subgoal in training and from the high policy's unit-normalised
prediction at test time.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aqm_mjx.learn import distance as to_steps, losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option


@dataclasses.dataclass(frozen=True)
class HIQLConfig(base.BaselineConfig):
    """OGBench's HIQL on AntMaze: expectile 0.7, high and low AWR temperature 3, k = 25, phi 10-d."""

    expectile: float = option(0.7, 'IVL expectile')
    high_alpha: float = option(3.0, 'high policy AWR temperature')
    low_alpha: float = option(3.0, 'low policy AWR temperature')
    rep_dim: int = option(10, 'goal representation width')
    low_rep_grad: bool = option(False, "low policy's gradient reaches phi (OGBench: False for states)")


def make(cfg: HIQLConfig, obs_size: int, action_size: int):
    rep = networks.GoalRep(cfg.value_hidden, cfg.rep_dim, cfg.layer_norm)
    value = networks.Value(cfg.value_hidden, cfg.layer_norm)
    steer = 0 if cfg.conditioning == 'goal' else 2  # the direction beside phi (see the module's note)
    low = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    high = networks.Actor(cfg.actor_hidden, cfg.rep_dim + steer, cfg.const_std)
    x, g, _ = base.example_inputs(obs_size, action_size, cfg)
    r = jnp.zeros((1, cfg.rep_dim))

    def phi(p, s, goal):
        return rep.apply(p, jnp.concatenate([s, goal], axis=-1))

    def subgoal(p, s, goal):
        """The high policy's target for subgoal ``goal``: phi([s; goal]) (and its unit direction)."""
        z = phi(p, s, goal)
        return jnp.concatenate([z, policy.unit_direction(s, goal)], -1) if steer else z

    def low_input(s, sub):
        """The low policy's goal input from a subgoal target (true or predicted) ``sub [B, rep + steer]``."""
        if not steer:
            return sub
        unit = sub[..., cfg.rep_dim:] / (jnp.linalg.norm(sub[..., cfg.rep_dim:], axis=-1, keepdims=True) + 1e-6)
        return jnp.concatenate([sub[..., :cfg.rep_dim], policy.direction_input(s, unit, cfg.conditioning)], -1)

    heads = base.rep_value_heads(rep, value)

    def init_params(key):
        k_r, k_v, k_l, k_h = jax.random.split(key, 4)
        return {'goal_rep': rep.init(k_r, jnp.concatenate([x, x], -1)), 'value': value.init(k_v, x, r),
                'low_actor': low.init(k_l, x, jnp.zeros((1, cfg.rep_dim + steer))), 'high_actor': high.init(k_h, x, g)}

    def loss(params, target, batch, key):
        del key
        s, s1 = batch.observations, batch.next_observations
        fixed = jax.lax.stop_gradient(params)
        l_v, info, v_mean = base.ivl_terms(heads, params, target, batch, cfg.discount, cfg.expectile)
        # LOW: act towards w = s_{min(t+k, end)}
        w = batch.low_goals
        w_rep = subgoal(params['goal_rep'] if cfg.low_rep_grad else fixed['goal_rep'], s, w)
        mu, ls = low.apply(params['low_actor'], s, low_input(s, w_rep))
        l_lo, lo_info = losses.awr_actor_loss(policy.log_prob(mu, ls, batch.actions), v_mean(s1, w) - v_mean(s, w),
                                              cfg.low_alpha, prefix='low_actor')
        # HIGH: predict phi([s; w_h]) of w_h = s_{min(t+k, goal index)} for goal g_h
        gh, wh = batch.actor_goals, batch.subgoals
        mu_h, ls_h = high.apply(params['high_actor'], s, base.goal_in(cfg, s, gh))
        l_hi, hi_info = losses.awr_actor_loss(policy.log_prob(mu_h, ls_h, subgoal(fixed['goal_rep'], s, wh)),
                                              v_mean(wh, gh) - v_mean(s, gh), cfg.high_alpha, prefix='high_actor')
        return l_v + l_lo + l_hi, {**info, **lo_info, **hi_info,
                                   'low_actor/mse': jnp.mean(jnp.square(mu - batch.actions))}

    def controller(p, obs, goal, t, key):
        del t, key
        pred = high.apply(p['high_actor'], obs, base.goal_in(cfg, obs, goal))[0]
        sub = jnp.concatenate([networks.length_normalize(pred[..., :cfg.rep_dim]), pred[..., cfg.rep_dim:]], -1)
        return low.apply(p['low_actor'], obs, low_input(obs, sub))[0]

    distance = to_steps.of_value(lambda p, s, g: jnp.mean(heads(p, s, g)), cfg.discount,
                                   'log_gamma(1 + (1 - gamma) V), V the mean of its two heads of V(s, phi([s; g]))')
    return base.make_learner(cfg, init_params, ('value',), loss, controller,
                             {'goal_rep': rep, 'value': value, 'low_actor': low, 'high_actor': high}, distance=distance)


METHODS = (base.Method('hiql', HIQLConfig, make, summary='HIQL: IVL value with goal representation, high and '
                       'low AWR policies', style_defaults=base.ogbench_styles(high_alpha=10.0, low_alpha=10.0)),)
