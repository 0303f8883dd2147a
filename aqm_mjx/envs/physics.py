"""Named physics settings of the MJX environments: OGBench's, and the rows of the fidelity study.

    envs.make('antmaze-medium', physics='fast')       # aqm-mjx ... --physics-preset fast

Every name is a row of the study (``benchmarks/experiments/physics_fidelity.py``, RESULTS 7.6): the
same control step (0.1 s) with another integrator, dt or constraint solve. ``'ogbench'`` is
OGBench's physics (RK4, dt 0.02, 5 substeps, Newton 100 iterations / 50 line search) and stays the
default everywhere. ``'fast'`` is the study's choice (Newton 4/8): the fastest row whose closed-loop
success on the shipped model lies inside the OGBench backend's interval on the unchanged maze and on
every closure (Newton 2/4, 1.4x faster again, lies above it on two layouts), 2.2x the whole agent's
steps/s on a CPU, RESULTS 7.6. A setting outside this list is
refused: its fidelity was never measured.
"""

from __future__ import annotations

from typing import Optional

from aqm_mjx.envs.locomaze import PhysicsOptions

OGBENCH = 'ogbench'
FAST = 'fast'
#: The study's rows, slowest and most faithful first. RK4 keeps OGBench's 5 substeps except in 'rk4-x4':
#: fewer (dt 0.033, 0.05) slow or flip the trotting ant in MuJoCo's C library too; Euler and implicitfast
#: do not keep the trot at any dt tried (RESULTS 7.6).
STUDY = {
    OGBENCH: PhysicsOptions(),
    'newton-10': PhysicsOptions(iterations=10, ls_iterations=10),
    'newton-4': PhysicsOptions(iterations=4, ls_iterations=8),
    'newton-2': PhysicsOptions(iterations=2, ls_iterations=4),
    'newton-1': PhysicsOptions(iterations=1, ls_iterations=4),
    'newton-1-ls1': PhysicsOptions(iterations=1, ls_iterations=1),
    'newton-1-caps8': PhysicsOptions(iterations=1, ls_iterations=4, contact_caps=(8, 16)),
    'newton-1-ls1-caps8': PhysicsOptions(iterations=1, ls_iterations=1, contact_caps=(8, 16)),
    'rk4-x4': PhysicsOptions(substeps=4, iterations=1, ls_iterations=4),
    'euler': PhysicsOptions(integrator='euler', iterations=1, ls_iterations=4),
    'implicitfast': PhysicsOptions(integrator='implicitfast', iterations=1, ls_iterations=4),
}
#: The row ``'fast'`` stands for: the fastest inside the reference's intervals (RESULTS 7.6; not the default).
FAST_ROW = 'newton-4'
PRESETS = {**STUDY, FAST: STUDY[FAST_ROW]}
NAMES = tuple(PRESETS)


def get(name) -> PhysicsOptions:
    """The settings of preset ``name`` (one of :data:`NAMES`); a ``PhysicsOptions`` passes through."""
    if isinstance(name, PhysicsOptions):
        return name
    if name not in PRESETS:
        raise ValueError(f'unknown physics preset {name!r}; expected one of {", ".join(NAMES)} '
                         '(the fidelity study\'s rows, RESULTS 7.6)')
    return PRESETS[name]


def name_of(options: PhysicsOptions) -> Optional[str]:
    """The preset name of ``options`` (``'fast'`` before the row it stands for), or None."""
    if options == PRESETS[FAST]:
        return FAST
    return next((k for k, v in PRESETS.items() if v == options), None)


def describe(name) -> str:
    """One line: ``'fast (rk4, 5 x dt 0.02, newton 2/4, caps (12, 24), jax)'``."""
    p = get(name)
    dt = 0.1 / p.substeps
    label = name if isinstance(name, str) else (name_of(p) or 'custom')
    return (f'{label} ({p.integrator}, {p.substeps} x dt {dt:.3g}, {p.solver} {p.iterations}/{p.ls_iterations}, '
            f'caps {p.contact_caps}, {p.impl})')


__all__ = ['OGBENCH', 'FAST', 'FAST_ROW', 'STUDY', 'PRESETS', 'NAMES', 'get', 'name_of', 'describe']
