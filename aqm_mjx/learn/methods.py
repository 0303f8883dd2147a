"""The method registry: a plain dict from a name to how to configure, build and train a method.

    method = methods.get('aqm')
    cfg = method.preset('cpu', env='antmaze-medium')      # a typed, frozen config
    learner = method.make(cfg, obs_size, action_size)      # init, update, params, agent

Evaluation sees only the :class:`~aqm_mjx.interface.Agent` that ``learner.agent(params)`` returns,
so a new method is an entry here (its config, presets and ``make``) and nothing else changes.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

from aqm_mjx.learn import aqm
from aqm_mjx.learn.baselines import base, crl, gcbc, gciql, gcivl, hiql, qrl, saw
from aqm_mjx.learn.learner import Learner


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
        progress: ``{metric: short name}`` of the metrics the training bar shows.
    """

    name: str
    config: type
    make: Callable[..., Learner]
    defaults: dict = dataclasses.field(default_factory=dict)
    summary: str = ''
    style_defaults: dict = dataclasses.field(default_factory=dict)
    progress: dict = dataclasses.field(default_factory=lambda: dict(base.PROGRESS))

    def preset(self, preset: str, style: Optional[str] = None, **overrides):
        """The config of preset ``preset`` with this entry's defaults, those of dataset ``style``
        (``navigate``, ``stitch``, ``explore``; None: none), then ``overrides``."""
        return self.config.preset(preset, **{**self.defaults, **self.style_defaults.get(style, {}), **overrides})

    def from_dict(self, d: dict):
        return self.config.from_dict(d)


METHODS: dict[str, Method] = {}


def register(method: Method) -> Method:
    if method.name in METHODS:
        raise ValueError(f'method {method.name!r} is already registered')
    METHODS[method.name] = method
    return method


def get(name: str) -> Method:
    if name not in METHODS:
        raise ValueError(f'unknown method {name!r}; expected one of {", ".join(METHODS)}')
    return METHODS[name]


def names() -> list[str]:
    return list(METHODS)


AQM_EXPLORE = {'explore': {'policy_goals': 'random'}}  # paper App. 10.3: uniform random goals on explore data
register(Method('aqm', aqm.AQMConfig, aqm.make, {'objective': 'saw'},
                'AQM: IQE quasimetric (QRL), Q-AWR target and Q-SAW main policies', AQM_EXPLORE, aqm.PROGRESS))
register(Method('aqm-awr', aqm.AQMConfig, aqm.make, {'objective': 'awr'},
                "AQM's quasimetric with a Q-AWR policy on the goal (ablation)", AQM_EXPLORE, aqm.PROGRESS))
register(Method('aqm-bc', aqm.AQMConfig, aqm.make, {'objective': 'bc'},
                "AQM's quasimetric with a behaviour-cloned policy (ablation)", AQM_EXPLORE, aqm.PROGRESS))
# OGBench's per-dataset settings (impls/hyperparameters.sh, antmaze-*-stitch and -explore): actor goals from
# random dataset states on data whose trajectories do not cross the maze, and the explore alphas. GCBC keeps
# its trajectory goals. SAW's public settings for these styles are not known to us: it takes HIQL's goal
# mixture (it shares HIQL's value and sampler) and keeps its alphas.
STITCH_GOALS = {'actor_p_random': 0.5, 'actor_p_trajectory': 0.5}
EXPLORE_GOALS = {'actor_p_random': 1.0, 'actor_p_trajectory': 0.0}


def _ogbench_styles(**explore) -> dict:
    return {'stitch': dict(STITCH_GOALS), 'explore': {**EXPLORE_GOALS, **explore}}


register(Method('gcbc', gcbc.GCBCConfig, gcbc.make, summary='GCBC: goal-conditioned behaviour cloning'))
register(Method('gcivl', gcivl.GCIVLConfig, gcivl.make, summary='GCIVL: implicit V-learning value, AWR actor',
                style_defaults=_ogbench_styles()))
register(Method('gciql', gciql.GCIQLConfig, gciql.make, summary='GCIQL: IQL Q and V, DDPG+BC actor',
                style_defaults=_ogbench_styles(alpha=0.01)))
register(Method('qrl', qrl.QRLConfig, qrl.make, summary="QRL (OGBench's): IQE quasimetric, latent dynamics, DDPG+BC",
                style_defaults=_ogbench_styles(alpha=0.001)))
register(Method('crl', crl.CRLConfig, crl.make, summary='CRL: contrastive critic (InfoNCE), DDPG+BC actor',
                style_defaults=_ogbench_styles(alpha=0.003)))
register(Method('hiql', hiql.HIQLConfig, hiql.make, summary='HIQL: IVL value with goal representation, high and '
                'low AWR policies', style_defaults=_ogbench_styles(high_alpha=10.0, low_alpha=10.0)))
register(Method('saw', saw.SAWConfig, saw.make, summary='SAW: IVL value, sub-policy and a flat policy bootstrapped '
                'from it', style_defaults=_ogbench_styles()))
