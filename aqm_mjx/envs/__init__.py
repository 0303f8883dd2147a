"""MJX maze environments: ``make('antmaze-large')``, ``make('antmaze-large', physics='fast')``,
``make('pointmaze-medium', iterations=4)``."""

from __future__ import annotations

import dataclasses

from aqm_mjx.envs import mazes, physics as physics_presets
from aqm_mjx.envs.locomaze import N_PROXIES, MazeEnv, PhysicsOptions, State

AGENTS = ('ant', 'point')
ENV_NAMES = tuple(f'{a}maze-{m}' for a in AGENTS for m in mazes.MAZE_NAMES)
_PHYSICS_FIELDS = ('integrator', 'solver', 'iterations', 'ls_iterations', 'impl', 'contact_caps', 'substeps')


def with_physics(env: MazeEnv, physics) -> MazeEnv:
    """``env`` itself when it already steps with preset ``physics``, else the same environment (name,
    episode limit, termination) built with it."""
    options = physics_presets.get(physics)
    if env.physics == options:
        return env
    return make(env.name, physics=options, max_episode_steps=env.max_episode_steps,
                terminate_at_goal=env.terminate_at_goal)


def parse_name(name: str) -> tuple[str, str]:
    """``'antmaze-large'`` (or OGBench's ``'antmaze-large-v0'``) -> ``('ant', 'large')``."""
    if not isinstance(name, str):
        raise TypeError(f'environment name must be a string, got {type(name).__name__}')
    base = name[:-3] if name.endswith('-v0') else name
    if base not in ENV_NAMES:
        raise ValueError(f'unknown environment {name!r}; expected one of {", ".join(ENV_NAMES)}')
    agent, maze = base.split('-', 1)
    return agent[: -len('maze')], maze


def make(name: str, physics='ogbench', **overrides) -> MazeEnv:
    """Build an environment by name.

    Args:
        name: ``{ant,point}maze-{arena,medium,large,giant,teleport}``.
        physics: a physics preset of :mod:`aqm_mjx.envs.physics` (``'ogbench'``, ``'fast'``, a row of
            the fidelity study) or a ``PhysicsOptions``.
        **overrides: physics options on top of the preset (``integrator``, ``solver``, ``iterations``,
            ``ls_iterations``, ``impl``, ``contact_caps``, ``substeps``), ``max_episode_steps`` and
            ``terminate_at_goal``.
    """
    agent, maze = parse_name(name)
    episode = ('max_episode_steps', 'terminate_at_goal')
    unknown = set(overrides) - set(_PHYSICS_FIELDS) - set(episode)
    if unknown:
        raise TypeError(f'unknown option(s) {sorted(unknown)} for make({name!r}); '
                        f'expected {sorted(_PHYSICS_FIELDS) + list(episode)}')
    options = dataclasses.replace(physics_presets.get(physics),
                                  **{k: v for k, v in overrides.items() if k in _PHYSICS_FIELDS})
    return MazeEnv(agent, maze, options, **{k: v for k, v in overrides.items() if k in episode})


__all__ = ['make', 'with_physics', 'physics_presets', 'parse_name', 'ENV_NAMES', 'MazeEnv', 'PhysicsOptions', 'State', 'N_PROXIES', 'mazes']
