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
    """

    encode: Callable
    dist: Callable
    controller: Callable
    aux: Any = None

    @property
    def plans(self) -> bool:
        """Whether the agent has a quasimetric to map and plan with."""
        return self.dist is not None

    def bind(self, aux: Any) -> 'Agent':
        """The same functions with parameters ``aux``."""
        return self._replace(aux=aux)
