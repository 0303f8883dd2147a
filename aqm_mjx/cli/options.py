"""The ``aqm-mjx`` options: one subcommand per job. The options of the map, agent and protocol
sections are built from the fields of their configs (help, choices and types included); every default
comes from :mod:`aqm_mjx.presets` or a config class. The lists come from :mod:`aqm_mjx.cli.catalog`,
so that building the parser imports no JAX: ``--help`` and a wrong argument answer at once.
"""

from __future__ import annotations

import argparse

from aqm_mjx import presets
from aqm_mjx.cli import catalog, commands


class Parser(argparse.ArgumentParser):
    """argparse's parser, whose errors are one line naming the problem and where the options are
    listed (instead of the whole usage first)."""

    def error(self, message):
        self.exit(2, f'{self.prog}: error: {message} (see {self.prog} --help)\n')


def section_options(p: argparse.ArgumentParser, sections: dict) -> None:
    """One option per field of the map, agent and protocol configs (``--max-keypoints``), taken as
    text and parsed by the config: unset options keep the preset's value."""
    for section, entry in sections.items():
        g = p.add_argument_group(f'{section} ({entry["cls"]}; default: the preset\'s)')
        for f in entry['fields']:
            kw = dict(dest=f'{section}.{f["name"]}', default=None, help=f['help'])
            if f['choices']:
                kw['choices'] = list(f['choices'])
                if '' in kw['choices']:  # an empty choice ('': the default) reads as '{,mjx,ogbench}' in help
                    kw['metavar'] = '{' + ','.join(c for c in kw['choices'] if c) + '}'
            if f['many']:
                kw['nargs'] = '*'
            g.add_argument('--' + f['name'].replace('_', '-'), **kw)


def process_options(p: argparse.ArgumentParser) -> None:
    """The options of several processes (JAX's multi-controller runtime, :mod:`aqm_mjx.processes`)."""
    g = p.add_argument_group('several processes (every process runs the same command with its own --process-id)')
    g.add_argument('--coordinator', default=None, metavar='HOST:PORT',
                   help="process 0's address, the same on every process (e.g. 127.0.0.1:12355 on one machine)")
    g.add_argument('--num-processes', type=int, default=None, metavar='N', help='processes taking part')
    g.add_argument('--process-id', type=int, default=None, metavar='I', help="this process's id, 0 .. N-1")
    g.add_argument('--distributed', action='store_true',
                   help='several processes, their addresses read from the cluster (SLURM, Open MPI, ...) by JAX')


def build_parser() -> argparse.ArgumentParser:
    """The ``aqm-mjx`` command line: one subcommand per job, each with its ``fn``."""
    import aqm_mjx  # pylint: disable=import-outside-toplevel

    known = catalog.load()
    method_names, physics_names = known['methods'], known['physics']
    p = Parser(prog='aqm-mjx', description='Adaptive Quasimetric Mapping on MuJoCo MJX.')
    p.add_argument('--version', action='version', version=f'aqm-mjx {aqm_mjx.__version__}')
    sub = p.add_subparsers(dest='cmd', required=True)
    r = sub.add_parser(
        'run', help='the whole pipeline: collect (or --dataset) -> train -> keypoints -> evaluate',
        description='Collect a navigate dataset in MJX (or use --dataset), train a method, select keypoints, and '
                    'evaluate AQM and its ablations with OGBench\'s protocol. Each stage shows its progress; '
                    'training checkpoints, so re-running the same command after an interrupt resumes. Writes '
                    'OUT/run.json, OUT/summary.json and OUT/eval/*.png. --one-program runs training, keypoints '
                    'and evaluation as one jitted program, vmapped over --seeds.')
    r.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    r.add_argument('--method', default='aqm', choices=method_names, help='registered method (aqm-mjx methods)')
    r.add_argument('--preset', default=presets.DEFAULT, choices=presets.names(),
                   help='every default of the run: cpu (minutes on a 2-core CPU: 100 MJX episodes, 20,000 '
                        'updates), cpu-quick (400 episodes collected on the host, 25,000 updates: replanning not '
                        'reliable at this scale), cpu-long (the default: the same data, 50,000 updates; antmaze-medium '
                        'in 10 min on a 2-core CPU), '
                        'cpu-giant (antmaze-giant in under 2 h: 400 episodes of 2,001 '
                        'states, 150,000 updates, delta 12), paper (the paper\'s sizes; for a GPU), ci (the wiring in a few minutes '
                        'of compiling on a CPU, for tests; its success rates mean nothing)')
    r.add_argument('--set', action='append', metavar='SECTION.FIELD=VALUE',
                   help='override any config field, e.g. --set train.batch_size=512 --set map.delta=10 (a field '
                        'name alone where it is unique: --set steps=400); repeatable')
    r.add_argument('--out', default=None, help='run folder (default runs/ENV)')
    r.add_argument('--dataset', default=None, help='an OGBench-format .npz to train on instead of collecting')
    r.add_argument('--collect-episodes', type=int, default=None,
                   help="navigate episodes to collect (1001 states each, 2001 on giant; default: the preset's: 100, "
                        "400 for cpu-quick, cpu-long and cpu-giant, 4 for ci)")
    r.add_argument('--collect-batch', type=int, default=55, help='episodes collected side by side')
    r.add_argument('--collect-physics', default=None, choices=['mjx', 'mujoco'],
                   help="physics of the collection: 'mjx', or 'mujoco' (MuJoCo on the host, 6-8x faster on a CPU); "
                        "default the preset's: mujoco for cpu-quick and cpu-long, mjx otherwise (and for "
                        'antmaze-teleport)')
    r.add_argument('--shift', default='base', help="evaluation layout: base, all, closures, a variant (close-I-J), or several joined by commas")
    r.add_argument('--seed', type=int, default=0, help='run seed: PRNGKey(seed) is split into train, map, evaluation')
    r.add_argument('--one-program', action='store_true',
                   help='train, select keypoints and evaluate as one jitted program (no checkpoints)')
    r.add_argument('--seeds', type=int, default=1, help='with --one-program: seeds vmapped in the one program')
    section_options(r, known['sections'])
    process_options(r)  # several processes: process 0 collects and writes, one data-parallel training, MJX evaluation
    r.set_defaults(fn=commands.cmd_run)
    e = sub.add_parser('envs', help='list the environments and their evaluation tasks')
    e.set_defaults(fn=commands.cmd_envs)
    m = sub.add_parser('methods', help='list the registered methods')
    m.set_defaults(fn=commands.cmd_methods)
    d = sub.add_parser('render', help='draw a maze with its evaluation tasks (or keypoint maps) as a PNG')
    d.add_argument('--env', default='antmaze-medium')
    d.add_argument('--out', default='maze.png')
    d.add_argument('--deltas', type=float, nargs='*', default=None,
                   help='draw IWE keypoint maps for these delta values: with --checkpoint in the learned '
                        "quasimetric's units (default the preset's), else in metres with the exact maze distance")
    d.add_argument('--checkpoint', default=None, help="draw a trained run's map (built as its evaluation builds it)")
    d.add_argument('--dataset', default=None, help="with --checkpoint: its data (default: config.json's)")
    d.set_defaults(fn=commands.cmd_render)
    c = sub.add_parser(
        'collect', help='collect an OGBench-format dataset in MJX (or host MuJoCo) with the scripted expert',
        description='Collect a dataset with OGBench\'s recipe: the scripted ant trot (or the point agent\'s '
                    'direct move) steered along BFS waypoints, run in MJX (or, with --physics mujoco, in MuJoCo '
                    'on the host), written as OGBench .npz plus the -val twin (a tenth as many episodes), a PNG of '
                    'some trajectories and a JSON summary.')
    c.add_argument('--env', default='antmaze-medium', help='environment, e.g. antmaze-medium, antmaze-large, pointmaze-medium')
    c.add_argument('--style', default='navigate', choices=['navigate', 'stitch', 'explore'],
                   help='navigate: a new junction-cell goal each time one is reached (noise 0.2); stitch: a goal '
                        'exactly 4 BFS cells away, 201-state episodes; explore: a random direction redrawn '
                        'every 10 steps (noise 1.0)')
    c.add_argument('--episodes', type=int, default=None,
                   help="training episodes (default OGBench's: 1000 navigate, 500 giant navigate, 5000 stitch, "
                        '10000 explore); validation adds a tenth')
    c.add_argument('--steps', type=int, default=None,
                   help="states per episode (default OGBench's: 1001 navigate, 2001 giant, 201 stitch, 501 explore)")
    c.add_argument('--noise', type=float, default=None, help='Gaussian action noise (default 0.2, explore 1.0)')
    c.add_argument('--batch', type=int, default=64,
                   help='episodes simulated side by side (CPU: 64 to 256; GPU: thousands)')
    c.add_argument('--seed', type=int, default=0, help='random seed (episode e uses fold_in(seed, e))')
    c.add_argument('--layout', default='base',
                   help="walls of the data: 'base' or a shifted layout (close-I-J, open-I-J: the names of evaluate --shift)")
    c.add_argument('--physics', default='mjx', choices=['mjx', 'mujoco'],
                   help="mjx: each chunk as one jitted MJX program (any device); mujoco: MuJoCo's C library on "
                        "the host with OGBench's static walls, several times faster on a CPU (other trajectories "
                        "than MJX's; not for antmaze-teleport)")
    c.add_argument('--physics-preset', default='ogbench', choices=physics_names,
                   help="the physics settings of either: 'ogbench' (OGBench's: RK4, Newton 100/50), 'fast' (Newton "
                        '4/8, RESULTS 7.6) or another row of the fidelity study')
    c.add_argument('--iterations', type=int, default=None,
                   help="MJX solver iterations (default MuJoCo's: 100); fewer trade fidelity for speed")
    c.add_argument('--ls-iterations', type=int, default=None, help="MJX line-search iterations (default MuJoCo's: 50)")
    c.add_argument('--out', required=True, help='output .npz (the -val twin, .png and .json go beside it)')
    c.add_argument('--overwrite', action='store_true', help='replace existing output files')
    process_options(c)  # several processes: chunk i on process i mod N, process 0 writes the files
    c.set_defaults(fn=commands.cmd_collect)
    t = sub.add_parser('train', help='train a method on a dataset (Orbax checkpoints)',
                       description='Train a registered method (default AQM: quasimetric IQE + QRL, Q-AWR target and '
                                   'Q-SAW main policies) on an OGBench-format .npz. Writes OUT/config.json, '
                                   'OUT/metrics.jsonl (JSON lines) and Orbax checkpoints in OUT/checkpoints.')
    t.add_argument('--dataset', required=True, help='OGBench .npz (e.g. antmaze-large-navigate-v0.npz)')
    t.add_argument('--env', default=None,
                   help='environment; inferred from a file name such as antmaze-large-navigate-v0.npz when omitted')
    t.add_argument('--method', default=None, choices=method_names,
                   help='registered method (aqm-mjx methods; default aqm)')
    t.add_argument('--preset', default=None, choices=presets.names(),
                   help='cpu: minutes on a 2-core CPU; cpu-quick: 25,000 updates; cpu-long: 50,000; cpu-giant: 150,000; '
                        'paper: Appendix 10 sizes (3x512, batch 1024, 1e6 updates); '
                        f'ci: smoke tests (default {presets.DEFAULT})')
    t.add_argument('--set', action='append', metavar='FIELD=VALUE',
                   help='override a training config field, e.g. --set batch_size=512 --set q_hidden=512,512 (repeatable)')
    t.add_argument('--steps', type=int, default=None, help='total updates (overrides the preset; extends a resumed run)')
    t.add_argument('--seed', type=int, default=None, help='initialisation seed (default 0)')
    t.add_argument('--out', required=True, help='run folder')
    t.add_argument('--resume', action='store_true',
                   help='continue the run in --out from its newest readable checkpoint with its saved config: '
                        'other options must agree with it (--steps may extend it), and the dataset must be the '
                        'one it was trained on (by fingerprint)')
    process_options(t)  # several processes: one run, each batch split over every process's devices
    t.set_defaults(fn=commands.cmd_train)
    v = sub.add_parser(
        'evaluate', help='evaluate a trained model: OGBench protocol, ablations and shifts in one batch',
        description='OGBench protocol: every task, --episodes each, deterministic actions clipped to [-1, 1], '
                    'success at the last step. The AQM agent, its ablations and every shifted layout run as rows '
                    'of one batch, --envs environments per jitted call, sharded over all devices. Defaults: the '
                    'run preset of the checkpoint\'s training preset (--preset to choose another). Writes '
                    'OUT/results.json, success.png, trajectories.png and, with several layouts, heatmap.png.')
    v.add_argument('--checkpoint', required=True, action='append',
                   help='run folder written by `aqm-mjx train` (or RUN/train); repeat it to put several checkpoints '
                        '(any methods, one environment) on the same episodes')
    v.add_argument('--dataset', default=None, help='states to select keypoints from (default: the training dataset)')
    v.add_argument('--shift', default='base',
                   help="layout: 'base', 'all' (the maze's shift suite), 'closures' (base and the suite's closed "
                        "corridors), one variant such as close-3-3, or several joined by commas")
    v.add_argument('--preset', default=None, choices=presets.names(),
                   help="map, agent and protocol defaults (default: the checkpoint's training preset)")
    v.add_argument('--set', action='append', metavar='SECTION.FIELD=VALUE',
                   help='override a map, agent or protocol field, e.g. --set agent.kappa=0.5 (repeatable)')
    v.add_argument('--seed', type=int, default=0,
                   help='PRNGKey(seed) split as in `aqm-mjx run`: the same seed gives the same map and episodes')
    v.add_argument('--out', default=None, help='output folder (default CHECKPOINT/eval; with several checkpoints '
                                               "the first one's parent/comparison; for a shipped or exported "
                                               'checkpoint, which is only read, runs/eval/NAME). Never a '
                                               'comparison, run or training folder, nor inside a checkpoint but '
                                               'beside its checkpoints/')
    process_options(v)
    section_options(v, known['sections'])
    v.set_defaults(fn=commands.cmd_evaluate)
    k = sub.add_parser(
        'compare', help='several methods x seeds on the same data and episodes: table and bar chart',
        description='Collect (or --dataset) once, train every method with --seeds seeds (vmapped in one program '
                    'per method), evaluate every checkpoint on the same episodes, and write OUT/results.json, '
                    'OUT/table.md and OUT/success.png: per-method mean success with 95% intervals over seeds '
                    'and over episodes. Re-running the same command after an interrupt resumes: finished methods '
                    'are not trained or evaluated again.')
    k.add_argument('--env', default='antmaze-medium', help='environment name (see `aqm-mjx envs`)')
    k.add_argument('--methods', nargs='+', default=list(known['compare_methods']), choices=method_names,
                   metavar='METHOD', help=f'registered methods (default: {" ".join(known["compare_methods"])})')
    k.add_argument('--seeds', type=int, default=2, help='training seeds per method (vmapped)')
    k.add_argument('--seed', type=int, default=0, help='the first seed: seeds are SEED, SEED+1, ...')
    k.add_argument('--eval-seed', type=int, default=0, help='PRNGKey of the map and the episodes, shared by all')
    k.add_argument('--preset', default=presets.DEFAULT, choices=presets.names(), help='every default of each method\'s run')
    k.add_argument('--set', action='append', metavar='[METHOD:]SECTION.FIELD=VALUE',
                   help='override a field for every method (--set steps=4000 --set protocol.episodes=10), or '
                        'for one (--set gciql:alpha=0.1); repeatable')
    k.add_argument('--dataset', default=None, help='an OGBench-format .npz instead of collecting')
    k.add_argument('--style', default='navigate', choices=['navigate', 'stitch', 'explore'],
                   help='the dataset to collect (taken from the file name with --dataset)')
    k.add_argument('--collect-episodes', type=int, default=None,
                   help="episodes to collect (default: the preset's, 100, or 400 for cpu-quick, cpu-long and cpu-giant)")
    k.add_argument('--collect-batch', type=int, default=55, help='episodes collected side by side')
    k.add_argument('--collect-physics', default=None, choices=['mjx', 'mujoco'],
                   help="physics of the collection (default the preset's: mujoco for cpu-quick and cpu-long, mjx "
                        'otherwise)')
    k.add_argument('--shift', default='base', help="evaluation layout: base, all, closures, a variant (close-I-J), or several joined by commas")
    k.add_argument('--backend', default=None, choices=['mjx', 'ogbench'],
                   help="physics of the evaluation: 'mjx' (default) or 'ogbench' (OGBench's own environments on "
                        'the host; same as --set protocol.backend=ogbench)')
    k.add_argument('--physics-preset', default=None, choices=physics_names,
                   help="physics of the collection and of the MJX evaluation: 'ogbench' (default) or 'fast' (Newton "
                        '4/8, RESULTS 7.6); same as --set protocol.physics_preset=NAME')
    k.add_argument('--workers', type=int, default=None, help="with --backend ogbench: processes stepping the "
                                                             'environments (default 0: this process)')
    around = [c for f in known['sections']['agent']['fields'] if f['name'] == 'planner' for c in f['choices'] if c != 'own']
    k.add_argument('--planners', nargs='+', default=[], choices=around, metavar='PLANNER',
                   help="each method's checkpoints also evaluated under these planners on the same episodes, as rows "
                        "METHOD+PLANNER: 'flat' (no map), 'aqm' (AQM's map, budgets and pruning on its distance), "
                        "'ttgs' (a TTGS-style search on it); --set agent.ttgs_tau=12 etc. for its settings")
    k.add_argument('--out', default=None, help='comparison folder (default runs/compare-ENV-STYLE)')
    process_options(k)
    k.set_defaults(fn=commands.cmd_compare)
    g = sub.add_parser(
        'merge', help='one table from several compare folders on the same data and episodes',
        description='Put the rows of finished `aqm-mjx compare` folders into one table (OUT/results.json, '
                    'OUT/table.md, OUT/success.png), after checking that they share the data (SHA-256), seeds, '
                    'episode key, layout, tasks, episodes and the overrides given to every method. Each method '
                    'comes from one folder; the folders are only read.')
    g.add_argument('folders', nargs='+', metavar='FOLDER', help='comparison folders (aqm-mjx compare --out)')
    g.add_argument('--out', required=True, help='folder of the merged table (not one of the comparisons)')
    g.set_defaults(fn=commands.cmd_merge)
    x = sub.add_parser(
        'export', help='a trained run folder made small enough to ship (newest checkpoint and its map states)',
        description='Copy a run folder\'s newest checkpoint, config.json, metrics.jsonl and curves.png into OUT, '
                    'with OUT/map_states.npz: the training states that the map of `aqm-mjx evaluate --seed SEED` '
                    'draws as candidates, so that `aqm-mjx evaluate --checkpoint OUT` builds the same map without '
                    'the dataset. OUT/data.json keeps the training data\'s fingerprint. Keypoint maps only.')
    x.add_argument('--checkpoint', required=True, help='run folder (aqm-mjx train / run / compare)')
    x.add_argument('--dataset', default=None, help="the run's training data (default: the path config.json records)")
    x.add_argument('--seed', type=int, default=0, help='the evaluation seed whose map the states reproduce')
    x.add_argument('--out', required=True, help='a new (or empty) folder, e.g. checkpoints/NAME')
    x.set_defaults(fn=commands.cmd_export)
    return p
