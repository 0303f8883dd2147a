"""The package's shape: stage packages whose imports point one way, no reaching into private names,
and a method registry that evaluation never looks behind."""

import ast
import pathlib

import pytest

import aqm_mjx

ROOT = pathlib.Path(aqm_mjx.__file__).parent
# Stages in data-flow order: a module may import its own stage and earlier ones only.
STAGES = ['_mjx', 'files', 'memory', 'processes', 'presets', 'config', 'interface', 'progress', 'envs', 'data', 'learn', 'mapping', 'agent', 'evaluation',
          'pipeline', 'assess', 'run', 'compare', 'cli']


def modules():
    for path in sorted(ROOT.rglob('*.py')):
        rel = path.relative_to(ROOT).with_suffix('')
        parts = [p for p in rel.parts if p != '__init__']
        yield 'aqm_mjx.' + '.'.join(parts) if parts else 'aqm_mjx', path


def stage_of(module: str) -> str:
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else ''


def imports(path):
    """``[(module imported, names taken from it)]`` of every aqm_mjx import, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith('aqm_mjx'):
            for alias in node.names:
                sub = f'{node.module}.{alias.name}'
                # `from aqm_mjx.learn import fit` imports a module; `from aqm_mjx.learn.fit import train` a name
                out.append((sub, []) if (ROOT / sub.split('.', 1)[1].replace('.', '/')).with_suffix('.py').exists()
                           or (ROOT / sub.split('.', 1)[1].replace('.', '/')).is_dir() else (node.module, [alias.name]))
        elif isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names if a.name.startswith('aqm_mjx')]
    return out


def test_every_module_belongs_to_a_stage():
    for module, _ in modules():
        if module != 'aqm_mjx':
            assert stage_of(module) in STAGES, f'{module} is in no stage of {STAGES}'


def test_no_stage_imports_a_later_one():
    bad = []
    for module, path in modules():
        if module == 'aqm_mjx':
            continue
        mine = STAGES.index(stage_of(module))
        for imported, _ in imports(path):
            if imported == 'aqm_mjx':
                continue
            theirs = STAGES.index(stage_of(imported))
            if theirs > mine:
                bad.append(f'{module} ({STAGES[mine]}) imports {imported} ({STAGES[theirs]})')
    assert not bad, '\n'.join(bad)


def test_evaluation_imports_nothing_from_training():
    for module, path in modules():
        if stage_of(module) in ('mapping', 'agent', 'evaluation'):
            learned = [m for m, _ in imports(path) if stage_of(m) == 'learn']
            assert not learned, f'{module} imports {learned}'


def test_no_module_reaches_into_another_modules_private_names():
    bad = []
    for module, path in modules():
        for imported, names in imports(path):
            bad += [f'{module}: from {imported} import {n}' for n in names if n.startswith('_')]
        tree = ast.parse(path.read_text())
        aliases = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module
                   and n.module.startswith('aqm_mjx') for a in n.names}
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and node.attr.startswith('_') and not node.attr.startswith('__')
                    and isinstance(node.value, ast.Name) and node.value.id in aliases):
                bad.append(f'{module}: {node.value.id}.{node.attr}')
    assert not bad, '\n'.join(bad)


def test_the_import_checker_sees_a_backward_import(tmp_path):
    # the checker itself: a learn module importing evaluation is reported
    fake = tmp_path / 'x.py'
    fake.write_text('from aqm_mjx.evaluation import protocol\nfrom aqm_mjx.learn.fit import _meta\n')
    got = imports(fake)
    assert ('aqm_mjx.evaluation.protocol', []) in got and ('aqm_mjx.learn.fit', ['_meta']) in got
    assert STAGES.index(stage_of('aqm_mjx.evaluation.protocol')) > STAGES.index('learn')


def test_no_module_outside_the_cli_imports_it():
    # the library never calls the command line: only the cli package's own modules import it
    for module, path in modules():
        if stage_of(module) != 'cli':
            assert all(stage_of(m) != 'cli' for m, _ in imports(path)), module


@pytest.mark.parametrize('name', ['aqm', 'aqm-awr', 'aqm-bc'])
def test_registered_methods_build_agents(name):
    import jax
    import numpy as np

    from aqm_mjx.interface import Agent
    from aqm_mjx.learn import methods

    m = methods.get(name)
    cfg = m.preset('ci', env='pointmaze-medium')
    learner = m.make(cfg, 2, 2)
    state = learner.init(jax.random.PRNGKey(0))
    agent = learner.agent(learner.params(state))
    assert isinstance(agent, Agent)
    z = agent.encode(agent.aux, np.zeros(2, np.float32))
    assert float(agent.dist(agent.aux, z, z)) == 0.0
    assert agent.controller(agent.aux, np.zeros(2), np.ones(2), 0, jax.random.PRNGKey(1)).shape == (2,)
    assert cfg.objective == {'aqm': 'saw', 'aqm-awr': 'awr', 'aqm-bc': 'bc'}[name]
    with pytest.raises(ValueError, match="unknown method 'ppo'"):
        methods.get('ppo')


def test_a_method_is_one_file_the_registry_discovers(tmp_path, monkeypatch):
    from aqm_mjx.learn import methods
    from aqm_mjx.learn.baselines import gcbc

    # every method file of the package is registered, each under the names its METHODS declare
    assert set(methods.names()) == {'aqm', 'aqm-awr', 'aqm-bc', 'crl', 'gas', 'gcbc', 'gciql', 'gcivl', 'hilp', 'hiql', 'qrl',
                                     'saw'}
    assert methods.get('hiql').style_defaults['explore']['high_alpha'] == 10.0
    # a new file declaring METHODS is all a method needs
    (tmp_path / 'my_method.py').write_text(
        'from aqm_mjx.learn.baselines import base, gcbc\n'
        "METHODS = (base.Method('gcbc-copy', gcbc.GCBCConfig, gcbc.make, summary='a copy'),)\n")
    (tmp_path / 'not_a_method.py').write_text('X = 1\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(methods, 'METHODS', dict(methods.METHODS))
    methods.discover(('my_method',))
    assert methods.get('gcbc-copy').make is gcbc.make and methods.get('gcbc-copy').preset('ci').steps == 200
    with pytest.raises(ValueError, match='already registered'):
        methods.discover(('my_method',))
    with pytest.raises(ValueError, match='not_a_method declares no METHODS'):
        methods.discover(('not_a_method',))


def test_readme_names_every_module():
    """README's layout section has a line for every module, as ``stage/module.py``."""
    readme = (ROOT.parent / 'README.md').read_text()
    missing = [str(p.relative_to(ROOT)) for _, p in modules()
               if p.name not in ('__init__.py', '_mjx.py') and f'`{p.relative_to(ROOT)}`' not in readme]
    assert not missing, f'README.md does not name {missing}'


def test_readme_is_a_front_page():
    """README stays a front page: about 200 lines, present tense (no dates, no issue numbers, no
    sessions), one install-and-run command and one test command, which .ci/run calls; the pictures
    and links it shows exist."""
    import re  # pylint: disable=import-outside-toplevel

    top = ROOT.parent
    readme = (top / 'README.md').read_text()
    assert len(readme.splitlines()) <= 210, len(readme.splitlines())
    assert not re.findall(r'\b20\d\d-\d\d-\d\d\b', readme) and not re.findall(r'\bissues? \d+', readme, re.I)
    assert 'session' not in readme.lower()
    blocks = re.findall(r'```bash\n(.*?)```', readme, re.S)
    installs = [ln for b in blocks for ln in b.splitlines() if ln.startswith('python3 -m venv')]
    assert len(installs) == 2 and installs[0].endswith('aqm-mjx run') and 'pytest' in installs[1]
    assert installs[1] in (top / '.ci' / 'run').read_text()
    for target in re.findall(r'\]\(([^)#]+)(?:#[^)]*)?\)', readme):
        if not target.startswith('http'):
            assert (top / target).exists(), target


def test_benchmarks_are_filed_and_results_cites_every_artefact():
    """benchmarks/ holds its scripts in throughput/, experiments/ and parity/, each listed in its
    README; every benchmarks/ path the docs name exists, and every artefact in benchmarks/results is
    cited by RESULTS.md (results hold only what the report cites)."""
    import re  # pylint: disable=import-outside-toplevel

    top = ROOT.parent
    bench = top / 'benchmarks'
    assert sorted(p.name for p in bench.glob('*.py')) == ['_report.py']
    listing = (bench / 'README.md').read_text()
    scripts = sorted(p for folder in ('throughput', 'experiments', 'parity') for p in (bench / folder).glob('*.py'))
    assert len(scripts) >= 25
    for p in scripts:
        assert f'`{p.name}`' in listing, f'{p.relative_to(top)} is not in benchmarks/README.md'
    docs = {name: (top / name).read_text() for name in ('README.md', 'GUIDE.md', 'RESULTS.md')}
    for name, text in docs.items():
        for cited in re.findall(r'benchmarks/[A-Za-z0-9_./-]*[A-Za-z0-9_/]', text):
            assert (top / cited).exists(), f'{name} names {cited}, which does not exist'
        for target in re.findall(r'\]\(([^)#]+)(?:#[^)]*)?\)', text):
            if not target.startswith('http'):
                assert (top / target).exists(), f'{name} links {target}'
    results = docs['RESULTS.md']
    for entry in sorted((bench / 'results').iterdir()):
        stem = entry.name if entry.is_dir() else entry.name.split('.')[0]
        assert f'benchmarks/results/{stem}' in results, f'benchmarks/results/{entry.name} is not cited by RESULTS.md'
    assert not re.findall(r'\bissues? \d+', results, re.I) and 'session' not in results.lower()


def test_no_import_circles_and_the_rollout_finds_rules_in_the_planner_registry():
    """The modules' imports (at any depth) form no circle; in agent/, the rule modules import nothing
    of the rollout (they meet it through the interface's Decide and the planners registry)."""
    from aqm_mjx.agent import planners  # pylint: disable=import-outside-toplevel

    graph = {}
    for module, path in modules():
        graph[module] = {m if m in dict(modules()) else m.rsplit('.', 1)[0] for m, _ in imports(path)} - {module}
    seen, stack, circles = set(), [], []

    def visit(m):
        if m in stack:
            circles.append(stack[stack.index(m):] + [m])
            return
        if m in seen or m not in graph:
            return
        seen.add(m)
        stack.append(m)
        for n in sorted(graph[m]):
            visit(n)
        stack.pop()

    for m in sorted(graph):
        visit(m)
    assert not [c for c in circles if any(x.startswith('aqm_mjx.agent') for x in c)], circles
    for rule in ('gas_rule', 'hilp_rule', 'ttgs_rule', 'planners'):
        assert 'aqm_mjx.agent.rollout' not in graph[f'aqm_mjx.agent.{rule}'], rule
    assert planners.names() == ['gas', 'hilp', 'ttgs']
    with pytest.raises(ValueError, match="unknown test-time rule 'astar'; registered: gas, hilp, ttgs"):
        planners.get('astar')
