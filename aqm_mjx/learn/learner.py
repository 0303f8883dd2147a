"""What every method provides (the registry's contract) and the training-loop settings they share.

A :class:`Learner` is built from a method's config by ``make(config, obs_size, action_size)``:
pure ``init`` and ``update`` functions (training composes them under ``lax.scan``), ``params``
to take the evaluation parameters out of a state, and ``agent`` to turn those into the
:class:`~aqm_mjx.interface.Agent` that mapping and evaluation use. The config never rides inside a
jitted pytree: it is captured by the closures.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple, Optional

from aqm_mjx import config as cfg_lib
from aqm_mjx import presets
from aqm_mjx.envs import parse_name
from aqm_mjx.interface import Distance

option = cfg_lib.option
# the training bar's metrics of a method that names none: the baselines' losses ({metric: short name})
PROGRESS = {'value/loss': 'value', 'critic/loss': 'critic', 'actor/loss': 'actor', 'high_actor/loss': 'high',
            'low_actor/loss': 'low', 'value/lambda': 'lambda'}


class Learner(NamedTuple):
    """Pure functions of one method, built from its config.

    Attributes:
        config: the method's config (frozen dataclass, :class:`LoopConfig` fields included).
        init: ``key -> state``: a ``flax.struct`` pytree with a ``step`` (int32) and a ``key``.
        update: ``(state, dataset: Dataset) -> (state, metrics dict of scalars)``; pure, jittable.
        params: ``state -> params``, the pytree the agent reads.
        agent: ``params -> Agent`` (``None``: the functions alone, parameters bound later).
        modules: the method's flax modules by name (for tools that inspect them).
        loss: ``(params, target, batch, key) -> (loss, info)``, the summed loss ``update`` differentiates
            (the baselines; tests and the parity benchmark evaluate it on a batch of their own).
        step: ``(state, batch, key) -> (state, metrics)``, one update on a given batch, which
            ``update`` runs on the batch it samples (the baselines; the parity benchmark).
        distance: the method's value as a time-to-reach in control steps
            (:class:`~aqm_mjx.interface.Distance`, :mod:`aqm_mjx.learn.distance`), which the planners
            around any method map and plan with (``evaluate --planner aqm|ttgs``); None: no value (GCBC).
    """

    config: Any
    init: Callable
    update: Callable
    params: Callable
    agent: Callable
    modules: dict
    loss: Optional[Callable] = None
    step: Optional[Callable] = None
    distance: Optional[Distance] = None


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Training-loop settings every method shares (their defaults and presets: :data:`aqm_mjx.presets.LOOP`);
    a method's config extends it."""

    preset: str = option(presets.DEFAULT, 'the preset these values came from (recorded with every result)')
    env: Optional[str] = option('antmaze-medium', 'environment the data come from (e.g. sets AQM\'s push offset)')
    steps: int = option(presets.default('loop', 'steps'), 'gradient updates in the run')
    batch_size: int = option(presets.default('loop', 'batch_size'), 'transitions per update (paper: 1024)')
    updates_per_call: int = option(presets.default('loop', 'updates_per_call'),
                                   'updates per jitted call (lax.scan length); steps must be a multiple')
    log_every: int = option(presets.default('loop', 'log_every'),
                            'updates between metric lines (a multiple of updates_per_call)')
    checkpoint_every: int = option(presets.default('loop', 'checkpoint_every'),
                                   'updates between checkpoints (a multiple of updates_per_call)')
    keep: int = option(3, 'checkpoints kept')
    seed: int = option(0, 'initialisation seed of a training run started on its own')

    def __post_init__(self):
        cfg_lib.check_types(self)
        cfg_lib.check_positive_int(self, 'steps', 'batch_size', 'updates_per_call', 'log_every', 'checkpoint_every',
                                   'keep')
        for name in ('steps', 'log_every', 'checkpoint_every'):
            if getattr(self, name) % self.updates_per_call:
                raise ValueError(f'{name} ({getattr(self, name)}) must be a multiple of updates_per_call '
                                 f'({self.updates_per_call})')
        if self.env is not None:
            parse_name(self.env)

    @property
    def chunks(self) -> int:
        """Jitted calls (chunks of ``updates_per_call`` updates) in the run."""
        return self.steps // self.updates_per_call

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict):
        return cfg_lib.from_dict(cls, d)

    def with_overrides(self, pairs):
        return cfg_lib.with_overrides(self, pairs)


@dataclasses.dataclass(frozen=True)
class Method:
    """A registry entry.

    Attributes:
        name: what ``--method`` and ``config.json`` call it.
        config: its config class (``.preset(name, **overrides)``, ``.from_dict``, ``.to_dict``).
        make: ``(config, obs_size, action_size) -> Learner``.
        defaults: config fields this entry sets before the preset's overrides (an ablation's objective).
        summary: one line for listings.
        style_defaults: ``{dataset style: fields}`` set for data of that style (AQM on ``explore``
            data: uniform random policy goals, the paper's App. 10.3), before ``overrides``.
        progress: ``{metric: short name}`` of the metrics the training bar shows (default: the
            baselines' :data:`PROGRESS`).
    """

    name: str
    config: type
    make: Callable[..., Learner]
    defaults: dict = dataclasses.field(default_factory=dict)
    summary: str = ''
    style_defaults: dict = dataclasses.field(default_factory=dict)
    progress: dict = dataclasses.field(default_factory=lambda: dict(PROGRESS))

    def preset(self, preset: str, style: Optional[str] = None, **overrides):
        """The config of preset ``preset`` with this entry's defaults, those of dataset ``style``
        (``navigate``, ``stitch``, ``explore``; None: none), then ``overrides``."""
        return self.config.preset(preset, **{**self.defaults, **self.style_defaults.get(style, {}), **overrides})

    def from_dict(self, d: dict):
        return self.config.from_dict(d)
