"""Progress a person can follow: one status line per training run.

:class:`ProgressBar` shows agent-steps, agent-steps/s, elapsed and remaining wall time and the current
episode metrics (per scenario: success, goal-reach rate, mean distance, collisions, floor hits of the
episodes that ended recently). On a terminal (``stream.isatty()``) it redraws one line with ``\\r``; otherwise
(a log file, a pipe, ``nohup``) it prints a full line every ``every_s`` seconds of wall time and at the end.
No dependency beyond the standard library.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, TextIO

#: episode metrics shown per scenario (short labels), in this order when present
SHOWN = (
    ("success", "succ", "{:.2f}"),
    ("goal_reach_rate", "reach", "{:.2f}"),
    ("mean_distance", "dist", "{:.2f} m"),
    ("collisions", "coll", "{:.3f}"),
    ("floor_hits", "floor", "{:.2f}"),
    ("replay_rate", "replay", "{:.2f}"),
)


def fmt_time(s: float) -> str:
    """Seconds as m:ss or h:mm:ss ('?' when unknown)."""
    if s is None or not math.isfinite(s) or s < 0:
        return "?"
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def fmt_steps(n: float) -> str:
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(n) >= div:
            return f"{n / div:.2f} {unit}"
    return f"{n:.0f}"


class ProgressBar:
    """``update(row)`` with each logged row of a trainer (keys ``env_steps``, ``<scenario>/<metric>``,
    ``reward_per_step``); ``close()`` at the end. ``total_steps`` / ``seconds``: this run's budget (either
    may be None); ``steps0``: agent-steps before this run (resumed runs); ``tty``: force the mode (default
    ``stream.isatty()``); ``every_s``: seconds between lines when not on a terminal. Episode metrics are
    averaged over the episodes of the last ``window`` rows that had any (weighted by their count)."""

    def __init__(
        self,
        total_steps: int | None = None,
        seconds: float | None = None,
        steps0: int = 0,
        stream: TextIO | None = None,
        tty: bool | None = None,
        every_s: float = 10.0,
        window: int = 20,
        width: int = 20,
    ):
        self.total_steps, self.seconds, self.steps0 = total_steps, seconds, int(steps0)
        self.stream = stream if stream is not None else sys.stdout
        if tty is None:
            isatty = getattr(self.stream, "isatty", None)
            tty = bool(isatty()) if callable(isatty) else False
        self.tty, self.every_s, self.window, self.width = tty, float(every_s), int(window), int(width)
        self.t0 = time.perf_counter()
        self._last_print = -math.inf
        self._recent: list[dict[str, Any]] = []
        self._line_len = 0

    # ------------------------------------------------------------------ formatting
    def fraction(self, steps: int, elapsed: float) -> float:
        f = 0.0
        if self.total_steps:
            f = max(f, (steps - self.steps0) / self.total_steps)
        if self.seconds:
            f = max(f, elapsed / self.seconds)
        return min(max(f, 0.0), 1.0)

    def remaining(self, steps: int, elapsed: float, rate: float) -> float:
        """Seconds left: the earlier of the wall-clock budget and the step budget at the current rate."""
        left = math.inf
        if self.seconds:
            left = min(left, self.seconds - elapsed)
        if self.total_steps and rate > 0:
            left = min(left, (self.total_steps - (steps - self.steps0)) / rate)
        return max(left, 0.0)

    def metrics(self) -> dict[str, dict[str, float]]:
        """Per scenario: episode-weighted means of the shown metrics over the recent rows."""
        out: dict[str, dict[str, float]] = {}
        for row in self._recent:
            for key, v in row.items():
                if "/" not in key or not isinstance(v, (int, float)) or not math.isfinite(v):
                    continue
                scn, name = key.split("/", 1)
                if name not in dict((k, 1) for k, _, _ in SHOWN):
                    continue
                n = row.get(f"{scn}/episodes", 1) if name != "replay_rate" else 1
                if not n:
                    continue
                acc = out.setdefault(scn, {}).setdefault(name, [0.0, 0.0])
                acc[0] += v * n
                acc[1] += n
        return {s: {k: a / b for k, (a, b) in d.items() if b > 0} for s, d in out.items()}

    def format(self, row: dict[str, Any], elapsed: float) -> str:
        steps = int(row.get("env_steps", 0))
        rate = (steps - self.steps0) / max(elapsed, 1e-9)
        frac = self.fraction(steps, elapsed)
        fill = int(round(frac * self.width))
        parts = [
            f"[{'#' * fill}{'.' * (self.width - fill)}] {100 * frac:3.0f}%",
            f"{fmt_steps(steps)} agent-steps",
            f"{fmt_steps(rate)}/s",
            f"{fmt_time(elapsed)} elapsed, {fmt_time(self.remaining(steps, elapsed, rate))} left",
        ]
        if "reward_per_step" in row:
            parts.append(f"r/step {row['reward_per_step']:.4f}")
        for scn, vals in self.metrics().items():
            shown = [f"{lab} {f.format(vals[k])}" for k, lab, f in SHOWN if k in vals]
            if shown:
                parts.append(f"{scn}: " + " ".join(shown))
        return " | ".join(parts)

    # ------------------------------------------------------------------ output
    def update(self, row: dict[str, Any], force: bool = False) -> None:
        self._recent = [r for r in self._recent[-(self.window - 1) :]] + [row] if self.window > 1 else [row]
        elapsed = time.perf_counter() - self.t0
        if not (force or self.tty or elapsed - self._last_print >= self.every_s):
            return
        self._last_print = elapsed
        line = self.format(row, elapsed)
        if self.tty:
            pad = max(self._line_len - len(line), 0)
            self.stream.write("\r" + line + " " * pad)
            self._line_len = len(line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self, row: dict[str, Any] | None = None) -> None:
        """Print the final state (``row``: the last row, if any) and end the line."""
        if row is not None:
            self._recent = self._recent[:-1] if self._recent and self._recent[-1] is row else self._recent
            self.update(row, force=True)
        if self.tty and self._line_len:
            self.stream.write("\n")
            self.stream.flush()
            self._line_len = 0
