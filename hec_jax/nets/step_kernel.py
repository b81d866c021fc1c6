"""The learner's network step (Eqs. 50-53): forward pass, backpropagation and the Eq. 52 update of
all n_axes x 3 networks of one run, as one function with two implementations.

``network_step(params, net_in, g_scale, learning, eta, u, theta, kernel, active)`` returns the
virtual impedance O (n_axes, 3) and the updated parameters:

* O = (U/2) tanh((x - theta)/2), x the pre-activation of Eq. 51 (``impedance_nets.apply``), where
  ``active`` (default True), 0 where not (a run whose O is not used this sample, e.g. outside the
  virtual sphere, where Eq. 47 gives F_o = 0: the Triton kernel then reads none of its weights),
* every weight w -> w - eta_kind dE/dw where ``learning & active``, unchanged (bitwise)
  otherwise, with dE/dw = sum_(axis, kind) g_scale[axis, kind] dO[axis, kind]/dw: ``g_scale``
  is dE/dO, which the learner forms as (dE/dF_act)_axis dF_o,axis/dO[axis, kind] (Eqs. 47, 53).

``kernel="xla"`` is the reference: ``jax.vjp`` through :func:`impedance_nets.apply` and a select.
Under ``vmap`` on an NVIDIA GPU it makes three passes over every run's 20 x 20 hidden weights per
sample (forward reduction, backward reduction, update) and writes them all, learning or not.

``kernel="triton"`` (or ``"interpret"``, the same kernel through Pallas' interpreter, for tests
on the CPU): the same step under ``vmap`` (a ``jax.custom_batching.custom_vmap`` rule) is
one Pallas Triton kernel on CUDA devices (``jax.lax.platform_dependent``; elsewhere, and when not
under ``vmap``, the reference runs). Each kernel program keeps ``NETS_PER_PROGRAM`` networks'
weights in registers through the forward pass, the backward pass and the update: the weights are
read once per sample (not at all for inactive runs) and written only by runs that learn that
sample (the outputs alias the input parameters, so runs that do not learn keep their buffers
untouched). The 20 x 20 blocks are loaded
as masked 32 x 32 tiles (Triton needs power-of-2 shapes). Where the step itself is
differentiated (e.g. backpropagation through time) the reference runs, primal included
(``jax.custom_jvp``), so ``grad``, ``jvp`` and ``vmap`` compose with either implementation.
For finite values the two agree to rounding: the kernel sums in its own order and computes in
the parameters' dtype (``tests/test_nets.py`` compares them in float32 and float64 through
Pallas' interpreter on the CPU; on an H200 a reviewer's check gave 2.6e-7 relative in float32,
6e-16 in float64). Where a value overflows, the
kernel may give +-inf where the reference gives NaN. Weights are written only by learning runs
when the parameters are a loop carry updated in place (as in the learner's scan); otherwise XLA
copies the buffer first.

Limits: two hidden layers of at most 32 units; under ``vmap`` with a batched ``eta`` or ``u`` the
reference runs; a learning rate of 0 stores nothing (w - 0 g = w also where g is not finite, unlike
the reference); the kernel has no partitioning rule for GSPMD: to split a run axis over several
GPUs, give each GPU its own executable on its own runs (``experiments/devices.py``, used by
``experiments/sweep.py``); under ``jax.shard_map`` the kernel alone runs, but XLA's GPU compiler
crashed on the whole catching loop there.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import Array

from hec_jax.nets import impedance_nets as nets

KERNELS = ("xla", "triton", "interpret")
# Networks per kernel program (a power of 2) and warps per program. Batch 65536 (393216 networks,
# 851 MB of float32 parameters), 100 samples in a scan, ms per sample (scratch probe, session 10):
#   one H100, 10% / 100% of the runs learning: (G, warps) = (2, 1) 0.40 / 0.65, (1, 1) 0.41 / 0.68,
#     (4, 1) 0.42 / 0.66, (8, 4) 0.75 / 0.90, (16, 8) 1.9 / 2.0; the reference 1.30 / 1.30;
#   one H200, none / 25% learning: (2, 1) 0.31 / 0.36, (1, 1) 0.32 / 0.37, (4, 2) 0.43 / 0.47,
#     (2, 2) 0.41 / 0.45; the reference - / 0.97. Triton's eviction hints on the loads: no change.
NETS_PER_PROGRAM = 2
NUM_WARPS = 1
_TILE = 32  # padded width of the 20-unit layers (power of 2 >= every layer width)


def _reference(params, net_in, g_scale, learning, eta, u, theta, active=None):
    """Reference step (XLA): O (0 where not ``active``), and the parameters after Eq. 52 where
    ``learning & active``; ``active`` None: always active.
    """

    def impedance(p):
        return nets.output_unit(nets.pre_activation(p, net_in), u, theta)

    o, pullback = jax.vjp(impedance, params)
    if active is not None:
        learning = learning & active
        o = jnp.where(active, o, 0.0)
    (grad,) = pullback(jnp.where(learning, g_scale, 0.0).astype(o.dtype))

    def step(w, g):
        rate = eta.reshape((1, 3) + (1,) * (g.ndim - 2)).astype(g.dtype)
        # the select keeps the weights exactly on samples that do not learn (a non-finite forward
        # value times the zero cotangent would otherwise give NaN)
        return jnp.where(learning, w - rate * g, w)

    return o, jax.tree_util.tree_map(step, params, grad)


def _check_params(params: dict) -> None:
    keys = sorted(params)
    if keys != ["hidden_0", "hidden_1", "output"]:
        raise ValueError(
            f"kernel='triton' supports two hidden layers (4-20-20-1); got parameters {keys}"
        )
    h0, n_in = params["hidden_0"]["weight"].shape[-2:]
    h1, h1_in = params["hidden_1"]["weight"].shape[-2:]
    if max(h0, h1) > _TILE or h1_in != h0 or n_in & (n_in - 1):
        raise ValueError(
            f"kernel='triton' supports hidden layers of at most {_TILE} units and a power-of-2 "
            f"input width; got inputs {n_in}, hidden ({h0}, {h1})"
        )


def _kernel_body(
    theta,
    w0_ref,  # (N, H0, I) first hidden layer weights, (out, in)
    b0_ref,  # (N, H0)
    w1_ref,  # (N, H1, H0)
    b1_ref,  # (N, H1)
    w2_ref,  # (N, H1) output unit weights
    b2_ref,  # (N,)
    x_ref,  # (N, I) normalised inputs
    g_ref,  # (N,) dE/dO
    rate_ref,  # (N,) learning rate where the run learns, 0 otherwise
    u_ref,  # (N,) U of Eq. 51
    active_ref,  # (N,) 1 where O is wanted, 0 where not (nothing of that network is read)
    o_ref,  # (N,) output O
    w0_out,
    b0_out,
    w1_out,
    b1_out,
    w2_out,
    b2_out,
):
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plt

    g_count, t = NETS_PER_PROGRAM, _TILE
    h0, n_in = w0_ref.shape[1:]
    h1 = w1_ref.shape[1]
    zero = jnp.int32(0)  # every slice start int32 (also with jax_enable_x64)
    nets_ = pl.ds(pl.program_id(0).astype(jnp.int32) * g_count, g_count)
    rows = jnp.arange(t, dtype=jnp.int32)
    row0 = rows < h0  # valid units of hidden layer 0
    row1 = rows < h1
    # inactive networks' loads are masked off (no memory traffic for their weights), and a program
    # whose networks are all inactive only writes O = 0
    act = active_ref[nets_] != 0  # (G,)
    m_w0 = jnp.broadcast_to(row0[None, :, None] & act[:, None, None], (g_count, t, n_in))
    m_w1 = row1[None, :, None] & row0[None, None, :] & act[:, None, None]  # (G, T, T)
    m_h0 = row0[None, :] & act[:, None]  # (G, T)
    m_h1 = row1[None, :] & act[:, None]
    any_active = jnp.max(act.astype(jnp.int32)) > 0

    @pl.when(jnp.logical_not(any_active))
    def _idle():  # no network of this program is wanted: O = 0, nothing read or written
        o_ref[nets_] = jnp.zeros((g_count,), o_ref.dtype)

    @pl.when(any_active)
    def _step():
        tile0 = (nets_, pl.ds(zero, t), pl.ds(zero, n_in))
        tile1 = (nets_, pl.ds(zero, t), pl.ds(zero, t))
        vec = (nets_, pl.ds(zero, t))

        w0 = plt.load(w0_ref.at[tile0], mask=m_w0, other=0.0)
        b0 = plt.load(b0_ref.at[vec], mask=m_h0, other=0.0)
        w1 = plt.load(w1_ref.at[tile1], mask=m_w1, other=0.0)
        b1 = plt.load(b1_ref.at[vec], mask=m_h1, other=0.0)
        w2 = plt.load(w2_ref.at[vec], mask=m_h1, other=0.0)
        b2 = plt.load(b2_ref.at[nets_], mask=act, other=0.0)
        x = x_ref[nets_, :]
        g = g_ref[nets_]
        rate = rate_ref[nets_]
        u = u_ref[nets_]

        # forward (Eqs. 50-51); padded units are held at 0
        y1 = jnp.where(m_h0, jax.nn.sigmoid(jnp.sum(w0 * x[:, None, :], axis=2) + b0), 0.0)
        y2 = jnp.where(m_h1, jax.nn.sigmoid(jnp.sum(w1 * y1[:, None, :], axis=2) + b1), 0.0)
        s = jnp.sum(w2 * y2, axis=1) + b2
        th = jnp.tanh(0.5 * (s - theta))
        o_ref[nets_] = jnp.where(act, 0.5 * u * th, 0.0)
        # backward: d(-rate E)/d(pre-activations); rate is 0 where the run does not learn
        d_s = -rate * g * 0.25 * u * (1.0 - th * th)  # (G,)
        d_2 = d_s[:, None] * w2 * y2 * (1.0 - y2)  # (G, T)
        d_1 = jnp.sum(w1 * d_2[:, :, None], axis=1) * y1 * (1.0 - y1)  # W1^T d_2, pre-update
        # Eq. 52, stored only by the networks of runs that learn (inactive runs have rate 0)
        learn = act & (rate != 0.0)
        l_h = learn[:, None]
        plt.store(
            w0_out.at[tile0], w0 + d_1[:, :, None] * x[:, None, :], mask=m_w0 & l_h[:, :, None]
        )
        plt.store(b0_out.at[vec], b0 + d_1, mask=m_h0 & l_h)
        plt.store(
            w1_out.at[tile1], w1 + d_2[:, :, None] * y1[:, None, :], mask=m_w1 & l_h[:, :, None]
        )
        plt.store(b1_out.at[vec], b1 + d_2, mask=m_h1 & l_h)
        plt.store(w2_out.at[vec], w2 + d_s[:, None] * y2, mask=m_h1 & l_h)
        plt.store(b2_out.at[nets_], b2 + d_s, mask=learn)


def _triton_batched(params, net_in, g_scale, learning, active, eta, u, theta, interpret=False):
    """The kernel over a batch: every argument with a leading batch axis (B, ...) except ``eta``
    (3,) and ``u`` (n_axes, 3), all in the parameters' dtype (``learning``, ``active``: bool).
    """
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plt

    batch, n_axes = net_in.shape[:2]
    n = batch * n_axes * 3
    n_pad = -(-n // NETS_PER_PROGRAM) * NETS_PER_PROGRAM
    dtype = params["hidden_1"]["weight"].dtype

    def flat(a, trailing):  # (B, n_axes, 3, *trailing) -> (n_pad, *trailing)
        a = a.reshape((n,) + trailing)
        return jnp.pad(a, [(0, n_pad - n)] + [(0, 0)] * len(trailing)) if n_pad > n else a

    h0, n_in = params["hidden_0"]["weight"].shape[-2:]
    h1 = params["hidden_1"]["weight"].shape[-2]
    leaves = (
        flat(params["hidden_0"]["weight"], (h0, n_in)),
        flat(params["hidden_0"]["bias"], (h0,)),
        flat(params["hidden_1"]["weight"], (h1, h0)),
        flat(params["hidden_1"]["bias"], (h1,)),
        flat(params["output"]["weight"], (h1,)),
        flat(params["output"]["bias"], ()),
    )
    x = flat(jnp.broadcast_to(net_in[:, :, None, :], (batch, n_axes, 3, n_in)), (n_in,))
    g = flat(g_scale, ())
    rate = jnp.where((learning & active)[:, None, None], eta[None, None, :], 0.0)
    rate = flat(jnp.broadcast_to(rate, (batch, n_axes, 3)), ())
    u_n = flat(jnp.broadcast_to(u, (batch, n_axes, 3)), ())
    act = flat(jnp.broadcast_to(active[:, None, None], (batch, n_axes, 3)).astype(jnp.int32), ())
    out_shape = (jax.ShapeDtypeStruct((n_pad,), dtype),) + tuple(
        jax.ShapeDtypeStruct(leaf.shape, dtype) for leaf in leaves
    )
    outs = pl.pallas_call(
        functools.partial(_kernel_body, float(theta)),
        out_shape=out_shape,
        grid=(n_pad // NETS_PER_PROGRAM,),
        input_output_aliases={i: i + 1 for i in range(len(leaves))},
        compiler_params=plt.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        interpret=interpret,
    )(*leaves, x, g, rate, u_n, act)
    o = outs[0][:n].reshape(batch, n_axes, 3)
    unflat = [leaf[:n].reshape((batch, n_axes, 3) + leaf.shape[1:]) for leaf in outs[1:]]
    new = {
        "hidden_0": {"weight": unflat[0], "bias": unflat[1]},
        "hidden_1": {"weight": unflat[2], "bias": unflat[3]},
        "output": {"weight": unflat[4], "bias": unflat[5]},
    }
    return o, new


@functools.cache
def _fused(theta: float, interpret: bool):
    """``custom_jvp(custom_vmap(reference))`` with the kernel as the vmap rule (per theta)."""

    def reference(params, net_in, g_scale, learning, active, eta, u):
        return _reference(params, net_in, g_scale, learning, eta, u, theta, active)

    batched_fn = jax.custom_batching.custom_vmap(reference)

    @batched_fn.def_vmap
    def _rule(axis_size, in_batched, params, net_in, g_scale, learning, active, eta, u):
        args = (params, net_in, g_scale, learning, active, eta, u)
        # a batch axis for every argument (constants broadcast), as the kernel reads them
        args = jax.tree_util.tree_map(
            lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + a.shape),
            args,
            tuple(in_batched),
        )

        def kernel(*a):
            p, x, g, lrn, act, e, uu = a
            return _triton_batched(p, x, g, lrn, act, e[0], uu[0], theta, interpret=interpret)

        def fallback(*a):
            return jax.vmap(reference)(*a)

        if in_batched[5] or in_batched[6]:  # rates or U swept: the kernel takes them shared
            out = fallback(*args)
        elif interpret:
            out = kernel(*args)
        else:
            out = jax.lax.platform_dependent(*args, cuda=kernel, default=fallback)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    fused = jax.custom_jvp(batched_fn)

    @fused.defjvp
    def _jvp(primals, tangents):
        # differentiated, the step is the reference's, primal included (one forward pass)
        return jax.jvp(reference, primals, tangents)

    return fused


def network_step(
    params: dict,
    net_in: Array,
    g_scale: Array,
    learning: Array,
    eta: Array,
    u: Array,
    theta: float,
    kernel: str = "xla",
    active: Array | None = None,
) -> tuple[Array, dict]:
    """O and the Eq. 52 update of one run's networks (see the module docstring).

    Args:
        params: network parameters, leading axes (n_axes, 3) (``impedance_nets.init_params``).
        net_in: (n_axes, 4) normalised inputs.
        g_scale: (n_axes, 3) dE/dO.
        learning: bool () whether this sample updates the weights.
        eta: (3,) learning rates of (VSN, VVN, VIN).
        u: (n_axes, 3) maximum outputs U.
        theta: output-unit threshold (static).
        kernel: "xla" (reference), "triton" (one Pallas Triton kernel under ``vmap`` on CUDA, the
            reference elsewhere) or "interpret" (the kernel through Pallas' interpreter on any
            device under ``vmap``, the reference without: slow, for tests on the CPU).
        active: bool () or None (always): where False, O is 0 and the weights are held (no
            learning); the kernel then reads none of the run's weights.

    Returns:
        (O (n_axes, 3), updated params).

    Under ``vmap`` with batched ``eta`` or ``u`` the "triton" kernel falls back to the reference.
    """
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    learning = jnp.asarray(learning, bool)
    active = None if active is None else jnp.asarray(active, bool)
    if kernel == "xla":
        return _reference(params, net_in, g_scale, learning, eta, u, theta, active)
    _check_params(params)
    # the kernel computes in the parameters' dtype
    dtype = params["hidden_1"]["weight"].dtype
    net_in, g_scale, eta, u = (jnp.asarray(a).astype(dtype) for a in (net_in, g_scale, eta, u))
    active = jnp.ones((), bool) if active is None else active
    return _fused(float(theta), kernel == "interpret")(
        params, net_in, g_scale, learning, active, eta, u
    )
