"""The test-time rules of the methods that plan their own way, by name: the rollout looks a rule up
here, as training looks a method up in :mod:`aqm_mjx.learn.methods`.

    planners.names()                      # ['gas', 'hilp']
    decide = planners.decide(agent)       # the Decide of agent.rule = spec('gas', ...)

A method's :class:`~aqm_mjx.interface.Agent` names its rule with :func:`aqm_mjx.interface.spec`
(``('gas', settings)``); an agent without one runs AQM's rules (:mod:`aqm_mjx.agent.rules`, with
budgets, pruning and their ablation rows), built by :func:`aqm_mjx.agent.rollout.make_decide`. Each
rule module builds a :class:`~aqm_mjx.interface.Decide` and imports nothing of the rollout, so the
imports of ``agent/`` point one way: rollout -> planners -> rule modules -> interface.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from aqm_mjx.agent import gas_rule, hilp_rule
from aqm_mjx.interface import Agent, Decide


class Planner(NamedTuple):
    """A registered test-time rule: ``make(encode, skill, **settings) -> Decide`` and what it is."""

    name: str
    make: Callable[..., Decide]
    about: str


PLANNERS = {p.name: p for p in (
    Planner('gas', gas_rule.make_decide, 'GAS: shortest paths on its own graph of dataset states, a node of the path '
            "as its skill policy's latent target"),
    Planner('hilp', hilp_rule.make_decide, 'HILP: midpoint planning over dataset states in its Hilbert space, its '
            'skill policy steered toward the planned waypoint'),
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
    return get(name).make(agent.encode, agent.skill, **dict(settings))
