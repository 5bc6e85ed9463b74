"""The JAX engine's sub-step loop of the default configuration on tuples of components.

With rotor control, the paper's floor and the free-body physics, the loop carries every vector as a
tuple of (N,) component arrays ((W, N) under ``vmap``), which XLA:CPU runs as contiguous loops over
worlds and quads (~1.45x the step at 512 worlds, docs/engines.md) instead of strided slices of
(N, 7) rows. The formulas are the model's own (:mod:`quadswarm_mj.components` is the one body of the
sub-step functions); ``tests/test_components.py`` checks it against the general loop.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quadswarm_mj import components
from quadswarm_mj.collisions import expand_per_quad
from quadswarm_mj.freebody import freebody_step_components
from quadswarm_mj.perf.xla_cpu import kernel_boundary
from quadswarm_mj.physics.freebody import WorldLocal
from quadswarm_mj.spatial import quat_to_rotmat_components


class ComponentLoop(WorldLocal):
    """The free-body physics of the default configuration as a whole sub-step loop on components, for
    :func:`quadswarm_mj.core.substeps.substep_loop` (its ``fused_loop``; the same formulas as the general
    loop with :class:`quadswarm_mj.physics.mjx.JaxSubstep` and :class:`quadswarm_mj.core.ops.JaxOps`).
    ``fb_constants``: :func:`quadswarm_mj.freebody.freebody_constants`; ``mix`` (3, 4) NumPy."""

    def __init__(self, fb_constants: Any, mix: np.ndarray) -> None:
        self.k, self.mix = fb_constants, mix

    def fused_loop(self, cfg: Any, carry: dict[str, Any], inp: dict[str, Any], consts: dict[str, Any],
                   ops: Any) -> dict[str, Any]:
        """:func:`~quadswarm_mj.core.substeps.substep_loop` (``carry["hit_floor"]`` all False, as there)."""
        c = carry
        q, v, R, u, f_norm, on_floor, hit_floor = component_substeps(
            cfg, self.k, self.mix, c["q"], c["v"], c["R"], c["u"], c["f_norm"], c["on_floor"], inp["params"],
            inp["cmd"], inp["eps"], consts["torque_spin"], ops.rnd["floor/yaw"])
        return {"q": q, "v": v, "R": R, "u": u, "f_norm": f_norm, "on_floor": on_floor,
                "hit_floor": hit_floor, "aux": c["aux"], "ctrl": c["ctrl"]}


def component_substeps(cfg: Any, fb_constants: Any, mix: np.ndarray, q: Any, v: Any, R: Any, u: Any, f_norm: Any,
                       on_floor: Any, params: dict[str, Any], cmd: Any, eps: Any, torque_spin: Any,
                       yaw: Any) -> tuple[Any, ...]:
    """The sub-step loop of the default configuration (rotor control, the paper's floor, free-body
    physics) with the vectors carried as tuples of components (:mod:`quadswarm_mj.components`):
    the same formulas as the general loop (:func:`quadswarm_mj.core.substeps.substep_loop`), in
    contiguous (W, N) arrays under vmap. Takes q (N, 7), v (N, 6), R (N, 3, 3), u and f_norm (N, 4),
    on_floor (N,) and ``yaw`` (substeps, slots), the floor landings' yaw draws (rad); returns (q, v, R,
    u, f_norm, on_floor, hit_floor (N,)) after ``cfg.substeps`` sub-steps."""
    n, f = q.shape[0], q.dtype
    k = fb_constants
    split = components.split
    alpha, mass = params["alpha"], params["mass"]
    gravity = split(jnp.asarray(k.gravity, f))
    max_w, floor_z = cfg.quad.max_omega, cfg.quad.arm

    def substep(i: jax.Array, carry: tuple) -> tuple:
        pos, quat, vel, omega, R, u, _, on_floor, hit_floor = carry
        # this sub-step's floor-landing yaw draws (slots,), indexed in the body: scanning over them
        # would transpose the (W, substeps, slots) draws into (substeps, W, slots) first
        yaw_i = jax.lax.dynamic_index_in_dim(yaw, i, 0, keepdims=False)
        # the loop-invariant inputs are split inside the body, where XLA fuses the slices into
        # their consumers (split outside, each component would be a loop operand: a copy kernel)
        cmd4, eps4, thrust_max, spin = split(cmd), split(eps), split(params["thrust_max"]), split(torque_spin)
        inertia = split(params["inertia"])
        u, f_norm, force, torque = components.rotor_wrench(u, cmd4, eps4, alpha, thrust_max, spin, mix, R)
        force, torque = components.floor_wrench(on_floor, force, torque, vel, mass, params["gravity"],
                                                cfg.collision.floor_friction, cfg.sim_dt)
        pos, quat, vel, omega = freebody_step_components(pos, quat, vel, omega, force, torque, mass, inertia,
                                                         k.ipos, k.iquat, gravity, k.dt, xp=jnp)
        omega = tuple(jnp.clip(w, -max_w, max_w) for w in omega)
        R = quat_to_rotmat_components(*quat)
        landing = (pos[2] <= floor_z) & ~on_floor
        d = expand_per_quad(landing, {"c": jnp.cos(yaw_i), "s": jnp.sin(yaw_i)})  # trig-free yaw draws
        # the landing yaw's (cos, sin) computed once, in their own kernels, instead of inside each
        # select of the floor impact that reads them (~25 % fewer operations in the loop body)
        one = 1.0 + 0.0 * i.astype(f)  # 1.0 that XLA cannot fold: see perf.xla_cpu.kernel_boundary
        mat = functools.partial(kernel_boundary, one=one)
        r = components.floor_impact(pos, vel, omega, quat, R, u, on_floor, floor_z, (d["c"], d["s"]), mat)
        return (r["pos"], r["quat"], r["vel"], r["omega"], r["R"], r["u"], f_norm, r["on_floor"],
                hit_floor | r["hit_floor"])

    qc, vc = split(q), split(v)
    # every sub-step sets f_norm before reading it: zeros, not the slices of the previous step's
    zeros = jnp.zeros((n,), f)
    f_norm0 = (zeros,) * 4 if cfg.substeps >= 1 else split(f_norm)
    carry0 = (qc[:3], qc[3:], vc[:3], vc[3:], split(R.reshape(n, 9)), split(u), f_norm0, on_floor,
              jnp.zeros((n,), bool))
    pos, quat, vel, omega, R, u, f_norm, on_floor, hit_floor = jax.lax.fori_loop(0, cfg.substeps, substep, carry0)
    stack = components.stack
    return (stack(pos + quat), stack(vel + omega), stack(R).reshape(n, 3, 3), stack(u), stack(f_norm),
            on_floor, hit_floor)
