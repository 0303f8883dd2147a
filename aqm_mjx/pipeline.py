"""A whole AQM run as one pure function: train -> map -> evaluate.

    cfg = RunConfig.preset('ci', env='pointmaze-medium')
    run = make_run(cfg, env)                                         # run(key, dataset) -> dict, pure
    out = jax.jit(run)(key, dataset)                                 # one compiled program
    outs = jax.jit(jax.vmap(run, in_axes=(0, None)))(keys, dataset)  # several seeds, the dataset shared

The stages are the functions the step-by-step path (:mod:`aqm_mjx.run`) calls between its
checkpoints: :func:`aqm_mjx.learn.fit.train_scan` (the training's chunk scan), :func:`aqm_mjx.mapping
.build.build_map`, :func:`aqm_mjx.agent.rollout.make_rollout` over the episode table of
:mod:`aqm_mjx.evaluation.protocol`, and its success rates. :func:`stage_keys` splits one key the
same way for every path, so they give the same results for the same key.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp

from aqm_mjx import config as cfg_lib
from aqm_mjx import envs, presets
from aqm_mjx.agent.rollout import make_rollout
from aqm_mjx.agent.rules import AgentConfig
from aqm_mjx.data import dataset as ds_io
from aqm_mjx.evaluation import calibration
from aqm_mjx.evaluation import protocol as proto
from aqm_mjx.learn import fit, methods
from aqm_mjx.mapping.build import MapConfig, build_map, own_map

SECTIONS = presets.SECTIONS  # the sections beside train, whose fields are command-line options


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """A whole experiment (saved as JSON with its results): which method and how to train it, how
    to map, the agent's rules and the evaluation protocol."""

    method: str = 'aqm'
    train: Any = dataclasses.field(default_factory=lambda: methods.get('aqm').preset(presets.DEFAULT))
    map: MapConfig = dataclasses.field(default_factory=MapConfig)
    agent: AgentConfig = dataclasses.field(default_factory=AgentConfig)
    protocol: proto.ProtocolConfig = dataclasses.field(default_factory=proto.ProtocolConfig)

    def __post_init__(self):
        method = methods.get(self.method)
        if not isinstance(self.train, method.config):
            raise ValueError(f'RunConfig.train is a {type(self.train).__name__}; method {self.method!r} takes a '
                             f'{method.config.__name__}')

    @classmethod
    def preset(cls, name: str, method: str = 'aqm', env: Optional[str] = None, seed: int = 0,
               style: Optional[str] = None) -> 'RunConfig':
        """Preset ``name`` (``ci``, ``cpu``, ``cpu-quick``, ``cpu-long``, ``cpu-giant``, ``paper``) for ``method`` on ``env``, trained on data of
        ``style`` (the method's rules for it: AQM draws uniform random goals on ``explore`` data)."""
        over = dict(seed=seed) if env is None else dict(env=env, seed=seed)
        return cls(method=method, train=methods.get(method).preset(presets.check(name), style=style, **over),
                   map=MapConfig(**presets.section(name, 'map')), agent=AgentConfig(**presets.section(name, 'agent')),
                   protocol=proto.ProtocolConfig(**presets.section(name, 'protocol')))

    def to_dict(self) -> dict:
        return dict(method=self.method, train=self.train.to_dict(), **{s: dataclasses.asdict(getattr(self, s))
                                                                      for s in SECTIONS})

    @classmethod
    def from_dict(cls, d: dict) -> 'RunConfig':
        method = d.get('method', 'aqm')
        classes = dict(map=MapConfig, agent=AgentConfig, protocol=proto.ProtocolConfig)
        return cls(method=method, train=methods.get(method).from_dict(d['train']),
                   **{s: cfg_lib.from_dict(classes[s], d.get(s, {})) for s in SECTIONS})

    def with_overrides(self, pairs) -> 'RunConfig':
        """``['train.batch_size=64', 'map.delta=10', 'agent.kappa=0.5']`` -> a new config. A field
        name without its section is taken where it is unique (``steps=400``: ``train.steps``)."""
        by_section = {}
        for pair in pairs:
            head = pair.split('=', 1)[0]
            if '.' not in head:
                owners = [s for s in ('train',) + SECTIONS if head in cfg_lib.field_names(type(getattr(self, s)))]
                if len(owners) != 1:
                    raise ValueError(f'override {pair!r}: ' + (f'{head!r} is a field of {" and ".join(owners)}; '
                                     'name the section' if owners else f'no section has a field {head!r}') +
                                     f' (sections: train, {", ".join(SECTIONS)}; e.g. map.delta=10)')
                pair = f'{owners[0]}.{pair}'
            section, rest = pair.split('.', 1)
            if section not in ('train',) + SECTIONS:
                raise ValueError(f'override {pair!r}: unknown section {section!r}; expected train, {", ".join(SECTIONS)}')
            by_section.setdefault(section, []).append(rest)
        return dataclasses.replace(self, **{s: cfg_lib.with_overrides(getattr(self, s), p)
                                            for s, p in by_section.items()})


collect_episodes = presets.collect_episodes
collect_physics = presets.collect_physics


def stage_keys(key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(train, map, evaluation) keys of a run; every path splits the run key this way."""
    k_train, k_map, k_eval = jax.random.split(key, 3)
    return k_train, k_map, k_eval


def make_run(cfg: RunConfig, env, variants: Optional[dict] = None, progress: Optional[Callable] = None):
    """Build ``run(key, dataset) -> dict`` for ``env`` (a :class:`aqm_mjx.envs.MazeEnv`).

    The dataset's style rules live in ``cfg`` (``RunConfig.preset(..., style='explore')``, as
    ``aqm-mjx run`` builds it from the dataset's name), since the dataset arrays do not say it.

    Args:
        variants: ``{name: grid}`` layouts to evaluate on (default: the maze's layout).
        progress: optional host callback ``progress(step)`` during training.
    Returns:
        ``run(key [2], dataset: Dataset) -> dict`` with ``success [agents, layouts, tasks]`` (rates),
        ``episode_success [E]``, ``pruned [E]`` (legs overrun), ``removed [E]`` (keypoint edges cut),
        ``legs [E, MAX_LEGS, 3]`` and ``n_legs [E]`` in the
        order of ``run.episodes.table``,
        ``keypoints`` (count), ``overflow``, ``metrics`` (last chunk's means) and ``params``; with
        ``cfg.protocol.calibrate`` also ``calibration`` (the AQM row's ``kappa`` and ``patience``
        and the ``legs`` of the calibration pass, run first on the training layout).
        ``run.episodes`` describes the episodes, ``run.learner`` the method's functions.
    """
    learner = methods.get(cfg.method).make(cfg.train, env.obs_size, env.action_size)
    agent = learner.agent()  # parameters come from training, inside run
    episodes = proto.plan_episodes(env, cfg.protocol, cfg.agent.kappa, variants, plans=agent.plans,
                                   patience=cfg.agent.patience, cut_slack=cfg.agent.cut_slack,
                                   own_rule=agent.rule is not None)
    rollout = make_rollout(envs.with_physics(env, cfg.protocol.physics_preset), agent, cfg.agent, episodes.steps)
    rule = cfg.protocol.calibrate if agent.prunes else 'none'
    calibrates = agent.prunes and proto.needs_calibration(cfg.protocol)
    if calibrates:  # the calibration pass: no pruning, training layout, cells no task uses, its own key
        cal_episodes = proto.calibration_episodes(env, cfg.protocol)
        aqm_rows = episodes.table.agent == 0  # the AQM row is the first agent of the table

    def run(key, ds: ds_io.Dataset) -> dict:
        k_train, k_map, k_eval = stage_keys(key)
        # TRAIN
        state, metrics = fit.train_scan(learner, k_train, ds, progress)
        params = learner.params(state)
        # MAP: keypoints and graph from dataset states (none for a method without a quasimetric)
        if agent.mapper is not None:  # a method's own map (GAS's) from every state; trajectories of the
            # collector's length at most (env.max_episode_steps + 1 states)
            graph, count, overflow = own_map(agent, params, ds.observations, ds.traj_end, env.max_episode_steps + 1,
                                             k_map)
        elif agent.plans:
            graph, kp = build_map(agent, ds.observations, cfg.map, k_map, params)
            count, overflow = kp.count, kp.overflow
        else:
            graph, count, overflow = None, jnp.int32(0), jnp.bool_(False)
        cal = {}
        if not calibrates:
            inputs = proto.table_inputs(episodes, k_eval)
        else:  # CALIBRATE: the budgets from the legs of a no-pruning pass
            c = calibration.calibrate(rollout(params, graph, proto.table_inputs(
                cal_episodes, jax.random.fold_in(k_eval, proto.CALIBRATION_FOLD)))['legs'], cfg.protocol.false_alarm,
                stall_scale=cfg.protocol.stall_scale)
            kappa, patience = calibration.budget(c, rule, cfg.agent.kappa, cfg.agent.patience)
            budgets = calibration.row_budgets(c, cfg.agent.kappa, cfg.agent.patience)
            inputs = proto.table_inputs(episodes, k_eval, budgets=budgets)
            inputs = inputs._replace(kappa=jnp.where(aqm_rows, kappa, inputs.kappa),
                                     patience=jnp.where(aqm_rows, patience, inputs.patience))
            cal = dict(calibration=dict(kappa=kappa, patience=patience, kappa_edges=budgets['paper'][0],
                                        legs=c['legs']))
        # EVALUATE: every agent x layout x task x episode in one batch
        out = rollout(params, graph, inputs)
        success = out['success'] > 0
        rates, _ = proto.success_rates(episodes, success, out['pruned'])
        return dict(success=rates, episode_success=success, pruned=out['pruned'], removed=out['removed'],
                    legs=out['legs'], n_legs=out['n_legs'], keypoints=count, overflow=overflow, metrics=metrics,
                    params=params, **cal)

    run.episodes, run.learner = episodes, learner
    return run


def summary(run, out: dict) -> dict:
    """``{agent: {layout: {'task_T': rate, 'mean': rate}}}`` from one seed's ``out`` (host side)."""
    e = run.episodes
    return proto.format_summary(out['success'], e.agents, list(e.variants), e.task_ids)
