"""What the baselines share: the config fields of OGBench's agents, the presets, the training state
(target networks included) and one update that samples a batch, takes the gradient of the method's
summed loss, applies one Adam step and moves the target networks.

A method supplies its modules, which of them have targets, a loss
``(params, target, batch: GCBatch, key) -> (loss, info)`` and its controller; :func:`make_learner`
turns them into a :class:`~aqm_mjx.learn.learner.Learner`. As in OGBench, one Adam optimises every
module on the summed loss, and the targets move towards the parameters *before* the step:
``target <- tau * params + (1 - tau) * target``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import optax
from flax import struct

from aqm_mjx import config as cfg_lib
from aqm_mjx import presets
from aqm_mjx.data import goals
from aqm_mjx.data.dataset import Dataset
from aqm_mjx.interface import Agent, Distance
from aqm_mjx.learn import losses, networks, policy
from aqm_mjx.learn.learner import Learner, LoopConfig, Method, option


@dataclasses.dataclass(frozen=True)
class BaselineConfig(LoopConfig):
    """OGBench's agent settings (``impls/agents/*.py`` ``get_config``), shared by every baseline."""

    lr: float = option(3e-4, 'Adam learning rate of every module')
    actor_hidden: tuple[int, ...] = option((256, 256, 256), 'actor MLP widths (paper: 3 x 512)')
    value_hidden: tuple[int, ...] = option((256, 256, 256), 'value/critic MLP widths (paper: 3 x 512)')
    layer_norm: bool = option(True, 'LayerNorm in value networks')
    discount: float = option(0.99, 'discount of the value and of geometric goal offsets')
    tau: float = option(0.005, 'target network Polyak rate')
    const_std: bool = option(True, 'actors with unit std (OGBench)')
    conditioning: str = option('egocentric', "what actors see of a raw goal: 'goal' (OGBench), 'direction', "
                               "'egocentric' (the cpu default, as AQM's)", policy.CONDITIONING)
    value_p_current: float = option(0.2, 'value goals: P(the state itself)')
    value_p_trajectory: float = option(0.5, 'value goals: P(a later state of the trajectory)')
    value_p_random: float = option(0.3, 'value goals: P(a random dataset state)')
    value_geometric: bool = option(True, 'value trajectory goals: geometric offsets (else uniform)')
    actor_p_current: float = option(0.0, 'actor goals: P(the state itself)')
    actor_p_trajectory: float = option(1.0, 'actor goals: P(a later state of the trajectory)')
    actor_p_random: float = option(0.0, 'actor goals: P(a random dataset state) (0.5 on stitch datasets)')
    actor_geometric: bool = option(False, 'actor trajectory goals: geometric offsets (else uniform)')
    subgoal_offset: int = option(25, 'k of subgoals s_{min(t+k, cap)} (HIQL, SAW)')
    subgoal_cap: str = option('goal', "'goal': cap subgoals at the actor goal's index (SAW, HIQL); 'end': at the "
                              "trajectory's end", goals.SUBGOAL_CAPS)

    def __post_init__(self):
        super().__post_init__()
        cfg_lib.check_positive_int(self, 'subgoal_offset')
        cfg_lib.check_widths(self, 'actor_hidden', 'value_hidden')
        for f in dataclasses.fields(self):
            if f.metadata.get('choices'):
                cfg_lib.check_choice(type(self).__name__, f.name, getattr(self, f.name), f.metadata['choices'])
        if not (math.isfinite(float(self.lr)) and self.lr > 0):
            raise ValueError(f'lr must be a finite number > 0; got {self.lr}')
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f'tau must be in (0, 1]; got {self.tau}')
        if any(h < 1 for h in (*self.actor_hidden, *self.value_hidden)):
            raise ValueError('hidden widths must be >= 1')
        self.sampling  # validates the goal mixtures  # pylint: disable=pointless-statement

    @property
    def sampling(self) -> goals.GCSampling:
        """The goal sampler's settings."""
        value = goals.GoalSampling(self.value_p_current, self.value_p_trajectory, self.value_p_random,
                                   self.value_geometric, self.discount, self.subgoal_offset)
        actor = goals.GoalSampling(self.actor_p_current, self.actor_p_trajectory, self.actor_p_random,
                                   self.actor_geometric, self.discount, self.subgoal_offset)
        return goals.GCSampling(value, actor, self.subgoal_offset, self.subgoal_cap)

    @classmethod
    def preset(cls, name: str, **overrides):
        """``paper``: OGBench's sizes (batch 1024, 3 x 512, 10^6 updates); ``cpu``: AQM's cpu scale
        (batch 256, 3 x 256, 20,000 updates); ``cpu-quick``: ``cpu`` for 25,000
        updates; ``cpu-long``: for 50,000; ``cpu-giant``: ``cpu`` for 150,000; ``ci``: tests."""
        size = presets.networks(name)
        return cls(**{**presets.loop(name), **SIZES[size], **cls.PRESET_OVERRIDES.get(size, {}), 'preset': name,
                      **overrides})

    PRESET_OVERRIDES = {}  # a method's values by network-size row (presets.networks; class attribute, not a field)


# the metrics the training bar shows, {metric: short name} (those a baseline logs)
# OGBench's per-dataset settings (impls/hyperparameters.sh, antmaze-*-stitch and -explore): actor goals from
# random dataset states on data whose trajectories do not cross the maze, and the explore alphas. GCBC keeps
# its trajectory goals. SAW's public settings for these styles are not known to us: it takes HIQL's goal
# mixture (it shares HIQL's value and sampler) and keeps its alphas.
STITCH_GOALS = {'actor_p_random': 0.5, 'actor_p_trajectory': 0.5}
EXPLORE_GOALS = {'actor_p_random': 1.0, 'actor_p_trajectory': 0.0}


def ogbench_styles(**explore) -> dict:
    """A method entry's ``style_defaults``: OGBench's stitch and explore goals, ``explore`` on top for explore."""
    return {'stitch': dict(STITCH_GOALS), 'explore': {**EXPLORE_GOALS, **explore}}


# the network widths of each size row (aqm_mjx.presets.networks: a preset's row), beside the loop's (presets.LOOP)
SIZES = {
    'paper': dict(actor_hidden=(512, 512, 512), value_hidden=(512, 512, 512), conditioning='goal'),
    'cpu': dict(actor_hidden=(256, 256, 256), value_hidden=(256, 256, 256)),
    'ci': dict(actor_hidden=(32, 32), value_hidden=(32, 32)),
}


@struct.dataclass
class State:
    """Every array a baseline run needs to continue exactly."""

    step: jax.Array  # int32 []
    key: jax.Array  # uint32 [2]
    params: Any  # {module name: parameters}
    target: Any  # {module name: target parameters} (empty for methods without targets)
    opt: Any  # Adam state of params


def polyak(params, target, tau: float):
    """``tau * params + (1 - tau) * target``, leaf by leaf."""
    return jax.tree.map(lambda p, t: tau * p + (1.0 - tau) * t, params, target)


def make_learner(cfg: BaselineConfig, init_params: Callable, targets: tuple, loss: Callable, controller: Callable,
                 modules: dict, encode: Callable = None, dist: Callable = None,
                 distance: Optional[Distance] = None) -> Learner:
    """A :class:`Learner` from a method's parts.

    Args:
        init_params: ``key -> {module name: params}``.
        targets: names of the modules with target copies (initialised equal to them).
        loss: ``(params, target, batch: GCBatch, key) -> (loss, info)``, the method's summed loss.
        controller: ``(params, obs [D], goal_obs [D], t, key) -> action [A]`` (the evaluation's actor).
        encode, dist: a quasimetric for methods that have one (QRL), else None.
        distance: the method's value in control steps (:mod:`aqm_mjx.learn.distance`), for the planners
            around any method; a quasimetric's own ``(encode, dist)`` when None and it has one.
    """
    tx = optax.adam(cfg.lr)
    sampling = cfg.sampling

    def init(key):
        k_params, k_run = jax.random.split(key)
        params = init_params(k_params)
        return State(step=jnp.zeros((), jnp.int32), key=k_run, params=params,
                     target={n: jax.tree.map(jnp.copy, params[n]) for n in targets},  # own buffers (donation)
                     opt=tx.init(params))

    def step(state: State, batch: goals.GCBatch, k_loss: jax.Array):
        """One update on a given batch (the state's key is left as it is)."""
        (_, info), grads = jax.value_and_grad(loss, has_aux=True)(state.params, state.target, batch, k_loss)
        updates, opt = tx.update(grads, state.opt, state.params)
        params = optax.apply_updates(state.params, updates)
        target = {n: polyak(state.params[n], state.target[n], cfg.tau) for n in targets}
        return State(step=state.step + 1, key=state.key, params=params, target=target, opt=opt), info

    def update(state: State, ds: Dataset):
        key, k_batch, k_loss = jax.random.split(state.key, 3)
        state, info = step(state, goals.sample_gc(ds, k_batch, cfg.batch_size, sampling), k_loss)
        return state.replace(key=key), info

    def params_of(state: State):
        return state.params

    def agent(aux=None) -> Agent:
        return Agent(encode, dist, controller, aux)

    if distance is None and dist is not None:
        distance = Distance(encode, dist, 'its quasimetric, in steps')
    return Learner(config=cfg, init=init, update=update, params=params_of, agent=agent, modules=modules, loss=loss,
                   step=step, distance=distance)


def goal_in(cfg: BaselineConfig, obs, goal):
    """What an actor sees of a raw goal (:func:`aqm_mjx.learn.policy.goal_input`)."""
    return policy.goal_input(obs, goal, cfg.conditioning)


def example_inputs(obs_size: int, action_size: int, cfg: BaselineConfig):
    """``(obs [1, D], goal_in [1, G], action [1, A])`` zeros for module initialisation."""
    g = policy.goal_input_size(obs_size, cfg.conditioning)
    return jnp.zeros((1, obs_size)), jnp.zeros((1, g)), jnp.zeros((1, action_size))


def ivl_terms(heads: Callable, params, target, batch, discount: float, expectile: float):
    """The IVL value loss that GCIVL, HIQL and SAW share, and the value their actors' advantages read.

    Args:
        heads: ``(params, obs [B, D], goal [B, D]) -> [2, B]``, reading ``params['value']`` (and any
            other module it needs, e.g. HIQL's ``goal_rep``).
        target: ``{'value': target parameters}``; the target heads use it with every other module
            held fixed (HIQL's and SAW's target value reads the online goal representation).
    Returns:
        ``(loss, info, v_mean)`` with ``v_mean(obs, goal) -> [B]`` the mean of the online heads,
        without gradient.
    """
    fixed = jax.lax.stop_gradient(params)
    held = {**fixed, **target}
    s, s1, vg = batch.observations, batch.next_observations, batch.value_goals
    loss, info = losses.ivl_value_loss(heads(params, s, vg), heads(held, s, vg), heads(held, s1, vg), batch.rewards,
                                       batch.masks, discount, expectile)

    def v_mean(obs, goal):
        return jnp.mean(heads(fixed, obs, goal), axis=0)

    return loss, info, v_mean


def rep_value_heads(rep: networks.GoalRep, value: networks.Value) -> Callable:
    """``heads(params, obs, goal) -> [2, B]`` of V(s, phi([s; g])) (HIQL's and SAW's value)."""

    def heads(p, obs, goal):
        return value.apply(p['value'], obs, rep.apply(p['goal_rep'], jnp.concatenate([obs, goal], axis=-1)))

    return heads
