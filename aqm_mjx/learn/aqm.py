"""AQM's learned parts (paper Algorithm 1, steps A and B): the IQE quasimetric trained with QRL,
its Lagrange multiplier, and the policies of one of :data:`~aqm_mjx.learn.objectives.OBJECTIVES`
(Q-AWR target + Q-SAW main by default).

    cfg = AQMConfig.preset('cpu', env='antmaze-medium')
    learner = make(cfg, obs_size=29, action_size=8)
    state = learner.init(jax.random.PRNGKey(0))
    state, metrics = learner.update(state, dataset)         # one update; training scans it
    agent = learner.agent(learner.params(state))            # IQE + the main policy's mean
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Optional

import jax
import jax.numpy as jnp
import optax
from flax import struct

from aqm_mjx import config as cfg_lib
from aqm_mjx import presets
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.data import goals
from aqm_mjx.envs import parse_name
from aqm_mjx.interface import Agent, Distance
from aqm_mjx.learn import objectives, policy
from aqm_mjx.learn.learner import Learner, LoopConfig, Method, option
from aqm_mjx.learn.losses import lambda_loss, qrl_loss
from aqm_mjx.learn.networks import INITS
from aqm_mjx.learn.quasimetric import IQE

QRL_VARIANTS = ('paper', 'ogbench')
# the states the push term d(s, g) reaches: 'rolled' pairs each s with the previous row's s' (QRL's reference
# implementation, Wang et al. 2023: the rows are drawn independently, so row i - 1's s' is independent of row i);
# 'sampled' draws B more states uniformly from the dataset, one more encoder pass with gradients (B rows of
# the 3B the quasimetric backpropagates through: 1.28x slower on a 2-core CPU at cpu-long, bench_train.py)
PUSH_PAIRS = ('rolled', 'sampled')
POLICY_GOALS = ('trajectory', 'random')
# Table 5 gives m for medium, large and giant; arena and teleport are not in it: arena takes medium's
# value and teleport large's (its maze is the size of large), both extrapolated by us.
PUSH_OFFSETS = {'arena': 50.0, 'medium': 50.0, 'large': 125.0, 'teleport': 125.0, 'giant': 250.0}
OGBENCH_PUSH_OFFSET = 500.0  # OGBench's QRL: 100 * softplus(5 - d / 100)
# fields added after runs were saved, with the value those runs were trained under
LEGACY = {'subgoal_cap': 'end', 'initializer': 'lecun', 'push_pairs': 'sampled'}


@dataclasses.dataclass(frozen=True)
class AQMConfig(LoopConfig):
    """Everything an AQM training run depends on; saved as JSON beside every checkpoint."""

    # quasimetric (paper section 4.2, Appendix 10.1)
    q_hidden: tuple[int, ...] = option((256, 256, 256), 'encoder MLP widths (paper: 3 x 512)')
    n_components: int = option(256, 'IQE components N (paper: 512)')
    component_size: int = option(1, "IQE component size M (paper: 1; OGBench's QRL: 8)")
    lr_quasimetric: float = option(1e-4, 'quasimetric learning rate')
    qrl: str = option('paper', "'paper': lambda >= 0 by projection; 'ogbench': lambda = exp(log lambda), offset 500",
                      QRL_VARIANTS)
    epsilon: float = option(math.sqrt(0.05),
                            "local-constraint slack: mean(relu(d(s,s') - 1)^2) <= epsilon^2 (OGBench 0.05)")
    push_offset: Optional[float] = option(None, 'm of omega; none: Table 5 by maze (or 500 for qrl=ogbench)')
    push_scale: float = option(0.01, 's of omega (Table 5)')
    push_pairs: str = option('rolled', "the push term's goals: 'rolled' (s' of the previous row in the batch, as QRL's "
                             "reference code) or 'sampled' (B more dataset states; runs before 2026-12-07)",
                             PUSH_PAIRS)
    lambda_init: float = option(1.0, 'initial Lagrange multiplier')
    lr_lambda: float = option(1e-2, 'multiplier learning rate')
    # policies (paper section 4.4, Appendix 10)
    pi_hidden: tuple[int, ...] = option((256, 256, 256), 'policy MLP widths (paper: 3 x 512)')
    const_std: bool = option(True, "unit std as in OGBench's actors (KL = squared mean difference / 2)")
    lr_policy: float = option(3e-4, 'policy learning rate')
    objective: str = option('saw', "'saw': Q-AWR target + Q-SAW main; 'awr': Q-AWR on the goal; 'bc': cloning",
                            tuple(objectives.OBJECTIVES))
    # 'egocentric' is our default: at CPU scale the ant ignores a raw goal (policy.py has the measurement)
    conditioning: str = option('egocentric', "'goal': raw goal obs (the paper); 'direction': unit x-y direction; "
                               "'egocentric': goal + that direction in the torso frame", policy.CONDITIONING)
    temperature: float = option(3.0, 'advantage temperature (beta_T = beta_M)')
    weight_clip: float = option(100.0, 'cap on exp(temperature * advantage) (SAW)')
    subgoal_offset: int = option(25, 'k: subgoal w = s_{min(t + k, cap)}')
    subgoal_cap: str = option('goal', "cap of the subgoal index: 'goal' (SAW's s_{min(t+k, goal index)}) or 'end' "
                              "(the trajectory's end; runs before 2026-11-24)", goals.SUBGOAL_CAPS)
    initializer: str = option('ogbench', "kernel init: 'ogbench' (variance scaling fan_avg uniform, policy mean "
                              "x 1e-2; the paper's) or 'lecun' (flax default; runs before 2026-11-24)", INITS)
    policy_goals: str = option('trajectory', "'trajectory': uniform over the rest of it; 'random': explore datasets",
                               POLICY_GOALS)

    def __post_init__(self):
        super().__post_init__()
        cfg_lib.check_positive_int(self, 'n_components', 'component_size', 'subgoal_offset')
        cfg_lib.check_widths(self, 'q_hidden', 'pi_hidden')
        for f in dataclasses.fields(self):
            if f.metadata.get('choices'):
                cfg_lib.check_choice(type(self).__name__, f.name, getattr(self, f.name), f.metadata['choices'])
        for name in ('lr_quasimetric', 'lr_lambda', 'lr_policy', 'temperature', 'weight_clip', 'push_scale'):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be a finite number > 0; got {v}')
        if self.lambda_init < 0 or self.epsilon < 0:
            raise ValueError('lambda_init and epsilon must be >= 0')
        if self.env is None and self.push_offset is None and self.qrl == 'paper':
            raise ValueError('push_offset must be given when env is None')

    @classmethod
    def preset(cls, name: str, **overrides) -> 'AQMConfig':
        """``paper``: Appendix 10 sizes; ``cpu``: a few minutes on a 2-core CPU; ``cpu-quick``: ``cpu`` for 1.25x the
        updates; ``cpu-long``: for 2.5x; ``cpu-giant``: ``cpu`` for 7.5x the updates; ``ci``: tests."""
        return cls(**{**presets.loop(name), **SIZES[presets.networks(name)], 'preset': name, **overrides})

    @property
    def offset(self) -> float:
        if self.push_offset is not None:
            return float(self.push_offset)
        if self.qrl == 'ogbench':
            return OGBENCH_PUSH_OFFSET
        return PUSH_OFFSETS[parse_name(self.env)[1]]

    @property
    def goal_sampling(self) -> goals.GoalSampling:
        if self.policy_goals == 'random':
            return goals.GoalSampling(p_trajectory=0.0, p_random=1.0, subgoal_offset=self.subgoal_offset,
                                      subgoal_cap=self.subgoal_cap)
        return goals.GoalSampling(p_trajectory=1.0, geometric=False, subgoal_offset=self.subgoal_offset,
                                  subgoal_cap=self.subgoal_cap)

    @classmethod
    def from_dict(cls, d: dict):
        """A saved config; a field it lacks because it was written before the field existed takes
        the value that reproduces what that run did (:data:`LEGACY`), not today's default."""
        if isinstance(d, dict):
            d = {**{k: v for k, v in LEGACY.items() if k not in d}, **d}
        return cfg_lib.from_dict(cls, d)


# the metrics the training bar shows, {metric: short name}
PROGRESS = {'qrl/d_pos_mean': 'd_pos_mean', 'qrl/d_goal_mean': 'd_goal_mean', 'qrl/lambda': 'lambda',
            'policy/main_loss': 'main_loss'}
# the sizes of each size row (aqm_mjx.presets.networks: a preset's row), beside the loop's (presets.LOOP)
SIZES = {
    'paper': dict(q_hidden=(512, 512, 512), n_components=512, component_size=1, pi_hidden=(512, 512, 512),
                  conditioning='goal'),
    # cpu: 50x fewer updates than the paper, so the quasimetric learns 3x faster (at 1e-4 its map of
    # antmaze-medium still joined keypoints across walls after 20,000 updates; RESULTS.md section 3.4)
    'cpu': dict(q_hidden=(256, 256, 256), n_components=256, component_size=1, pi_hidden=(256, 256, 256),
                lr_quasimetric=3e-4),
    'ci': dict(q_hidden=(32, 32), n_components=32, component_size=1, pi_hidden=(32, 32)),
}


@struct.dataclass
class TrainState:
    """Every array a run needs to continue exactly."""

    step: jax.Array  # int32 []
    key: jax.Array  # uint32 [2]
    q_params: Any
    q_opt: Any
    lam: jax.Array  # float32 []: lambda ('paper') or log lambda ('ogbench')
    lam_opt: Any
    pi_params: Any  # {'target': ..., 'main': ...}
    pi_opt: Any


def make(cfg: AQMConfig, obs_size: int, action_size: int) -> Learner:
    """Build the modules, optimisers and the pure update of an AQM run."""
    iqe = IQE(hidden=tuple(cfg.q_hidden), n_components=cfg.n_components, component_size=cfg.component_size,
              initializer=cfg.initializer)
    pi = policy.GaussianPolicy(action_size=action_size, hidden=tuple(cfg.pi_hidden), const_std=cfg.const_std,
                               initializer=cfg.initializer)
    q_tx = optax.adam(cfg.lr_quasimetric)
    lam_tx = optax.adam(cfg.lr_lambda)
    pi_tx = optax.adam(cfg.lr_policy)
    goal_dim = policy.goal_input_size(obs_size, cfg.conditioning)
    gs = cfg.goal_sampling
    offset, eps, temp, clip = cfg.offset, cfg.epsilon, cfg.temperature, cfg.weight_clip
    objective = objectives.OBJECTIVES[cfg.objective]
    b = cfg.batch_size

    def lam_value(raw):
        return jnp.exp(raw) if cfg.qrl == 'ogbench' else raw

    def init(key):
        k_q, k_t, k_m, k_run = jax.random.split(key, 4)
        x = jnp.zeros((1, obs_size))
        q_params = iqe.init(k_q, x, x)
        gi = jnp.zeros((1, goal_dim))
        pi_params = {'target': pi.init(k_t, x, gi), 'main': pi.init(k_m, x, gi)}
        lam = jnp.asarray(math.log(cfg.lambda_init) if cfg.qrl == 'ogbench' else cfg.lambda_init, jnp.float32)
        return TrainState(step=jnp.zeros((), jnp.int32), key=k_run, q_params=q_params, q_opt=q_tx.init(q_params),
                          lam=lam, lam_opt=lam_tx.init(lam), pi_params=pi_params, pi_opt=pi_tx.init(pi_params))

    def update(state: TrainState, ds: ds_io.Dataset):
        key, k_batch, k_rand = jax.random.split(state.key, 3)
        batch = goals.sample(ds, k_batch, b, gs)
        s, s1, w, g = batch.observations, batch.next_observations, batch.subgoals, batch.goals
        rolled = cfg.push_pairs == 'rolled'
        if not rolled:
            rand = goals.spread(ds.observations[jax.random.randint(k_rand, (b,), 0, ds.size)])
        lam = lam_value(state.lam)

        def dist_fn(qp):
            return lambda x, y: iqe.apply(qp, x, y, method=IQE.distance)

        # (A) QUASIMETRIC: one encoder pass over s, s' (and the sampled push goals): the rows with gradients
        def q_loss(qp):
            if rolled:
                zs, zs1 = jnp.split(iqe.apply(qp, jnp.concatenate([s, s1]), method=IQE.encode), 2)
                zr = jnp.roll(zs1, 1, axis=0)  # row i pushed from s_i to s'_{i-1}
            else:
                zs, zs1, zr = jnp.split(iqe.apply(qp, jnp.concatenate([s, s1, rand]), method=IQE.encode), 3)
            d_pos = dist_fn(qp)(zs, zs1)
            loss, info = qrl_loss(d_pos, dist_fn(qp)(zs, zr), lam, eps, offset, cfg.push_scale)
            return loss, (info, jax.lax.stop_gradient(zs), jax.lax.stop_gradient(zs1), jax.lax.stop_gradient(d_pos))

        (q_l, (q_info, zs, zs1, d_pos)), q_grads = jax.value_and_grad(q_loss, has_aux=True)(state.q_params)
        # Subgoals and goals only feed the policies' advantages: a forward pass, no backward through them
        zw, zg = jnp.split(iqe.apply(state.q_params, jnp.concatenate([w, g]), method=IQE.encode), 2)
        d = objectives.advantage_distances(dist_fn(state.q_params), zs, zs1, zw, zg)
        q_updates, q_opt = q_tx.update(q_grads, state.q_opt, state.q_params)
        q_params = optax.apply_updates(state.q_params, q_updates)

        # LAGRANGE MULTIPLIER: ascent on lambda * violation, with the tested lambda loss
        lam_grad, lam_info = jax.grad(lambda raw: lambda_loss(d_pos, lam_value(raw), eps), has_aux=True)(state.lam)
        lam_updates, lam_opt = lam_tx.update(lam_grad, state.lam_opt, state.lam)
        new_lam = optax.apply_updates(state.lam, lam_updates)
        if cfg.qrl == 'paper':
            new_lam = jnp.maximum(new_lam, 0.0)

        # (B) POLICIES: advantages from the quasimetric held fixed
        def run(params, goal):
            return pi.apply(params, s, policy.goal_input(s, goal, cfg.conditioning))

        (_, pi_info), pi_grads = jax.value_and_grad(
            lambda pp: objective(run, pp, batch, d, temp, clip), has_aux=True)(state.pi_params)
        pi_updates, pi_opt = pi_tx.update(pi_grads, state.pi_opt, state.pi_params)
        pi_params = optax.apply_updates(state.pi_params, pi_updates)

        metrics = {**q_info, **lam_info, **pi_info, 'qrl/loss': q_l,
                   'qrl/alpha': jax.nn.sigmoid(q_params['params']['alpha_logit']),
                   'qrl/d_subgoal_mean': jnp.mean(d['sw'])}
        new = TrainState(step=state.step + 1, key=key, q_params=q_params, q_opt=q_opt, lam=new_lam, lam_opt=lam_opt,
                         pi_params=pi_params, pi_opt=pi_opt)
        return new, metrics

    def params(state: TrainState) -> dict:
        return {'q': state.q_params, 'pi': state.pi_params}

    def encode(aux, obs):
        return iqe.apply(aux['q'], obs, method=IQE.encode)

    def dist(aux, x, y):
        return iqe.apply(aux['q'], x, y, method=IQE.distance)

    def controller(aux, obs, sub, t, key):
        del t, key  # deterministic: the main policy's mean
        return pi.apply(aux['pi']['main'], obs, policy.goal_input(obs, sub, cfg.conditioning))[0]

    def agent(aux=None) -> Agent:
        return Agent(encode, dist, controller, aux)

    return Learner(config=cfg, init=init, update=update, params=params, agent=agent,
                   modules={'quasimetric': iqe, 'policy': pi},
                   distance=Distance(encode, dist, 'its IQE quasimetric, in steps'))


EXPLORE = {'explore': {'policy_goals': 'random'}}  # paper App. 10.3: uniform random goals on explore data
METHODS = (
    Method('aqm', AQMConfig, make, {'objective': 'saw'},
           'AQM: IQE quasimetric (QRL), Q-AWR target and Q-SAW main policies', EXPLORE, PROGRESS),
    Method('aqm-awr', AQMConfig, make, {'objective': 'awr'},
           "AQM's quasimetric with a Q-AWR policy on the goal (ablation)", EXPLORE, PROGRESS),
    Method('aqm-bc', AQMConfig, make, {'objective': 'bc'},
           "AQM's quasimetric with a behaviour-cloned policy (ablation)", EXPLORE, PROGRESS),
)
