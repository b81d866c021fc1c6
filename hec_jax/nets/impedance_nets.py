"""The virtual stiffness, viscosity and inertia networks VSN, VVN, VIN (Sec. 5.1, Eqs. 50-51).

Reading implemented (docs/paper_readings.md, Sec. 3): one network per virtual-impedance parameter and per task
axis. For axis i, VSN_i, VVN_i and VIN_i take the four inputs (X_r,i, X_r,i', X_r,i'', F_int,i)
(normalised by fixed scales, since their units differ by orders of magnitude) and output K_o,i,
B_o,i and M_o,i: a diagonal virtual impedance. Each network is 4-20-20-1 with sigmoid hidden units
(Eq. 51, middle layer) and the output unit of Eq. 51,

    y = (U/2) (1 - exp(-x + theta)) / (1 + exp(-x + theta)) = (U/2) tanh((x - theta) / 2),

range (-U/2, U/2). Biases: Eq. 50 has none; we keep the usual bias in the hidden layers and in the
output unit (x = sum_j w_ij y_j + b_i); with the bias at 0 the output unit is exactly Eq. 51's.

Stability by construction (Eq. 49, strict form): with U_K = 2 K_e (1 - margin),
U_B = 2 B_e (1 - margin), U_M = 2 M_e (1 - margin), every output satisfies
K_o + K_e >= margin K_e > 0 (and likewise for B, M) for any weights, also where tanh rounds to
+-1 in floating point. The default margin is 1%.

Parameters are a pytree ``{"hidden_0": {"weight", "bias"}, ..., "output": {"weight", "bias"}}``
with a leading axis (n_axes, 3) over (axis, parameter kind), kind 0 = K (VSN), 1 = B (VVN),
2 = M (VIN). Weights are stored as Eq. 50 indexes them, w_ij from unit j to unit i: (out, in)
per network (hidden_l: (n_axes, 3, width_l, width_{l-1}); output: (n_axes, 3, width_last)).
The order matters for speed, not for the result: under ``vmap`` over tens of thousands of runs,
each with its own weights, the contraction then runs over the fastest-varying axis of the weights;
the learner's network step (forward, VJP, Eq. 52 update) ran 1.44x faster on an H100 than with
Flax's (in, out) kernels, and equally fast on the CPU (``benchmarks/nets.py``).
Initialisation is Flax's (``nn.Dense`` defaults, the output kernel drawn with
``init_output_std``); :func:`from_flax` / :func:`to_flax` convert to and from the Flax module
:class:`FlaxMlp`, which the tests use as the reference forward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

KINDS = ("k", "b", "m")  # order of the parameter-kind axis: VSN, VVN, VIN


def output_unit(x: Array, u_max: Array, theta: float) -> Array:
    """Output unit of Eq. 51: (U/2) (1 - e^{-x+theta}) / (1 + e^{-x+theta}) = (U/2) tanh((x-theta)/2)."""
    return 0.5 * u_max * jnp.tanh(0.5 * (x - theta))


def output_unit_derivative(x: Array, u_max: Array, theta: float) -> Array:
    """d(output_unit)/dx = (U/4) (1 - tanh^2((x - theta)/2))."""
    th = jnp.tanh(0.5 * (x - theta))
    return 0.25 * u_max * (1.0 - th**2)


@dataclass(frozen=True)
class NetConfig:
    """Static structure of the networks.

    Attributes:
        n_axes: task axes l (2 for the vertical plane).
        hidden: hidden layer widths (Sec. 6.2: two layers of 20).
        theta: threshold of the output unit (Eq. 51).
        input_scale: normalisation of (X_r [m], X_r' [m/s], X_r'' [m/s^2], F_int [N]).
        init_output_std: std of the initial output-layer weights (small: near-zero initial output).
        margin: stability margin of the output range (see the module docstring).
        neutral_init: start the output unit's bias at ``theta``, so that the initial networks
            output O = 0 up to the small random output weights (a neutral virtual impedance);
            False: bias 0, Eq. 51's unit as printed, whose initial output is
            (U/2) tanh(-theta/2) (about -0.05 U/2: a slightly attractive virtual spring).
    """

    n_axes: int = 2
    hidden: tuple[int, ...] = (20, 20)
    theta: float = 0.1
    input_scale: tuple[float, float, float, float] = (0.25, 1.0, 10.0, 10.0)
    init_output_std: float = 0.01
    margin: float = 0.01
    neutral_init: bool = False

    def __post_init__(self):
        if not (isinstance(self.n_axes, int) and self.n_axes >= 1):
            raise ValueError(f"NetConfig.n_axes must be an integer >= 1, got {self.n_axes}")
        if not self.hidden or not all(isinstance(h, int) and h >= 1 for h in self.hidden):
            raise ValueError(f"NetConfig.hidden must be widths >= 1, got {self.hidden}")
        if len(self.input_scale) != 4 or not all(
            np.isfinite(s) and s > 0 for s in self.input_scale
        ):
            raise ValueError(
                f"NetConfig.input_scale must be 4 finite values > 0, got {self.input_scale}"
            )
        if not (np.isfinite(self.theta) and np.isfinite(self.init_output_std)):
            raise ValueError("NetConfig.theta and init_output_std must be finite")
        if not 0 < self.margin < 1:  # 0: K_o + K_e = 0 at a saturated output (a pole at s = 0)
            raise ValueError(f"NetConfig.margin must be in (0, 1), got {self.margin}")


class FlaxMlp(nn.Module):
    """One network as a Flax module (the reference and the initialiser): Dense-sigmoid x
    len(hidden), then a Dense to the pre-activation x of Eq. 51.
    """

    hidden: tuple[int, ...]
    init_output_std: float

    @nn.compact
    def __call__(self, inputs: Array) -> Array:
        """Pre-activation x of the output unit for ``inputs`` (..., 4)."""
        y = inputs
        for width in self.hidden:
            y = nn.sigmoid(nn.Dense(width)(y))  # Eqs. 50-51, middle layers
        x = nn.Dense(1, kernel_init=nn.initializers.normal(self.init_output_std))(y)
        return x[..., 0]  # pre-activation of the output unit


def u_max(config: NetConfig, m_e: Array, b_e: Array, k_e: Array) -> Array:
    """U per (axis, kind): 2 (K_e, B_e, M_e) (1 - margin), shape (n_axes, 3)."""
    target = jnp.stack([jnp.asarray(k_e), jnp.asarray(b_e), jnp.asarray(m_e)], axis=-1)
    target = jnp.broadcast_to(target, (config.n_axes, 3))
    return 2.0 * (1.0 - config.margin) * target


def from_flax(flax_params: dict, n_hidden: int) -> dict:
    """Flax ``Dense_l`` params (kernels (..., in, out)) -> this module's (weights (..., out, in))."""
    out = {}
    for layer in range(n_hidden):
        dense = flax_params[f"Dense_{layer}"]
        out[f"hidden_{layer}"] = dict(
            weight=jnp.swapaxes(dense["kernel"], -1, -2), bias=dense["bias"]
        )
    last = flax_params[f"Dense_{n_hidden}"]
    out["output"] = dict(weight=last["kernel"][..., 0], bias=last["bias"][..., 0])
    return out


def to_flax(params: dict, n_hidden: int) -> dict:
    """Inverse of :func:`from_flax`."""
    out = {}
    for layer in range(n_hidden):
        hidden = params[f"hidden_{layer}"]
        out[f"Dense_{layer}"] = dict(
            kernel=jnp.swapaxes(hidden["weight"], -1, -2), bias=hidden["bias"]
        )
    last = params["output"]
    out[f"Dense_{n_hidden}"] = dict(kernel=last["weight"][..., None], bias=last["bias"][..., None])
    return out


def init_params(key: Array, config: NetConfig, dtype=jnp.float32) -> dict:
    """Random parameters for all n_axes x 3 networks (leading axes (n_axes, 3)), in ``dtype``
    (Flax's initialisation of :class:`FlaxMlp`, converted with :func:`from_flax`).
    """
    model = FlaxMlp(config.hidden, config.init_output_std)
    keys = jax.random.split(key, config.n_axes * 3)
    params = jax.vmap(lambda k: model.init(k, jnp.zeros((4,), jnp.float32))["params"])(keys)
    params = jax.tree_util.tree_map(
        lambda p: p.reshape((config.n_axes, 3) + p.shape[1:]).astype(dtype), params
    )
    params = from_flax(params, len(config.hidden))
    if config.neutral_init:
        out = params["output"]
        params["output"] = dict(out, bias=jnp.full_like(out["bias"], config.theta))
    return params


def normalise_inputs(
    config: NetConfig, x_r: Array, xd_r: Array, xdd_r: Array, f_int: Array
) -> Array:
    """Per-axis network inputs (n_axes, 4) from task-space vectors (n_axes,) each."""
    raw = jnp.stack([x_r, xd_r, xdd_r, f_int], axis=-1)
    return raw / jnp.broadcast_to(jnp.asarray(config.input_scale, raw.dtype), raw.shape)


def _layer(weight: Array, y: Array) -> Array:
    """sum_j w_ij y_j (Eq. 50) over the last axis: weight (..., out, in), y (..., in) with leading
    axes broadcastable to weight's -> (..., out).
    """
    y = jnp.broadcast_to(y, weight.shape[:-2] + y.shape[-1:])
    return jnp.einsum("...oi,...i->...o", weight, y)


def pre_activation(params: dict, inputs: Array) -> Array:
    """X of Eq. 51 for every network, shape (n_axes, 3): sum_j w_ij y_j + b_i through the sigmoid
    middle layers (Eq. 50), with the weights (out, in).

    Args:
        params: from :func:`init_params`.
        inputs: (n_axes, 4) normalised inputs of each axis, shared by its three networks.
    """
    if "output" not in params:
        raise ValueError(
            "params need 'hidden_<l>' and 'output' entries (weights (out, in)); got keys "
            f"{sorted(params)} (Flax 'Dense_<l>' params convert with from_flax)"
        )
    n_hidden = sum(key.startswith("hidden_") for key in params)
    y = inputs[:, None, :]  # (n_axes, 1, 4): broadcast over the kinds
    for layer in range(n_hidden):
        hidden = params[f"hidden_{layer}"]
        z = _layer(hidden["weight"], y) + hidden["bias"]
        y = jax.nn.sigmoid(z)  # (n_axes, 3, width)
    return _layer(params["output"]["weight"][..., None, :], y)[..., 0] + params["output"]["bias"]


def apply(params: dict, config: NetConfig, inputs: Array, u: Array) -> Array:
    """Virtual impedance O = (K_o, B_o, M_o) per axis, shape (n_axes, 3) (Eqs. 50-51).

    Args:
        params: from :func:`init_params`.
        config: the networks' structure (threshold theta of Eq. 51).
        inputs: (n_axes, 4) normalised inputs of each axis (:func:`normalise_inputs`).
        u: (n_axes, 3) maximum outputs U (:func:`u_max`).

    Raises:
        ValueError: ``inputs`` not (..., n_axes, 4) (no silent broadcasting of a width-1 input).
    """
    shape = jnp.shape(inputs)
    if len(shape) < 2 or shape[-2:] != (config.n_axes, 4):
        raise ValueError(f"inputs must have shape (..., {config.n_axes}, 4), got {shape}")
    return output_unit(pre_activation(params, inputs), u, config.theta)


def stability_margins(o: Array, m_e: Array, b_e: Array, k_e: Array) -> Array:
    """Strict Eq. 49 margins (K_o + K_e, B_o + B_e, M_o + M_e) per axis, shape (..., n_axes, 3);
    all must be > 0.
    """
    target = jnp.stack([jnp.asarray(k_e), jnp.asarray(b_e), jnp.asarray(m_e)], axis=-1)
    return o + jnp.broadcast_to(target, o.shape)
