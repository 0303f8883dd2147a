"""HILP (Park et al., 2024, "Foundation Policies with Hilbert Representations") for goal-conditioned
navigation, as its public code trains it (``hilp_gcrl/src/agents/hilp.py``):

- a Hilbert representation ``phi``: the value ``V(s, g) = -||phi(s) - phi(g)||`` (two heads,
  :class:`~aqm_mjx.learn.networks.HilbertValue`) learned by implicit V-learning on goal-reaching
  rewards (:func:`~aqm_mjx.learn.losses.ivl_value_loss`, expectile 0.95), with a target copy;
- a latent-conditioned policy ``pi(a | s, z)`` for unit directions ``z`` drawn at random per
  transition, rewarded by the progress ``(phi(s') - phi(s)) . z`` along them (``phi`` held fixed):
  IQL's value and twin critic on ``(s, z)`` (no terminal) and an AWR actor (temperature 10; a ReLU
  MLP without LayerNorm and a learned log-std, as ``jaxrl_m``'s ``Policy``);
- at test time the direction to a waypoint, ``z = (phi(w) - phi(s)) / ||phi(w) - phi(s)||``: with
  ``planning_recursions`` > 0 (3, as HILP's AntMaze runs) its test-time planning
  (:mod:`aqm_mjx.agent.hilp_rule`: midpoints among ``planning_states`` dataset states), with 0 the
  goal itself (a flat method).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aqm_mjx.interface import Agent, spec
from aqm_mjx.learn import distance as to_steps, losses, networks, policy
from aqm_mjx.learn.baselines import base
from aqm_mjx.learn.learner import option


@dataclasses.dataclass(frozen=True)
class HILPConfig(base.BaselineConfig):
    """HILP's settings for AntMaze (``hilp_gcrl/main.py``): latent 32, expectiles 0.95 and 0.9,
    AWR temperature 10, value goals 62.5% from the trajectory (geometric), 37.5% random."""

    latent: int = option(32, "phi's width (HILP's skill_dim)")
    expectile: float = option(0.95, "the representation's IVL expectile")
    skill_expectile: float = option(0.9, "the latent policy's IQL expectile")
    skill_temperature: float = option(10.0, "the latent policy's AWR temperature")
    skill_discount: float = option(0.99, "the latent policy's discount")
    const_std: bool = option(False, 'actor with a learned state-independent log-std (HILP)')
    value_p_current: float = option(0.0, 'value goals: P(the state itself)')
    value_p_trajectory: float = option(0.625, 'value goals: P(a later state of the trajectory)')
    value_p_random: float = option(0.375, 'value goals: P(a random dataset state)')
    planning_recursions: int = option(3, 'test-time planning: midpoint recursions (0: steer at the goal itself)')
    planning_states: int = option(50_000, 'test-time planning: dataset states drawn (with replacement) per evaluation')
    planning_knns: int = option(50, 'test-time planning: nearest states averaged into each midpoint')

    PRESET_OVERRIDES = {'ci': {'latent': 8, 'planning_states': 512, 'planning_knns': 8}}

    def __post_init__(self):
        super().__post_init__()
        if self.planning_recursions < 0:
            raise ValueError(f'planning_recursions must be >= 0 (0: no planning); got {self.planning_recursions}')
        if not 1 <= self.planning_knns <= self.planning_states:
            raise ValueError(f'planning_knns must be in [1, planning_states = {self.planning_states}]; '
                             f'got {self.planning_knns}')


def unit(x: jax.Array) -> jax.Array:
    """``x / ||x||`` along the last axis (a zero vector stays zero)."""
    return x / jnp.maximum(jnp.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def make(cfg: HILPConfig, obs_size: int, action_size: int):
    value = networks.HilbertValue(cfg.value_hidden, cfg.latent, cfg.layer_norm)
    skill_value = networks.Value(cfg.value_hidden, cfg.layer_norm, heads=1)
    skill_critic = networks.Value(cfg.value_hidden, cfg.layer_norm, heads=2)
    actor = networks.Actor(cfg.actor_hidden, action_size, cfg.const_std, activation='relu')  # jaxrl_m's Policy MLP
    x, _, a = base.example_inputs(obs_size, action_size, cfg)
    z0 = jnp.zeros((1, cfg.latent))

    def heads(p, obs, goal):
        return value.apply(p['value'], obs, goal)

    def phi(p, obs):
        return value.apply(p['value'], obs, method='phi')

    def init_params(key):
        k = jax.random.split(key, 4)
        return {'value': value.init(k[0], x, x), 'skill_value': skill_value.init(k[1], x, z0),
                'skill_critic': skill_critic.init(k[2], x, z0, a), 'actor': actor.init(k[3], x, z0)}

    def loss(params, target, batch, key):
        s, s1, act = batch.observations, batch.next_observations, batch.actions
        l_v, info, _ = base.ivl_terms(heads, params, target, batch, cfg.discount, cfg.expectile)
        # the latent policy: random unit directions, rewarded by progress along them in a fixed phi
        fixed = jax.lax.stop_gradient(params)
        z = unit(jax.random.normal(key, (s.shape[0], cfg.latent)))
        r = jnp.sum((phi(fixed, s1) - phi(fixed, s)) * z, axis=-1)
        q_target = skill_critic.apply(target['skill_critic'], s, z, act)
        v = skill_value.apply(params['skill_value'], s, z)
        l_sv, sv_info = losses.iql_value_loss(q_target, v, cfg.skill_expectile)
        next_v = skill_value.apply(fixed['skill_value'], s1, z)
        l_c, c_info = losses.iql_critic_loss(skill_critic.apply(params['skill_critic'], s, z, act), next_v, r,
                                             jnp.ones_like(r), cfg.skill_discount)
        adv = jnp.min(q_target, axis=0) - jax.lax.stop_gradient(v)
        mean, log_std = actor.apply(params['actor'], s, z)
        l_a, a_info = losses.awr_actor_loss(policy.log_prob(mean, log_std, act), adv, cfg.skill_temperature,
                                            prefix='skill_actor')
        info = {**info, **{f'skill_{k}': v for k, v in {**sv_info, **c_info}.items()}, **a_info,
                'skill/reward_mean': jnp.mean(r), 'skill_actor/mse': jnp.mean(jnp.square(mean - act))}
        return l_v + l_sv + l_c + l_a, info

    def controller(p, obs, goal, t, key):
        del t, key
        z = unit(phi(p, goal) - phi(p, obs))
        return actor.apply(p['actor'], obs, z)[0]

    def encode(p, obs):
        return phi(p, obs[None])[0]

    distance = to_steps.of_hilbert(encode, cfg.discount, 'log_gamma(1 - (1 - gamma) ||phi(s) - phi(g)||) of its '
                                   'Hilbert value')
    learner = base.make_learner(cfg, init_params, ('value', 'skill_critic'), loss, controller,
                                {'value': value, 'skill_value': skill_value, 'skill_critic': skill_critic,
                                 'actor': actor}, distance=distance)
    if not cfg.planning_recursions:
        return learner

    def steer(p, obs, phi_s, target):
        """The latent policy's mean toward latent ``target`` from ``obs`` (``phi_s = phi(obs)``)."""
        return actor.apply(p['actor'], obs, unit(target - phi_s))[0]

    # its planning states (aqm_mjx.mapping.states) and midpoint rule (aqm_mjx.agent.hilp_rule), resolved there
    mapper = spec('hilp', states=cfg.planning_states)
    rule = spec('hilp', recursions=cfg.planning_recursions, knns=cfg.planning_knns)

    def agent(aux=None) -> Agent:
        return Agent(encode, None, controller, aux, rule=rule, mapper=mapper, skill=steer)

    return learner._replace(agent=agent)


METHODS = (base.Method('hilp', HILPConfig, make, summary='HILP: Hilbert representation, latent-direction policy, '
                       'midpoint planning among dataset states',
                       progress={'value/loss': 'value', 'skill_critic/loss': 'critic', 'skill_actor/loss': 'actor'}),)
