"""The task half of the CPU engine's control step for several quads, in few NumPy calls.

:func:`quadswarm_mj.core.control.task_step` (scenario, reward terms, metrics, observation, reward sum) spends
most of its time in NumPy's fixed cost per call on small (B, N, .) arrays. :class:`SwarmTask` computes the
same values with the same operations in the same order (the same bits, signs of zero included;
``tests/test_numpy_swarm.py`` checks seeded episodes against the model's functions): the reward's five norms
as one product and left-to-right sums over a zero-padded (4, 5, B, N) block (adding +0.0 to a sum of squares
changes no bit); the terms as one product of a (T, B, N) cost block with the factors -dt * scale (the -0.0
terms keep a zero cost) and the reward as their running sum in ``rewards.TERMS`` order (adding -0.0 changes
no bit); the proximity term (+0.0 with no pair within the falloff), the collision count and the metric
accumulators that only events change gated on their events (x + 0.0 is x for these non-negative sums); the
observation written part by part into one fresh array (the decks' part by ``perf.numpy_deck``). Used for the
"rotor" mode without obstacles, "base"/"floor" own state, neighbours by distance without neighbour noise,
several quads. NumPy only.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from quadswarm_mj import metrics as metrics_lib
from quadswarm_mj import np_calls, rewards
from quadswarm_mj.collisions import off_diagonal
from quadswarm_mj.observations import _gather_index, _neighbor_bounds, _obs_neighbor_bounds
from quadswarm_mj.perf import numpy_deck
from quadswarm_mj.pipeline import _no_jump

#: set to False for the model's functions (the same-values tests compare the two)
ENABLED = True

_count_nonzero, _copyto, _clip = np_calls.count_nonzero, np_calls.copyto, np_calls.clip  # no np wrappers
# rows of the norm block: goal offset, clipped action, omega, velocity, thrust change
_NORM_TERMS = ("pos", "effort", "spin", "vel", "action_change")


def applies(cfg: Any, B: int, N: int) -> bool:
    """Whether :class:`SwarmTask` covers an engine of B worlds of N quads with ``cfg``."""
    return (B * N > 1 and cfg.control_mode == "rotor" and cfg.obstacles is None and cfg.rewards.vel_limit == 0
            and cfg.obs_self in ("base", "floor") and not cfg.noise.neighbor_obs_noise
            and (cfg.neighbors == 0 or (cfg.neighbor_sort == "distance" and cfg.neighbor_form == "raw")))


class SwarmTask:
    """``fused_task`` of :func:`quadswarm_mj.core.control.task_step` for a CPU engine of B worlds of N quads
    (:func:`applies`); ``swarm`` the :class:`~quadswarm_mj.envs.cpu_core.CpuSwarm` (bounds, scale, draws)."""

    def __init__(self, swarm: Any) -> None:
        cfg = swarm.cfg
        B, N = swarm.B, swarm.N
        self.cfg, self.B, self.N = cfg, B, N
        self.zero_terms = swarm._zero_terms
        self.dt, self.episode_steps, self.grace = cfg.control_dt, cfg.episode_steps, cfg.grace_period_s
        factors = rewards._term_factors(cfg.rewards, cfg.sim_dt, cfg.control_dt)
        self.terms = tuple(k for k, _, _ in factors)
        self.T = len(self.terms)
        self.factors = factors
        self.row = {k: i for i, k in enumerate(self.terms)}
        self.live = {k for k, _, base in factors if base is not None}  # terms whose cost is computed
        self.annealed = any(k in rewards.ANNEALED and k in self.live for k in self.terms) and \
            cfg.rewards.anneal_steps > 0
        self.coef = self._coef(1.0)
        self.falloff = cfg.rewards.proximity_falloff_arms * cfg.quad.arm
        self.offdiag = off_diagonal(N)
        # observation layout and bounds (the neighbour bounds folded in, as build_obs does every step)
        self.K, self.self_dim, self.D = cfg.neighbors, cfg.self_obs_dim, cfg.obs_dim
        low, high = swarm.obs_low, swarm.obs_high
        if self.K > 0:
            nb_lo, nb_hi = _obs_neighbor_bounds(cfg.self_obs_dim, self.K, tuple(_neighbor_bounds(cfg)),
                                                cfg.obs_dim - cfg.self_obs_dim - 6 * self.K)
            low, high = np.maximum(np.asarray(low), nb_lo), np.minimum(np.asarray(high), nb_hi)
            self.first, self.own = _gather_index(B * N, N, self.K)
        self.low, self.high, self.scale = low, high, swarm.obs_scale
        self.floor = cfg.obs_self == "floor"
        self._alloc()

    def _alloc(self) -> None:
        """Work blocks and their views (made again in a copy: a deep copy does not keep views)."""
        B, N, T = self.B, self.N, self.T
        self.V = np.zeros((4, 5, B, N))  # the norm block, components on axis 0 (padding stays 0.0)
        self.V_goal = self.V[:3, 0].transpose(1, 2, 0)  # (B, N, 3) views of the rows
        self.V_act = self.V[:, 1].transpose(1, 2, 0)
        self.V_omega, self.V_vel = self.V[:3, 2].transpose(1, 2, 0), self.V[:3, 3].transpose(1, 2, 0)
        self.V_df = self.V[:, 4].transpose(1, 2, 0)
        self.SQ = np.empty((4, 5, B, N))
        self.S = np.empty((5, B, N))
        self.C = np.zeros((T, B, N))  # costs, rewards.TERMS order (rows of -0.0 terms stay 0.0)
        self.C_norm3 = self.C[0:3]  # pos, effort, spin
        self.C_norm2 = self.C[5:7]  # vel, action_change
        self.acc = np.empty((T, B, N))
        self.key = np.empty((B, N, N))
        self.pv = np.empty((B * N, 6))
        self.pv_p, self.pv_v = self.pv[:, :3].reshape(B, N, 3), self.pv[:, 3:].reshape(B, N, 3)
        self.mpos = np.empty((B, N, 3))
        W, d0, K = np.empty((B, N, self.D)), self.self_dim, self.K
        self._o = SimpleNamespace(W=W, pos=W[..., 0:3], vel=W[..., 3:6], R=W[..., 6:15], omega=W[..., 15:18],
                                  z=W[..., 18] if self.floor else None, nb=W[..., d0:d0 + 6 * K].reshape(B, N, K, 6),
                                  deck=W[..., d0 + 6 * K:])
        if K > 0:
            self._o.first = self.first.reshape(B, N, 1)  # quad 0's row of each world
            self._o.own = self.own.reshape(B, N, K)  # each row's own index, K times
        # constant operands of the full shape of the other operand (NumPy calls on same-shape contiguous arrays cost
        # less than ones that broadcast or convert a Python float), the rotation's diagonal gathered in one take
        self.diag = np.empty((3, B, N))
        self.diag_idx = (9 * np.arange(B * N) + np.array([[0], [4], [8]])).reshape(3, B, N)
        live, C, row, S = self.live, self.C, self.row, self.S
        v = {k: (C[row[k]] if k in live else None) for k in ("crash", "orient", "yaw", "rot", "quad_collision",
                                                            "proximity")}
        self._w = SimpleNamespace(  # the views of the reward's rows, made once, and which of them are live
            SQ=self.SQ, SQ0=self.SQ[0], SQ1=self.SQ[1], SQ2=self.SQ[2], SQ3=self.SQ[3], S=S, S3=S[:3], S2=S[3:],
            norm2="vel" in live or "action_change" in live, C0=C[0], pos_off="pos" not in live, crash=v["crash"],
            diag=any(k in live for k in ("orient", "yaw", "rot")), orient=v["orient"], yaw=v["yaw"], rot=v["rot"],
            d0=self.diag[0], d1=self.diag[1], d2=self.diag[2], qc=v["quad_collision"], prox=v["proximity"],
            key="proximity" in live or self.K > 0, out_shape=(T + 1, B, N), acc_last=self.acc[-1],
            hits=[(C[row[n]], "hit_" + n[:-4]) for n in ("floor_hit", "wall_hit", "ceiling_hit") if n in live])
        self.no_jump = _no_jump((B, N))
        self.c = SimpleNamespace(one=np.ones(()), two=np.full((), 2.0), neg_one=np.full((), -1.0),
                                 dt=np.full((), self.dt), reach=np.full((), metrics_lib.REACH_DISTANCE),
                                 falloff=np.full((), self.falloff), diag_inf=np.where(off_diagonal(N), 0.0, np.inf)
                                 * np.ones((B, 1, 1)),
                                 coef=np.broadcast_to(self.coef, (T, B, N)).copy(), far=np.empty((B, N, N), bool),
                                 low=np.broadcast_to(self.low, (B, N, self.D)).copy(),
                                 high=np.broadcast_to(self.high, (B, N, self.D)).copy())

    _KEEP = ("cfg", "B", "N", "zero_terms", "dt", "episode_steps", "grace", "terms", "T", "factors", "row", "live",
             "annealed", "coef", "falloff", "offdiag", "K", "self_dim", "D", "low", "high", "scale",
             "floor", "first", "own")

    def __getstate__(self) -> dict[str, Any]:
        return {k: self.__dict__[k] for k in self._KEEP if k in self.__dict__}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._alloc()

    def _coef(self, anneal: Any) -> np.ndarray:
        """(T, 1, 1) factors: -dt * scale (annealed: -dt * (scale * anneal)), -0.0 for the -0.0 terms."""
        out = []
        for k, neg_dt, base in self.factors:
            if base is None:
                out.append(-0.0)
            elif k in rewards.ANNEALED:
                out.append(neg_dt * (base * anneal))
            else:
                out.append(neg_dt * base)
        return np.array(out, dtype=np.float64).reshape(-1, 1, 1)

    def __call__(self, cfg: Any, scenario: Any, s: dict[str, Any], k: dict[str, Any], action: Any,
                 consts: dict[str, Any], ops: Any) -> dict[str, Any] | None:
        """``task_step``'s result (the same values), or None where this form does not apply (a float32
        action, other constants than this engine's: the caller runs ``task_step``)."""
        if cfg is not self.cfg or action.dtype != np.float64 or consts["zero_terms"] != self.zero_terms:
            return None
        steps, total_steps = s["steps"] + 1, s["total_steps"] + 1
        t = np.multiply(steps, self.c.dt)  # = steps.astype(float64) * dt
        anneal = rewards.anneal_factor(cfg, total_steps) if self.annealed else 1.0  # (read only when annealed)
        prev = s["sstate"]
        pos, vel, R, omega = k["pos"], k["vel"], k["R"], k["omega"]
        sstate = scenario.step(cfg, prev, t, pos, ops.draws("scenario", None, None))
        goals, goal_vel = sstate.goals, sstate.goal_vel
        if goals is prev.goals:
            jump = self.no_jump
        else:
            jump = metrics_lib.goal_jump(prev.goals, goals, goal_vel, self.dt)
        new_contact = k["new_contact"]
        any_new = _count_nonzero(new_contact) > 0
        out, dist_goal = self._rewards(s, k, action, goals, anneal, any_new)
        hf, hw, hc = k["hit_floor"], k["hit_wall"], k["hit_ceiling"]
        m = self._metrics(s["metrics_acc"], t[..., None], dist_goal, new_contact, any_new, hf, hw, hc, jump)
        obs = self._obs(pos, vel, R, omega, goals, ops.draws("sensor", None, None), k["dist"],
                        ops.draws("deck", None, None) if self.cfg.sensors.any else None)  # (decks off: no draw)
        return {"steps": steps, "total_steps": total_steps, "t": t, "sstate": sstate, "goals": goals,
                "goal_vel": goal_vel, "terms": dict(zip(self.terms, out[1:])), "reward": out[0], "metrics_acc": m,
                "obst_metrics": None, "obs": obs, "done": steps >= self.episode_steps, "rows": out}

    def _rewards(self, s: dict[str, Any], k: dict[str, Any], action: np.ndarray, goals: np.ndarray, anneal: Any,
                 any_new: bool) -> tuple[np.ndarray, np.ndarray]:
        """:func:`quadswarm_mj.rewards.reward_terms` and ``total_reward`` (same values) and the goal distance:
        returns a fresh (1 + T, B, N) block (the reward, then the terms in ``rewards.TERMS`` order) and the
        distance (B, N) m; sets ``self.key`` (the pair distances, inf on the diagonal) for :meth:`_obs`."""
        live, C, w = self.live, self.C, self._w
        pos, R = k["pos"], k["R"]
        # the norms (rewards.reward_terms' norm_last costs and task_stage's goal distance)
        np.subtract(goals, pos, out=self.V_goal)
        if "effort" in live:
            _clip(action, self.c.neg_one, self.c.one, self.V_act)  # = min(max(a, -1), 1) (bounds not zero: same bits)
        if "spin" in live:
            _copyto(self.V_omega, k["omega"])
        if "vel" in live:
            _copyto(self.V_vel, k["vel"])
        if "action_change" in live:
            np.subtract(k["f_norm"], s["f_norm"], out=self.V_df)
        np.multiply(self.V, self.V, w.SQ)
        np.add(w.SQ0, w.SQ1, w.S)
        np.add(w.S, w.SQ2, w.S)
        np.add(w.S, w.SQ3, w.S)
        np.sqrt(w.S3, self.C_norm3)
        if w.norm2:
            np.sqrt(w.S2, self.C_norm2)
        dist_goal = w.C0.copy()
        if w.pos_off:  # a -0.0 term: its cost stays 0.0
            w.C0[...] = 0.0
        on_floor, c, diag = k["on_floor"], self.c, self.diag
        if w.crash is not None:
            _copyto(w.crash, on_floor)
        if w.diag:  # R00, R11, R22
            R.reshape(-1).take(self.diag_idx, None, diag, "wrap")
        if w.orient is not None:
            np.negative(w.d2, w.orient)
            _copyto(w.orient, c.one, where=on_floor)
        if w.yaw is not None:
            np.negative(w.d0, w.yaw)
        if w.rot is not None:  # -(R00 + R11 + R22 - 1.0) / 2.0
            r = w.rot
            np.add(w.d0, w.d1, r)
            np.add(r, w.d2, r)
            np.subtract(r, c.one, r)
            np.negative(r, r)
            np.divide(r, c.two, r)
        if w.qc is not None:
            if any_new:
                np.add.reduce(k["new_contact"], axis=-1, dtype=np.float64, out=w.qc)
            else:
                w.qc[...] = 0.0
        key = self.key
        if w.key:  # the pair distances with inf on the diagonal: dist + 0.0 is dist (never -0.0), 0.0 + inf is inf
            np.add(k["dist"], c.diag_inf, key)
        if w.prox is not None:
            if _count_nonzero(np.greater_equal(key, c.falloff, c.far)) == key.size:  # no pair within: +0.0
                w.prox[...] = 0.0
            else:
                np.add.reduce(np.maximum(1.0 - key / self.falloff, 0.0), axis=-1, out=w.prox)
        for row, name in w.hits:
            _copyto(row, k[name])
        coef = self._coef(anneal) if self.annealed else c.coef
        out = np.empty(w.out_shape)  # reward, then the terms
        terms = out[1:]
        np.multiply(C, coef, terms)
        np.add.accumulate(terms, axis=0, out=self.acc)  # rewards.total_reward's running sum, TERMS order
        _copyto(out[0], w.acc_last)
        return out, dist_goal

    def _metrics(self, m: dict[str, Any], t: Any, dist: np.ndarray, new_contact: np.ndarray, any_new: bool,
                 hit_floor: np.ndarray, hit_wall: np.ndarray, hit_ceiling: np.ndarray, jump: np.ndarray
                 ) -> dict[str, Any]:
        """:func:`quadswarm_mj.metrics.update` (same values); accumulators no event changes are kept."""
        out = dict(m)
        if any_new:
            out["collisions"] = m["collisions"] + new_contact.sum(axis=-1, dtype=np.float64) * (t >= self.grace)
        for name, flag in (("floor_hits", hit_floor), ("wall_hits", hit_wall), ("ceiling_hits", hit_ceiling)):
            if _count_nonzero(flag):
                out[name] = m[name] + flag
        out["dist_sum"] = m["dist_sum"] + dist
        out["steps"] = np.add(m["steps"], self.c.one)
        last = m["last_dist"]
        new_last = np.empty_like(last)
        new_last[..., :-1, :] = last[..., 1:, :]
        new_last[..., -1, :] = dist
        out["last_dist"] = new_last
        reached = m["seg_reached"]
        near = np.less(dist, self.c.reach)
        if _count_nonzero(jump):
            close = jump & ((t - m["seg_start"]) >= metrics_lib.MIN_SEGMENT_S - 1e-9)
            out["seg_count"] = m["seg_count"] + close
            out["seg_success"] = m["seg_success"] + (close & reached)
            out["seg_start"] = np.where(jump, t, m["seg_start"])
            out["seg_reached"] = near | (reached & ~jump)
        else:
            out["seg_reached"] = near | reached
        return out

    def _obs(self, pos: np.ndarray, vel: np.ndarray, R: np.ndarray, omega: np.ndarray, goals: np.ndarray,
             noise: dict[str, Any] | None, dist: np.ndarray, deck_draws: dict[str, Any] | None) -> np.ndarray:
        """:func:`quadswarm_mj.observations.build_obs` (same values) for this layout."""
        B, N, o = self.B, self.N, self._o
        W = o.W  # the observation before its bounds, written part by part into views made once
        mpos = self.mpos
        if noise is not None:
            np.add(pos, noise["pos"], mpos)
            np.subtract(mpos, goals, o.pos)
            np.add(vel, noise["vel"], o.vel)
            _copyto(o.R, R.reshape(B, N, 9))
            np.add(omega, noise["omega"], o.omega)
        else:
            mpos = pos
            np.subtract(pos, goals, o.pos)
            _copyto(o.vel, vel)
            _copyto(o.R, R.reshape(B, N, 9))
            _copyto(o.omega, omega)
        if self.floor:
            _copyto(o.z, mpos[..., 2])
        K = self.K
        if K > 0:  # observations.neighbor_obs: the K nearest others by distance (key: self.key, set above)
            _copyto(self.pv_p, pos)
            _copyto(self.pv_v, vel)
            idx = self.key.argsort(axis=-1)[..., :K]  # (B, N, K) quad indices in their world
            if B > 1:
                idx = idx + o.first
            np.subtract(self.pv.take(idx, axis=0), self.pv.take(o.own, axis=0), o.nb)
        if self.cfg.sensors.any:  # the decks' readings of the true state, last
            numpy_deck.deck_part(self.cfg, pos, vel, R, omega, None, deck_draws, o.deck)
        obs = _clip(W, self.c.low, self.c.high)  # fresh; = min(max(obs, low), high) on same-shape bounds: same bits
        return obs if self.scale is None else obs / self.scale
