"""The networks of the OGBench family of baselines, built as OGBench builds them (its
``impls/utils/networks.py`` was read, not copied): GELU MLPs with variance-scaling (fan_avg,
uniform) initialisation, LayerNorm after each hidden activation in value networks, two-head
ensembles by ``nn.vmap``, a Gaussian actor with a constant unit std whose mean layer starts at
1e-2 scale, the CRL bilinear critic and HIQL's length-normalised goal representation.

Attribute names follow OGBench's modules (``actor_net``, ``mean_net``, ``value_net``, ``phi``,
``psi``), so a parameter tree maps onto the reference agents' by renaming its top-level keys
(``benchmarks/parity/bench_parity.py``).
"""

from __future__ import annotations

from typing import Optional, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp


INITS = ('ogbench', 'lecun')


def kernel_init(init: str = 'ogbench', scale: float = 1.0):
    """Dense kernels of every network: ``'ogbench'`` variance scaling (fan_avg, uniform) at ``scale``,
    OGBench's and so the paper's (Appendix 10.1); ``'lecun'`` flax's default (LeCun normal; ``scale``
    ignored), an AQM option for comparison."""
    if init not in INITS:
        raise ValueError(f'unknown init {init!r}; expected one of {INITS}')
    return nn.initializers.variance_scaling(scale, 'fan_avg', 'uniform') if init == 'ogbench' else \
        nn.linear.default_kernel_init


def default_init(scale: float = 1.0):
    """:func:`kernel_init` ``('ogbench', scale)``: OGBench's initialiser, the baselines' networks'."""
    return kernel_init('ogbench', scale)


class MLP(nn.Module):
    """``[..., D_in] -> [..., hidden[-1]]``: Dense, then the activation (GELU, OGBench's; HILP's actor:
    ReLU) and (optionally) LayerNorm after every layer but the last (after the last too when
    ``activate_final``)."""

    hidden: Sequence[int]
    activate_final: bool = False
    layer_norm: bool = False
    activation: str = 'gelu'  # 'gelu' or 'relu'

    @nn.compact
    def __call__(self, x):
        act = {'gelu': nn.gelu, 'relu': nn.relu}[self.activation]
        for i, size in enumerate(self.hidden):
            x = nn.Dense(size, kernel_init=default_init())(x)
            if i + 1 < len(self.hidden) or self.activate_final:
                x = act(x)
                if self.layer_norm:
                    x = nn.LayerNorm()(x)
        return x


def ensemble(module_cls, n: int = 2):
    """``module_cls`` with ``n`` independent parameter sets; outputs gain a leading ``[n]``."""
    return nn.vmap(module_cls, variable_axes={'params': 0}, split_rngs={'params': True}, in_axes=None, out_axes=0,
                   axis_size=n)


class Actor(nn.Module):
    """Goal-conditioned Gaussian actor: ``(obs [..., D], goal_in [..., G]) -> (mean [..., A], log_std [..., A])``.

    The mean is unbounded (no tanh); evaluation clips it to [-1, 1]. ``const_std``: log-std 0, else
    a learned state-independent log-std clipped to [-5, 2]. ``activation``: the MLP's (:class:`MLP`).
    """

    hidden: Sequence[int]
    action_size: int
    const_std: bool = True
    final_scale: float = 1e-2
    activation: str = 'gelu'

    def setup(self):
        self.actor_net = MLP(tuple(self.hidden), activate_final=True, activation=self.activation)
        self.mean_net = nn.Dense(self.action_size, kernel_init=default_init(self.final_scale))
        if not self.const_std:
            self.log_stds = self.param('log_stds', nn.initializers.zeros, (self.action_size,))

    def __call__(self, obs, goal_in):
        mean = self.mean_net(self.actor_net(jnp.concatenate([obs, goal_in], axis=-1)))
        if self.const_std:
            return mean, jnp.zeros_like(mean)
        return mean, jnp.broadcast_to(jnp.clip(self.log_stds, -5.0, 2.0), mean.shape)


class Value(nn.Module):
    """``V(x_1, ..., x_n)`` of the concatenated inputs: ``[..., sum D_i] -> [E, ...]`` with ``E =
    heads`` (``heads=1``: no leading axis). V(s, g), Q(s, g, a) and HIQL's V(s, phi) are all this."""

    hidden: Sequence[int]
    layer_norm: bool = True
    heads: int = 2

    def setup(self):
        cls = MLP if self.heads == 1 else ensemble(MLP, self.heads)
        self.value_net = cls((*self.hidden, 1), activate_final=False, layer_norm=self.layer_norm)

    def __call__(self, *inputs):
        return self.value_net(jnp.concatenate(inputs, axis=-1))[..., 0]


class Bilinear(nn.Module):
    """CRL's critic ``phi(s, a) . psi(g) / sqrt(L)`` with two heads.

    ``(obs [B, D], goal [B, D], action [B, A] or None)`` -> ``(v [2, B], phi [2, B, L], psi [2, B, L])``.
    """

    hidden: Sequence[int]
    latent: int
    layer_norm: bool = True

    def setup(self):
        cls = ensemble(MLP, 2)
        self.phi = cls((*self.hidden, self.latent), activate_final=False, layer_norm=self.layer_norm)
        self.psi = cls((*self.hidden, self.latent), activate_final=False, layer_norm=self.layer_norm)

    def __call__(self, obs, goal, action: Optional[jax.Array] = None):
        phi = self.phi(obs if action is None else jnp.concatenate([obs, action], axis=-1))
        psi = self.psi(goal)
        return jnp.sum(phi * psi, axis=-1) / jnp.sqrt(self.latent), phi, psi


def hilbert_value(phi_s: jax.Array, phi_g: jax.Array) -> jax.Array:
    """A value as a distance in a Hilbert representation (HILP, GAS's TDR): ``-||phi(s) - phi(g)||``,
    the norm floored at 1e-3 as both references do (``-sqrt(max(|.|^2, 1e-6))``): ``[..., L] -> [...]``."""
    return -jnp.sqrt(jnp.maximum(jnp.sum(jnp.square(phi_s - phi_g), axis=-1), 1e-6))


class HilbertValue(nn.Module):
    """HILP's and GAS's value ``V_i(s, g) = -||phi_i(s) - phi_i(g)||`` with two heads.

    ``(obs [B, D], goal [B, D]) -> v [2, B]``; :meth:`phi` ``(obs [B, D]) -> [B, L]``, the first head's
    representation (the one both references plan and condition their policies with).
    """

    hidden: Sequence[int]
    latent: int
    layer_norm: bool = True

    def setup(self):
        self.phi_net = ensemble(MLP, 2)((*self.hidden, self.latent), activate_final=False, layer_norm=self.layer_norm)

    def phi(self, obs):
        return self.phi_net(obs)[0]

    def __call__(self, obs, goal):
        return hilbert_value(self.phi_net(obs), self.phi_net(goal))


def length_normalize(x: jax.Array) -> jax.Array:
    """``x`` scaled to length ``sqrt(dim)`` along the last axis. The norm is floored at 1e-6 (OGBench
    divides by it as is), so a zero vector, e.g. the representation of the all-zero input [s; g] at
    initialisation, gives 0 rather than NaN."""
    norm = jnp.sqrt(jnp.maximum(jnp.sum(jnp.square(x), axis=-1, keepdims=True), 1e-12))  # finite gradient at 0
    return x / norm * jnp.sqrt(x.shape[-1])


class GoalRep(nn.Module):
    """HIQL's subgoal representation ``phi([s; g])``: ``[..., 2 D] -> [..., rep]``, length sqrt(rep)."""

    hidden: Sequence[int]
    rep: int = 10
    layer_norm: bool = True

    @nn.compact
    def __call__(self, s_and_g):
        return length_normalize(MLP((*self.hidden, self.rep), layer_norm=self.layer_norm)(s_and_g))
