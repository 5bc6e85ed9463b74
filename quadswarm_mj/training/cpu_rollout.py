"""The CPU trainer's rollout batch: one ``CpuSwarm`` (the batched MuJoCo C engine) per training scenario,
seen as one flat batch of agents (every quad is an agent).

Episodes end by truncation only. So that episode ends are spread over iterations, the first episode of
every world is truncated early, after a random number of steps in [1, episode_steps]
(:attr:`AgentBatch.first_len`); its scenario starts at t = 0 as every episode does (no scenario clock is
moved, so time-driven goal changes happen at their times). The metrics of these first, shortened episodes
are not logged. NumPy and MuJoCo only (no JAX).
"""

from __future__ import annotations

import numpy as np

from quadswarm_mj.config import EnvConfig
from quadswarm_mj.envs.cpu_core import CpuSwarm


class AgentBatch:
    """One ``CpuSwarm`` per scenario, seen as one flat batch of A = sum(B_k * N) agents.

    ``cfgs`` must agree on ``num_quads`` and ``obs_dim``; ``worlds`` gives B_k per engine.
    Observations are float32 (A, obs_dim); rewards (A,) are the per-quad rewards.
    """

    def __init__(self, cfgs: list[EnvConfig], worlds: list[int], seed: int, desync: bool = True):
        if not cfgs or len(cfgs) != len(worlds):
            raise ValueError("need one world count per scenario config")
        n, d = cfgs[0].num_quads, cfgs[0].obs_dim
        for c in cfgs:
            if c.num_quads != n or c.obs_dim != d:
                raise ValueError("all training scenarios must share num_quads and the observation layout")
        self.cfgs, self.N, self.obs_dim = cfgs, n, d
        self.engines = [CpuSwarm(c, b) for c, b in zip(cfgs, worlds)]
        for k, e in enumerate(self.engines):
            e.seed(seed * 1000 + k)
            e.reset()
            got = e.observe().shape[-1]
            if got != d:
                raise ValueError(f"the MuJoCo engine's observation has {got} features, the config needs {d}")
            e.seed(seed * 1000 + k)  # the check's reset leaves the seeded streams as before
        self.sizes = [e.B * n for e in self.engines]
        self.num_agents = sum(self.sizes)
        self.desync = desync
        self.rng = np.random.default_rng(seed)
        self.ep_return = [np.zeros((e.B, n)) for e in self.engines]
        self.first = [np.ones(e.B, bool) for e in self.engines]
        #: (B_k,) control steps after which the first episode of each world is truncated.
        self.first_len = [np.full(e.B, e.cfg.episode_steps, np.int64) for e in self.engines]

    def reset(self) -> np.ndarray:
        for k, e in enumerate(self.engines):
            e.reset()
            self.first[k][:] = True
            steps = e.cfg.episode_steps
            self.first_len[k] = (self.rng.integers(1, steps + 1, size=e.B).astype(np.int64) if self.desync
                                 else np.full(e.B, steps, np.int64))
            self.ep_return[k][:] = 0.0
        return self.observe()

    def observe(self) -> np.ndarray:
        return np.concatenate([e.observe().reshape(-1, self.obs_dim) for e in self.engines]).astype(np.float32)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list]:
        """Step every engine; worlds whose episode ended are reset.

        Returns (next_obs before resets, rewards, truncation flags, obs to act on next, finished)
        where ``finished`` lists (scenario, metrics dict of (n_done,) arrays, returns (n_done,)).
        """
        a = np.asarray(actions, dtype=np.float64)
        next_obs, rew, trunc, cont, finished = [], [], [], [], []
        i = 0
        for k, e in enumerate(self.engines):
            ak = a[i:i + self.sizes[k]].reshape(e.B, self.N, 4)
            i += self.sizes[k]
            out = e.step(ak)
            o = out["obs"].reshape(-1, self.obs_dim)
            r = out["rewards"]
            self.ep_return[k] += r
            # a world's first episode may be cut short (desynchronization); the engine's own time
            # limit ends every other episode
            done = np.asarray(out["truncated"], bool) | (self.first[k] & (e.steps >= self.first_len[k]))
            next_obs.append(o)
            rew.append(r.reshape(-1))
            trunc.append(np.repeat(done, self.N))
            if done.any():
                log = done & ~self.first[k]
                if log.any():
                    m = e.episode_metrics()
                    finished.append((e.cfg.scenario, {key: np.asarray(v)[log] for key, v in m.items()},
                                     self.ep_return[k][log].mean(-1)))
                self.first[k] &= ~done
                self.ep_return[k][done] = 0.0
                e.reset(mask=done)
                cont.append(e.observe().reshape(-1, self.obs_dim))
            else:
                cont.append(o)
        return (np.concatenate(next_obs).astype(np.float32), np.concatenate(rew).astype(np.float32),
                np.concatenate(trunc).astype(np.float32), np.concatenate(cont).astype(np.float32), finished)
