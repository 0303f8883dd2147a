"""SAW (subgoal advantage-weighted policy bootstrapping): HIQL's IVL value V(s, phi([s; g])), a
target sub-policy pi_sub(a | s, w) trained by AWR towards w = s_{min(t+k, end)}, and one flat
policy pi(a | s, g) trained by one-step AWR towards g plus the bootstrap term
``min(exp(alpha (V(w, g) - V(s, g))), 100) * |mu(s, g) - mu_sub(s, w)|^2`` with
w = s_{min(t+k, goal index)} (SAW's reference, ``johnlyzhou/saw``, read not copied). The main
policy sees the goal through its own goal representation (SAW's ``share_goal_rep=False``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aqm_mjx.learn import distance as to_steps, losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option


@dataclasses.dataclass(frozen=True)
class SAWConfig(base.BaselineConfig):
    """SAW's defaults: expectile 0.7, temperatures 3 (sub-policy, AWR, bootstrap), k = 25, phi 10-d."""

    expectile: float = option(0.7, 'IVL expectile')
    low_alpha: float = option(3.0, 'sub-policy AWR temperature')
    awr_alpha: float = option(3.0, "main policy's one-step AWR temperature")
    kl_alpha: float = option(3.0, 'bootstrap (waypoint) term temperature')
    rep_dim: int = option(10, 'goal representation width')


def make(cfg: SAWConfig, obs_size: int, action_size: int):
    rep = networks.GoalRep(cfg.value_hidden, cfg.rep_dim, cfg.layer_norm)
    value = networks.Value(cfg.value_hidden, cfg.layer_norm)
    sub_actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std)
    x, g, _ = base.example_inputs(obs_size, action_size, cfg)
    r = jnp.zeros((1, cfg.rep_dim))

    heads = base.rep_value_heads(rep, value)

    def main(p, s, goal):
        """The main policy: ``(mean, log_std)`` of pi(. | s, phi_actor([s; goal input]))."""
        z = rep.apply(p['actor_goal_rep'], jnp.concatenate([s, base.goal_in(cfg, s, goal)], -1))
        return actor.apply(p['actor'], s, z)

    def init_params(key):
        k_r, k_v, k_s, k_ar, k_a = jax.random.split(key, 5)
        return {'goal_rep': rep.init(k_r, jnp.concatenate([x, x], -1)), 'value': value.init(k_v, x, r),
                'sub_actor': sub_actor.init(k_s, x, g), 'actor_goal_rep': rep.init(k_ar, jnp.concatenate([x, g], -1)),
                'actor': actor.init(k_a, x, r)}

    def loss(params, target, batch, key):
        del key
        s, s1, act = batch.observations, batch.next_observations, batch.actions
        fixed = jax.lax.stop_gradient(params)
        l_v, info, v_mean = base.ivl_terms(heads, params, target, batch, cfg.discount, cfg.expectile)
        # SUB-POLICY towards w = s_{min(t+k, end)}
        w = batch.low_goals
        mu_s, ls_s = sub_actor.apply(params['sub_actor'], s, base.goal_in(cfg, s, w))
        l_sub, sub_info = losses.awr_actor_loss(policy.log_prob(mu_s, ls_s, act), v_mean(s1, w) - v_mean(s, w),
                                                cfg.low_alpha, prefix='sub_actor')
        # MAIN: one-step AWR towards g, and the bootstrap towards pi_sub(. | s, w_g), w_g = s_{min(t+k, goal)}
        gh, wh = batch.actor_goals, batch.subgoals
        mu, ls = main(params, s, gh)
        l_awr, awr_info = losses.awr_actor_loss(policy.log_prob(mu, ls, act), v_mean(s1, gh) - v_mean(s, gh),
                                                cfg.awr_alpha, prefix='actor')
        mu_w = sub_actor.apply(fixed['sub_actor'], s, base.goal_in(cfg, s, wh))[0]
        l_kl, kl_info = losses.waypoint_loss(mu, mu_w, v_mean(wh, gh) - v_mean(s, gh), cfg.kl_alpha)
        return l_v + l_sub + l_awr + l_kl, {**info, **sub_info, **awr_info, **kl_info,
                                             'actor/mse': jnp.mean(jnp.square(mu - act))}

    def controller(p, obs, goal, t, key):
        del t, key
        return main(p, obs, goal)[0]

    distance = to_steps.of_value(lambda p, s, g: jnp.mean(heads(p, s, g)), cfg.discount,
                                   'log_gamma(1 + (1 - gamma) V), V the mean of its two heads of V(s, phi([s; g]))')
    return base.make_learner(cfg, init_params, ('value',), loss, controller,
                             {'goal_rep': rep, 'value': value, 'sub_actor': sub_actor, 'actor': actor}, distance=distance)


METHODS = (base.Method('saw', SAWConfig, make, summary='SAW: IVL value, sub-policy and a flat policy bootstrapped '
                       'from it', style_defaults=base.ogbench_styles()),)
