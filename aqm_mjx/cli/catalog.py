"""What the command line lists, without importing the package's JAX side: the registered methods
(and what each is), ``compare``'s default methods, the physics presets, the fields of the map, agent
and protocol configs (their help, choices and whether they take several values), and the lines of
``aqm-mjx envs``.

``aqm-mjx --help``, ``--version``, ``envs``, ``methods`` and every wrong argument answer from
``catalog.json`` beside this file, in a fraction of a second; a command imports JAX only once its arguments are parsed. :func:`build` reads
the same lists from the package itself; ``tests/test_cli.py`` checks that the two agree, and

    python -c 'from aqm_mjx.cli import catalog; catalog.write()'   # after a method, physics or field changes
"""

from __future__ import annotations

import dataclasses
import json
import os

PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'catalog.json')


def build() -> dict:
    """The catalog from the package (imports JAX, MuJoCo and every method)."""
    from aqm_mjx import compare, pipeline  # pylint: disable=import-outside-toplevel
    from aqm_mjx.envs import physics  # pylint: disable=import-outside-toplevel
    from aqm_mjx.learn import methods  # pylint: disable=import-outside-toplevel

    sections = {}
    for s in pipeline.SECTIONS:
        cls = type(getattr(pipeline.RunConfig(), s))
        sections[s] = dict(cls=cls.__name__, fields=[
            dict(name=f.name, help=f.metadata.get('help', ''),
                 choices=list(f.metadata['choices']) if f.metadata.get('choices') else None,
                 many=isinstance(f.default, tuple)) for f in dataclasses.fields(cls)])
    from aqm_mjx import envs  # pylint: disable=import-outside-toplevel

    env_lines = []
    for name in envs.ENV_NAMES:
        _, maze = envs.parse_name(name)
        env_lines.append(f'{name:<22} grid {envs.mazes.layout(maze).shape}  tasks: '
                         + ', '.join(f'{t.init_ij}->{t.goal_ij}' for t in envs.mazes.tasks(maze)))
    return dict(methods=list(methods.names()), summaries={m.name: m.summary for m in methods.METHODS.values()},
                compare_methods=list(compare.DEFAULT_METHODS), physics=list(physics.NAMES), sections=sections,
                envs=env_lines)


def load() -> dict:
    """The stored catalog (``catalog.json``)."""
    with open(PATH, encoding='utf-8') as f:
        return json.load(f)


def write() -> str:
    """Rewrite ``catalog.json`` from :func:`build`; returns its path."""
    text = json.dumps(build(), indent=1) + '\n'
    with open(PATH + '.tmp', 'w', encoding='utf-8') as f:
        f.write(text)
    os.replace(PATH + '.tmp', PATH)
    return PATH
