"""The method registry: a name -> how to configure, build and train a method, found in the method files.

    method = methods.get('aqm')
    cfg = method.preset('cpu', env='antmaze-medium')      # a typed, frozen config
    learner = method.make(cfg, obs_size, action_size)      # init, update, params, agent

A method is one file: :mod:`aqm_mjx.learn.aqm` or a module of :mod:`aqm_mjx.learn.baselines` that
declares ``METHODS``, a tuple of :class:`~aqm_mjx.learn.learner.Method` entries (its config, presets,
per-style defaults, progress metrics and ``make``). This module imports those files and registers
what they declare; nothing else changes when a file is added. Evaluation sees only the
:class:`~aqm_mjx.interface.Agent` that ``learner.agent(params)`` returns.
"""

from __future__ import annotations

import importlib
import pkgutil

from aqm_mjx.learn import baselines
from aqm_mjx.learn.learner import Method

METHODS: dict[str, Method] = {}
METHOD_MODULES = ('aqm_mjx.learn.aqm',) + tuple(  # AQM's file, then every baseline's (base holds no method)
    f'{baselines.__name__}.{m.name}' for m in sorted(pkgutil.iter_modules(baselines.__path__), key=lambda m: m.name)
    if m.name != 'base')


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


def discover(modules=METHOD_MODULES) -> None:
    """Register the ``METHODS`` of every module in ``modules`` (import paths); a module without
    ``METHODS`` is an error that names it."""
    for name in modules:
        module = importlib.import_module(name)
        if not hasattr(module, 'METHODS'):
            raise ValueError(f'method file {name} declares no METHODS (a tuple of learner.Method)')
        for method in module.METHODS:
            register(method)


discover()
