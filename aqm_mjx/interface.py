"""The seam between a method and the evaluation: an :class:`Agent`.

A method (:mod:`aqm_mjx.learn.methods`) turns its trained parameters into an Agent; mapping,
planning, the rollout and the evaluation use nothing else of it. The functions take the parameter
pytree ``aux`` as an argument, so parameters are never compile-time constants: one compiled
program serves any parameters of the same shapes (seeds vmapped, checkpoints swapped).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple


class Agent(NamedTuple):
    """What planning and evaluation need from a model.

    Attributes:
        encode: ``(aux, obs [D]) -> latent [L]``, the quasimetric's input.
        dist: ``(aux, latent [L], latent [L]) -> scalar`` time-to-reach in control steps.
            ``encode`` and ``dist`` are None for a method without a quasimetric (the flat
            baselines): no map is built for it and it is evaluated as a flat controller.
        controller: ``(aux, obs [D], subgoal_obs [D], t, key) -> action [A]``.
        aux: the pytree the functions read (parameters, tables); None while not bound.
        rule: a method's own test-time rule, a :func:`spec` the agent stage resolves
            (``('gas', ...)``: :mod:`aqm_mjx.agent.gas_rule`, ``('hilp', ...)``:
            :mod:`aqm_mjx.agent.hilp_rule`); None: AQM's rules (:mod:`aqm_mjx.agent.rules`, budgets
            and pruning, with their ablation rows).
        mapper: a method's own map, a :func:`spec` the mapping stage resolves
            (:func:`aqm_mjx.mapping.build.own_map`: GAS's graph from every state, HILP's planning
            states); None: keypoints (:mod:`aqm_mjx.mapping.build`).
        skill: ``(aux, obs [D], phi_obs [L], target [L]) -> action [A]``, the latent-conditioned
            policy a rule of its own steers toward a latent target (GAS's and HILP's, each with its
            own direction: GAS's ``skill``, HILP's ``unit``); None otherwise.
    """

    encode: Callable
    dist: Callable
    controller: Callable
    aux: Any = None
    rule: Any = None
    mapper: Any = None
    skill: Any = None

    @property
    def plans(self) -> bool:
        """Whether the agent plans on a map: a quasimetric to build keypoints with, or a map of its own."""
        return self.dist is not None or self.mapper is not None

    @property
    def prunes(self) -> bool:
        """Whether the agent runs AQM's rules (budgets, pruning, calibration, their ablation rows)."""
        return self.plans and self.rule is None

    def bind(self, aux: Any) -> 'Agent':
        """The same functions with parameters ``aux``."""
        return self._replace(aux=aux)


class Distance(NamedTuple):
    """A method's goal-conditioned value read as a time-to-reach in control steps, the distance a
    planner (:mod:`aqm_mjx.agent.planners`) maps and plans with.

    ``encode(aux, obs [D]) -> z [L]``; ``dist(aux, z [L], z' [L]) -> scalar`` steps, >= 0. A method
    whose value is not factored (GCIVL's V(s, g)) encodes a state as itself (``z = obs``).
    ``about`` says how the steps are read from the method's value (docs and ``aqm-mjx methods``).
    """

    encode: Callable
    dist: Callable
    about: str = ''


class Decide(NamedTuple):
    """The agent's side of a control step, apart from the physics, so that a host-stepped backend
    (:func:`aqm_mjx.agent.rollout.make_host_rollout` over :mod:`aqm_mjx.envs.ogbench_env`) runs the same
    decisions as the MJX program. Both functions are pure and batched over a leading ``[B]``; jit them
    at the outside. A planner (:mod:`aqm_mjx.agent.planners`) makes one from an :class:`Agent`.

    ``init(aux, graph, obs [B, O], goal [B, O], inputs) -> agents``;
    ``act(aux, graph, agents, obs [B, O], goal [B, O], done [B], t, inputs) -> (actions [B, A] in
    [-1, 1], agents)``. An agent without a quasimetric keeps ``agents`` as an empty tuple.
    """

    init: Callable
    act: Callable


def spec(name: str, **settings) -> tuple:
    """A rule or map a later stage resolves by name: ``(name, ((setting, value), ...))`` (hashable)."""
    return (name, tuple(sorted(settings.items())))
