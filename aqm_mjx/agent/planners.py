"""The planners an agent can run, by name: the rollout looks a rule up here, as training looks a
method up in :mod:`aqm_mjx.learn.methods`, and :func:`around` puts a planner around any method.

    planners.names()                      # ['gas', 'hilp', 'ttgs']: rules with a map of their own
    decide = planners.decide(agent)       # the Decide of agent.rule = spec('ttgs', ...)
    agent = planners.around(agent, distance, 'aqm')   # AQM's map and rules on a method's distance

A method's :class:`~aqm_mjx.interface.Agent` names its rule with :func:`aqm_mjx.interface.spec`
(``('gas', settings)``); an agent without one runs AQM's rules (:mod:`aqm_mjx.agent.rules`, with
budgets, pruning and their ablation rows), built by :func:`aqm_mjx.agent.rollout.make_decide`. Each
rule module builds a :class:`~aqm_mjx.interface.Decide` and imports nothing of the rollout, so the
imports of ``agent/`` point one way: rollout -> planners -> rule modules -> interface.

The planner an evaluation runs (``aqm-mjx evaluate --planner``, :data:`CHOICES`):

- ``own``: the method as it comes (AQM and QRL on AQM's map, GAS and HILP on their own, the
  others flat);
- ``flat``: the method's controller aimed at the goal, no map;
- ``aqm``: AQM's test-time machinery on the method's distance (IWE keypoints, tau edges,
  Floyd-Warshall, budgets with the calibration, pruning and replanning), subgoals handed to the
  method's own controller;
- ``ttgs``: a TTGS-style search on the same distance (:mod:`aqm_mjx.agent.ttgs_rule`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Optional

from aqm_mjx.agent import gas_rule, hilp_rule, ttgs_rule
from aqm_mjx.interface import Agent, Decide, Distance, spec

CHOICES = ('own', 'flat', 'aqm', 'ttgs')


class Planner(NamedTuple):
    """A registered test-time rule: ``make(agent, **settings) -> Decide`` and what it is."""

    name: str
    make: Callable[..., Decide]
    about: str


PLANNERS = {p.name: p for p in (
    Planner('gas', lambda agent, **kw: gas_rule.make_decide(agent.encode, agent.skill, **kw),
            "GAS: shortest paths on its own graph of dataset states, a node of the path as its skill policy's latent "
            'target'),
    Planner('hilp', lambda agent, **kw: hilp_rule.make_decide(agent.encode, agent.skill, **kw),
            'HILP: midpoint planning over dataset states in its Hilbert space, its skill policy steered toward the '
            'planned waypoint'),
    Planner('ttgs', ttgs_rule.make_decide,
            'TTGS: Dijkstra once per episode on a dense map of random dataset states (soft penalty past tau), the '
            'farthest path point within T as the subgoal of the method\'s own controller'),
)}


def names() -> list[str]:
    """The registered rules."""
    return list(PLANNERS)


def get(name: str) -> Planner:
    """The rule ``name``, or a ValueError that lists them."""
    if name not in PLANNERS:
        raise ValueError(f'unknown test-time rule {name!r}; registered: {", ".join(PLANNERS)}')
    return PLANNERS[name]


def decide(agent: Agent) -> Decide:
    """The :class:`~aqm_mjx.interface.Decide` of ``agent``'s own rule (``agent.rule``, a spec)."""
    if agent.rule is None:
        raise ValueError('this agent names no rule of its own: it runs AQM\'s (aqm_mjx.agent.rollout.make_decide)')
    name, settings = agent.rule
    return get(name).make(agent, **dict(settings))


def around(agent: Agent, distance: Optional[Distance], planner: str, method: str = 'this method',
           ttgs: Optional[dict] = None) -> Agent:
    """``agent`` (a method's own, parameters bound or not) with ``planner`` (:data:`CHOICES`) around it.

    Args:
        distance: the method's value in steps (``Learner.distance``); needed by ``aqm`` and ``ttgs``.
        method: its name, for errors.
        ttgs: ``nodes``, ``tau`` (the map's), ``horizon``, ``window`` (the rule's) for ``ttgs``.
    Returns:
        the :class:`~aqm_mjx.interface.Agent` to map and evaluate: ``flat`` drops every map and rule,
        ``aqm`` plans with AQM's rules on ``distance`` (no rule or map of the method's own), ``ttgs``
        names the TTGS map and rule.
    """
    if planner not in CHOICES:
        raise ValueError(f'unknown planner {planner!r}; choose one of {", ".join(CHOICES)}')
    if planner == 'own':
        return agent
    if planner == 'flat':
        return agent._replace(encode=None, dist=None, rule=None, mapper=None, skill=None)
    if distance is None:
        raise ValueError(f'{method} has no value to plan with (no distance in steps): --planner {planner} needs one; '
                         'run it flat')
    agent = agent._replace(encode=distance.encode, dist=distance.dist, rule=None, mapper=None, skill=None)
    if planner == 'aqm':
        return agent
    t = dict(ttgs or {})
    return agent._replace(rule=spec('ttgs', horizon=float(t['horizon']), window=int(t['window'])),
                          mapper=spec('ttgs', nodes=int(t['nodes']), tau=float(t['tau'])))
