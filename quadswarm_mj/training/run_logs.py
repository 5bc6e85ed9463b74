"""Run outputs of the PPO trainers: the start of a run (output directory, earlier rows of a resumed run,
the progress bar), ``progress.json`` / ``progress.csv`` (:func:`write_logs`) and ``curves.png``
(:func:`plot_curves`, matplotlib optional). NumPy only.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def start_run(out_dir: str | Path | None, history: list[dict[str, Any]] | None, total_steps: int | None,
              seconds: float | None, progress: bool) -> tuple[Path | None, list[dict[str, Any]], float, Any]:
    """Common start of both trainers' ``train``: the output directory (``checkpoints/`` created), the
    earlier log rows of a resumed run, their wall time (s) and the ProgressBar (None without progress)."""
    if total_steps is None and seconds is None:
        raise ValueError("give a budget: total_steps and/or seconds")
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = list(history or [])
    wall0 = float(rows[-1]["wall_s"]) if rows else 0.0
    bar = None
    if progress:  # one \r-updated line on a terminal, a line every 10 s otherwise (training/progress.py)
        from quadswarm_mj.training.progress import ProgressBar

        bar = ProgressBar(total_steps, seconds)
    return out, rows, wall0, bar


def write_logs(out: Path, rows: list[dict[str, Any]]) -> None:
    """``progress.json`` (list of rows) and ``progress.csv`` (one column per key)."""
    out = Path(out)
    (out / "progress.json").write_text(json.dumps(rows, allow_nan=True))
    if not rows:
        return
    keys = list(rows[0])
    for r in rows[1:]:
        keys += [k for k in r if k not in keys]
    lines = [",".join(keys)]
    for r in rows:
        lines.append(",".join("" if r.get(k) is None else str(r.get(k)) for k in keys))
    (out / "progress.csv").write_text("\n".join(lines) + "\n")


def _smooth_metric(rows: list[dict[str, Any]], key: str, window: int) -> np.ndarray:
    """Episode-weighted mean of ``key`` over the last ``window`` rows (NaN where no episode ended)."""
    scn = key.split("/")[0]
    vals = np.array([r.get(key, np.nan) for r in rows], float)
    cnt = np.array([r.get(f"{scn}/episodes", 0) for r in rows], float)
    ok = np.isfinite(vals) & (cnt > 0)
    num = np.convolve(np.where(ok, vals * cnt, 0.0), np.ones(window))[: len(rows)]
    den = np.convolve(np.where(ok, cnt, 0.0), np.ones(window))[: len(rows)]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def plot_curves(progress_json: str | Path, png: str | Path, title: str | None = None,
                window: int | None = None, marks: list[tuple[float, str]] | None = None) -> None:
    """Reward and episode-metric curves vs agent-steps (matplotlib, Agg). Episode metrics are
    averaged over the episodes that ended in the last ``window`` iterations (default: about
    1/60 of the run, at least 10), weighted by episode count. ``marks``: (agent-steps, label)
    vertical lines, e.g. the checkpoint that was shipped."""
    try:  # optional: without matplotlib the run goes on without curves
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    rows = json.loads(Path(progress_json).read_text())
    if not rows:
        return
    window = min(window or max(10, len(rows) // 60), len(rows))
    x = np.array([r["env_steps"] for r in rows], float) / 1e6
    wall = np.array([r["wall_s"] for r in rows], float) / 60
    scns = list(dict.fromkeys(k.split("/")[0] for r in rows[:1] for k in r if "/" in k))
    panels = [("reward_per_step", "reward per agent-step"), ("success", "success rate"),
              ("goal_reach_rate", "goal-reach rate"), ("collisions", "collisions / quad / episode"),
              ("mean_distance", "mean distance to goal (m)"), ("floor_hits", "floor hits / quad / episode"),
              ("wall_hits", "wall hits / quad / episode"), ("_time", "wall time (min)")]
    fig, axes = plt.subplots(2, 4, figsize=(17, 7.5))
    for ax, (key, label) in zip(axes.ravel(), panels):
        if key == "reward_per_step":
            y = np.array([r[key] for r in rows], float)
            ax.plot(x, y, lw=0.5, alpha=0.4, color="C0")
            k = np.ones(window) / window
            ax.plot(x[window - 1:], np.convolve(y, k, mode="valid"), lw=1.5, color="C0")
        elif key == "_time":
            ax.plot(x, wall, lw=1.5, color="k")
            ax.set_ylabel("min")
        else:
            for i, s in enumerate(scns):
                y = _smooth_metric(rows, f"{s}/{key}", window)
                ok = np.isfinite(y)
                if ok.any():
                    ax.plot(x[ok], y[ok], lw=1.5, color=f"C{i + 1}", label=s)
            if key in ("success", "goal_reach_rate"):
                ax.set_ylim(-0.02, 1.02)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
        for steps, lab in marks or []:
            ax.axvline(steps / 1e6, color="k", ls="--", lw=1)
            if key == "reward_per_step":
                ax.annotate(lab, (steps / 1e6, 0.02), xycoords=("data", "axes fraction"), fontsize=7,
                            rotation=90, ha="right", va="bottom")
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("agent-steps (M)")
        ax.grid(alpha=0.3)
    fig.suptitle(title or f"{Path(progress_json).parent.name}: {rows[-1]['env_steps'] / 1e6:.1f} M agent-steps in "
                 f"{rows[-1]['wall_s'] / 60:.1f} min (stochastic training policy; episode metrics averaged over "
                 f"{window} iterations)", fontsize=11)
    fig.tight_layout()
    fig.savefig(png, dpi=80)
    plt.close(fig)
