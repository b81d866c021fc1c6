"""Online learning of the virtual impedance (Sec. 5.2, Eqs. 52-58) for catching and hitting.

``make_online_learner(config, dt, m_e, b_e, k_e)`` returns pure ``init(key) -> LearnerState`` and
``update(state, inputs, allow=True) -> (state, LearnerOutput)``; ``update`` runs once per control
sample inside the jitted rollout (one ``lax.scan``), never in Python; ``allow`` False (e.g. the
object not seen) holds the weights for that sample.

Per sample (readings from docs/paper_readings.md, Sec. 3):

1. X_r = X_o - X_e and its derivatives; inside = |X_r| <= r. t_c is the first sample inside after
   being outside: X_r'(t_c) is latched per encounter.
2. O = (K_o, B_o, M_o) per axis from the networks (Eqs. 50-51), and
   F_o = M_o dX_o'' + B_o dX_o' + K_o dX_o inside the sphere, 0 outside (Eq. 47); the geometry
   (dX_o and derivatives, Eq. 45-46) comes in with the inputs (``LearnerInputs.sphere``): the
   hand's ``hec_jax.control.sphere_kinematics`` computes it; ``nets`` stands alone.
3. Energy E(t) of the task and its gradient with respect to X_e and X_e' (autodiff of the energy
   expression, object state held fixed):
   * catching (Eqs. 59-62): E = c 1/2 |alpha(|X_r|) X_r'(t_c) - X_r'(t)|^2 + mu e_f, where c = 1
     until the first contact of the encounter and 0 after it (Sec. 6.2: "relative velocity ...
     should be reduced before contact, and the end-point force after contact ... should be
     controlled"; with the velocity term kept after contact, alpha > 0 at the contact distance
     keeps asking for an approach velocity the object cannot have, which pulls the hand into the
     object and unlearns the catch),
   * hitting (Eqs. 63-66): E = 1/2 |beta(|X_r|) X_o'(t) - X_e'(t)|^2 + mu e_f,
   where e_f = 1/2 |F_d - F_int|^2 is the integrand of E_cf / E_hf (Eqs. 61, 65): the part of the
   integral that the current control can still change. F_d = -f_d n while in contact, 0 otherwise
   (the object presses on the hand with f_d, along -n). dF_int/dX_e, which the paper does not give,
   is the nominal contact-stiffness Jacobian -k_c n n^T while in contact and 0 otherwise.
4. The paper's approximation (Eqs. 54-58, the hand as a unit mass over one sample):
   dE/dF_act = dE/dX_e dt^2 + dE/dX_e' dt (Eq. 54's second factor read as dX_e'/dF_act; Eq. 56's
   "(k)" is debris).
5. dw = -eta (dE/dF_act)^T (dF_act/dO)(dO/dw) (Eqs. 52-53) with F_act = F_o: dE/dO formed from
   Eq. 47, then backpropagation through the networks (``network_step``). A separate learning rate
   per network kind (VSN, VVN, VIN).
6. Gate (found in a 1-D prototype, not in the paper): no learning while the object recedes inside
   the sphere without contact (n . X_r' > 0). In catching the latched approach velocity then
   becomes a wrong target and the hand unlearns the catch; in hitting, beta X_o' of a receding
   object asks the hand to move away from it, which trains the networks against the next strike.
   R_b must be below the contact distance (hand radius + half cube), or the catching learner learns
   to avoid contact; this is a parameter choice. ``gate_receding=False`` learns whenever inside.

Gain functions: alpha (Eq. 62) = sin((|X_r| - R_b) pi / (2 (r - R_b))) for |X_r| >= R_b, else 0;
beta (Eq. 66) = alpha - 1 for |X_r| >= R_b, else 0: beta jumps from -1 to 0 at R_b, as printed (the
paper's choice, kept and flagged).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from hec_jax.nets import impedance_nets as nets
from hec_jax.nets.step_kernel import KERNELS, network_step

TASKS = ("catching", "hitting")
# With ``nets_outside=False`` the networks run where |X_r| <= r (1 + NETS_SHELL): a thin shell past
# the sphere, so that the controller, which tests |X_r| <= r with its own rounding, never finds O
# missing at the boundary.
NETS_SHELL = 1e-4


@dataclass(frozen=True)
class LearnerConfig:
    """Static configuration of the online learner (parameter values: docs/paper_readings.md, Sec. 4).

    Attributes:
        task: "catching" or "hitting".
        radius: virtual sphere radius r [m].
        r_b: R_b of the gain functions [m] (below the contact distance).
        eta: learning rates of (VSN, VVN, VIN).
        mu: weight of the force term E_cf / E_hf.
        f_desired: desired contact force magnitude f_d [N] (F_cd or F_hd = -f_d n in contact).
        contact_stiffness: nominal k_c [N/m] for dF_int/dX_e = -k_c n n^T in contact.
        gate_receding: pause learning while the object recedes without contact (in catching with
            ``velocity_after_contact``, only until the first contact of the encounter).
        velocity_after_contact: keep E_cv after the first contact (Eq. 59 as printed); False: E_cv
            only before it (see the module docstring).
        contact_damping: nominal b_c [N s/m] of the contact for dF_int/dX_e' = -b_c n n^T in
            contact (its gradient enters with dt instead of dt^2); 0: stiffness only.
        gain: "paper": the gains alpha (Eq. 62) and beta (Eq. 66) shape the desired velocity
            with the distance |X_r|; "off" (an ablation): constant gains, alpha = 0 and beta = -1
            at every distance (catching: the relative velocity is driven to 0 as soon as the
            object is inside the sphere; hitting: the hand's desired velocity is -X_o'
            throughout); the latched X_r'(t_c) then plays no part.
        net: network structure.
        kernel: implementation of the network step (forward, backpropagation, Eq. 52 update):
            "xla" (reference) or "triton" (one Pallas Triton kernel per sample under ``vmap`` on
            CUDA GPUs, the reference elsewhere; ``hec_jax.nets.network_step``) or "interpret" (that
            kernel through Pallas' interpreter: slow, for tests on the CPU). Same results to
            rounding; gradients through the learner go through the reference either way.
        nets_outside: evaluate the networks outside the virtual sphere too (O logged there,
            unused: Eq. 47 gives F_o = 0 outside). False: O = 0 outside the sphere (beyond
            r (1 + NETS_SHELL); also in the logs, and the Eq. 49 margins there are the target
            impedance's, so a minimum margin over a run covers only the samples where the virtual
            impedance acts), the same forces, torques and learning, and the "triton" kernel reads
            no weights of runs outside the sphere that sample (a sweep's or benchmark's choice).
    """

    task: Literal["catching", "hitting"] = "catching"
    radius: float = 0.25
    r_b: float = 0.06
    eta: tuple[float, float, float] = (0.1, 0.1, 0.1)
    mu: float = 1e-3
    f_desired: float = 1.0
    contact_stiffness: float = 1e4
    gate_receding: bool = True
    velocity_after_contact: bool = False
    contact_damping: float = 0.0
    gain: Literal["paper", "off"] = "paper"
    net: nets.NetConfig = field(default_factory=nets.NetConfig)
    kernel: Literal["xla", "triton", "interpret"] = "xla"
    nets_outside: bool = True

    def __post_init__(self):
        if self.kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {self.kernel!r}")
        if self.gain not in ("paper", "off"):
            raise ValueError(f"gain must be 'paper' or 'off', got {self.gain!r}")
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {self.task!r}")
        if not (0.0 <= self.r_b < self.radius):
            raise ValueError(f"need 0 <= R_b < r, got R_b={self.r_b}, r={self.radius}")
        if len(self.eta) != 3 or not all(math.isfinite(e) and e >= 0 for e in self.eta):
            raise ValueError(f"eta must be 3 finite rates >= 0 (VSN, VVN, VIN), got {self.eta}")
        if not (math.isfinite(self.radius) and math.isfinite(self.r_b)):
            raise ValueError(f"radius and r_b must be finite, got {self.radius}, {self.r_b}")
        for name in ("mu", "f_desired", "contact_stiffness", "contact_damping"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"LearnerConfig.{name} must be finite and >= 0, got {v}")


class SphereGeometry(NamedTuple):
    """The virtual sphere's geometry at one sample (task space, per axis; Eqs. 45-46): the
    object's offset from the sphere surface dX_o [m] and its derivatives [m/s], [m/s^2].
    """

    dx_o: Array
    dxd_o: Array
    dxdd_o: Array


class LearnerInputs(NamedTuple):
    """One control sample, task space (n_axes,) each, plus the contact flag ()."""

    x_e: Array  # [m] hand position
    xd_e: Array  # [m/s]
    xdd_e: Array  # [m/s^2]
    x_o: Array  # [m] object position
    xd_o: Array  # [m/s]
    xdd_o: Array  # [m/s^2]
    f_int: Array  # [N] force exerted on the hand by the environment (Eq. 39)
    in_contact: Array  # bool ()
    sphere: SphereGeometry  # Eqs. 45-46 at this sample, for the learner's sphere radius


class LearnerState(NamedTuple):
    """What the learner carries from sample to sample (weights and the encounter's memory)."""

    params: dict  # network parameters, leading axes (n_axes, 3)
    xd_r_tc: Array  # (n_axes,) X_r'(t_c) latched at the last entry into the sphere
    was_inside: Array  # bool ()
    touched: Array  # bool (): contact has occurred since the last entry into the sphere
    energy_f: Array  # () running E_cf / E_hf integral [N^2 s]
    encounters: Array  # int () number of entries into the sphere so far
    nonfinite_samples: Array  # int () samples skipped for a non-finite input (NaN/inf)


class LearnerOutput(NamedTuple):
    """What one learner sample reports (forces, impedance, energy, flags, margins)."""

    f_o: Array  # (n_axes,) virtual force F_o [N] (Eq. 47)
    impedance: Array  # (n_axes, 3) O = (K_o, B_o, M_o)
    energy: Array  # () E(t) of the task (velocity term + mu * force integrand)
    de_df_act: Array  # (n_axes,) the paper's dE/dF_act
    inside: Array  # bool ()
    learning: Array  # bool (): weights updated this sample
    margins: Array  # (n_axes, 3) strict Eq. 49 margins, all > 0
    finite: Array  # bool (): every input finite; else the sample is skipped (F_o = 0, O = 0)


def gain_alpha(rho: Array, radius: float, r_b: float) -> Array:
    """alpha(|X_r|) of Eq. 62."""
    phase = (rho - r_b) * jnp.pi / (2.0 * (radius - r_b))
    return jnp.where(rho >= r_b, jnp.sin(phase), 0.0)


def gain_beta(rho: Array, radius: float, r_b: float) -> Array:
    """beta(|X_r|) of Eq. 66 (jumps from -1 to 0 at R_b, as printed)."""
    phase = (rho - r_b) * jnp.pi / (2.0 * (radius - r_b))
    return jnp.where(rho >= r_b, jnp.sin(phase) - 1.0, 0.0)


def _norm(v: Array) -> Array:
    sq = jnp.sum(v * v)
    ok = sq > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def desired_force(config: LearnerConfig, x_r: Array, in_contact: Array) -> tuple[Array, Array]:
    """(n, F_d): unit vector hand -> object (0 at X_r = 0) and the desired force on the hand,
    -f_d n while in contact, 0 otherwise (F_cd of Eq. 61 / F_hd of Eq. 65).
    """
    rho = _norm(x_r)
    n = jnp.where(rho > 0, x_r / jnp.where(rho > 0, rho, 1.0), 0.0)
    return n, -config.f_desired * in_contact.astype(x_r.dtype) * n


def task_energy(
    config: LearnerConfig,
    x_e: Array,
    xd_e: Array,
    inputs: LearnerInputs,
    xd_r_tc: Array,
    touched: Array | bool = False,
) -> Array:
    """E(t) as a function of the hand state (X_e, X_e'), object state held fixed (Eqs. 59-66).

    The force term is mu * 1/2 |F_d - F_int(X_e)|^2 with F_int linearised about the measured value
    with the nominal contact stiffness (see the module docstring).
    """
    x_r = inputs.x_o - x_e
    rho = _norm(x_r)
    n0, f_d = desired_force(config, inputs.x_o - inputs.x_e, inputs.in_contact)
    contact = inputs.in_contact.astype(x_e.dtype)
    # F_int(X_e) = F_int + dF_int/dX_e (X_e - X_e0), dF_int/dX_e = -k_c n n^T in contact.
    f_int = inputs.f_int - contact * config.contact_stiffness * n0 * jnp.dot(n0, x_e - inputs.x_e)
    # ... and -b_c n n^T (X_e' - X_e0') with the nominal contact damping.
    f_int = f_int - contact * config.contact_damping * n0 * jnp.dot(n0, xd_e - inputs.xd_e)
    e_force = 0.5 * jnp.sum((f_d - f_int) ** 2)
    if config.task == "catching":
        alpha = gain_alpha(rho, config.radius, config.r_b) if config.gain == "paper" else 0.0
        e_vel = 0.5 * jnp.sum((alpha * xd_r_tc - (inputs.xd_o - xd_e)) ** 2)  # Eq. 60
        if not config.velocity_after_contact:
            e_vel = jnp.where(touched, 0.0, e_vel)  # before contact only (Sec. 6.2)
    else:
        beta = gain_beta(rho, config.radius, config.r_b) if config.gain == "paper" else -1.0
        e_vel = 0.5 * jnp.sum((beta * inputs.xd_o - xd_e) ** 2)  # Eq. 64
    return e_vel + config.mu * e_force


def make_online_learner(
    config: LearnerConfig, dt: float, m_e, b_e, k_e
) -> tuple[Callable[[Array], LearnerState], Callable[..., tuple[LearnerState, LearnerOutput]]]:
    """Factory of the pure ``init`` and ``update`` of the online learner (Eqs. 52-58).

    Args:
        config: static configuration.
        dt: [s] sampling interval Delta t_s (the control period).
        m_e: [kg] (n_axes,) target inertia M_e: with b_e and k_e it fixes the bound U of Eq. 51
            and the Eq. 49 margins (the controller's own values).
        b_e: [N s/m] (n_axes,) target damping B_e.
        k_e: [N/m] (n_axes,) target stiffness K_e.

    Raises:
        ValueError: ``dt`` not positive, or a target impedance without ``n_axes`` positive entries.
    """
    n_axes = config.net.n_axes
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be finite and > 0, got {dt}")
    target = {}
    for name, v in (("m_e", m_e), ("b_e", b_e), ("k_e", k_e)):
        a = np.asarray(v, dtype=float)
        if a.shape != (n_axes,) or not np.all(np.isfinite(a) & (a > 0)):
            raise ValueError(f"{name} must have {n_axes} finite positive entries, got {v}")
        target[name] = jnp.asarray(a)
    m_e, b_e, k_e = target["m_e"], target["b_e"], target["k_e"]
    u = nets.u_max(config.net, m_e, b_e, k_e)
    eta = jnp.asarray(config.eta)

    def init(key: Array, dtype=jnp.float32) -> LearnerState:
        params = nets.init_params(key, config.net, dtype)
        return LearnerState(
            params=params,
            xd_r_tc=jnp.zeros((n_axes,), dtype),
            was_inside=jnp.asarray(False),
            touched=jnp.asarray(False),
            energy_f=jnp.zeros((), dtype),
            encounters=jnp.zeros((), jnp.int32),
            nonfinite_samples=jnp.zeros((), jnp.int32),
        )

    def update(
        state: LearnerState, inputs: LearnerInputs, allow: Array | bool = True
    ) -> tuple[LearnerState, LearnerOutput]:
        """One control sample; ``allow`` (bool ()) False: no Eq. 52 step this sample (the
        weights are held, ``LearnerOutput.learning`` is False). A sample with a non-finite input
        (NaN or inf anywhere in ``inputs``) is skipped: no learning, F_o = 0 and O = 0 (as
        outside the sphere), the encounter's memory and E_cf unchanged, and it is counted in
        ``LearnerState.nonfinite_samples`` and flagged by ``LearnerOutput.finite``.
        """
        finite = jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(v)) for v in jax.tree_util.tree_leaves(inputs)])
        )
        x_r = inputs.x_o - inputs.x_e
        xd_r = inputs.xd_o - inputs.xd_e
        xdd_r = inputs.xdd_o - inputs.xdd_e
        rho = _norm(x_r)
        inside = finite & (rho > 0) & (rho <= config.radius)  # as SphereKinematics (Eq. 47)
        entering = inside & ~state.was_inside
        xd_r_tc = jnp.where(entering, xd_r, state.xd_r_tc)  # latch X_r'(t_c) per encounter
        touched = (state.touched & ~entering) | (inside & inputs.in_contact)
        touched = jnp.where(finite, touched, state.touched)  # a skipped sample changes nothing
        geometry = inputs.sphere
        net_in = nets.normalise_inputs(config.net, x_r, xd_r, xdd_r, inputs.f_int)
        energy, (de_dx, de_dxd) = jax.value_and_grad(
            lambda xe, xde: task_energy(config, xe, xde, inputs, xd_r_tc, touched), argnums=(0, 1)
        )(inputs.x_e, inputs.xd_e)
        de_df_act = de_dx * dt**2 + de_dxd * dt  # Eqs. 54-58
        learning = inside & allow
        if config.gate_receding:
            receding = jnp.dot(x_r, xd_r) > 0
            gate = receding & ~inputs.in_contact
            if config.velocity_after_contact and config.task == "catching":
                gate = gate & ~touched  # after the first contact the learning goes on
            learning = learning & ~gate
        # F_o = M_o dX_o'' + B_o dX_o' + K_o dX_o inside the sphere (Eq. 47), so
        # dE/dO[axis, kind] = (dE/dF_act)_axis * (dX_o, dX_o', dX_o'')[kind] (Eq. 53, F_act = F_o)
        terms = jnp.stack([geometry.dx_o, geometry.dxd_o, geometry.dxdd_o], axis=-1)  # K, B, M
        g_scale = jnp.where(learning, de_df_act[:, None] * terms, 0.0)
        o, params = network_step(
            state.params,
            net_in,
            g_scale,
            learning,
            eta,
            u,
            config.net.theta,
            config.kernel,
            active=None if config.nets_outside else rho <= config.radius * (1.0 + NETS_SHELL),
        )  # Eq. 52 where learning (the weights held exactly otherwise); O = 0 where not active
        o = jnp.where(finite, o, 0.0)
        f_o = jnp.where(inside, jnp.sum(o * terms.astype(o.dtype), axis=-1), 0.0)  # Eq. 47
        _, f_d = desired_force(config, x_r, inputs.in_contact)
        e_f = jnp.where(finite, 0.5 * jnp.sum((f_d - inputs.f_int) ** 2) * dt, 0.0)
        energy_f = state.energy_f + e_f
        new_state = LearnerState(
            params=params,
            xd_r_tc=xd_r_tc,
            was_inside=jnp.where(finite, inside, state.was_inside),
            touched=touched,
            energy_f=energy_f,
            encounters=state.encounters + entering.astype(jnp.int32),
            nonfinite_samples=state.nonfinite_samples + (~finite).astype(jnp.int32),
        )
        margins = nets.stability_margins(o, m_e, b_e, k_e)
        out = LearnerOutput(
            f_o=f_o,
            impedance=o,
            energy=energy,
            de_df_act=de_df_act,
            inside=inside,
            learning=learning,
            margins=margins,
            finite=finite,
        )
        return new_state, out

    return init, update
