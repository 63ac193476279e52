"""The convergence plot of a run: mean episodic reward against env steps (SPEC §6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml


def plot_convergence(run: Path, window: int = 10) -> Path | None:
    """Mean episodic reward against env steps, per AC and their mean (the paper's Figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    csv_path = Path(run) / "episodes.csv"
    if not csv_path.exists():
        return None
    df = pd.read_csv(csv_path)
    if df.empty:
        return None
    fig, ax = plt.subplots(figsize=(7, 4))
    curves = []
    for agent, g in df.groupby("agent"):
        g = g.sort_values("env_step")
        smooth = g["return"].rolling(window, min_periods=1).mean()
        ax.plot(g["env_step"], smooth, lw=1, alpha=0.6, label=agent)
        curves.append(pd.Series(smooth.to_numpy(), index=g["env_step"].to_numpy()))
    grid = np.linspace(df["env_step"].min(), df["env_step"].max(), 100)
    mean = np.nanmean([np.interp(grid, c.index, c.to_numpy()) for c in curves], axis=0)
    ax.plot(grid, mean, color="k", lw=2.5, label="mean")
    cfg = yaml.safe_load((Path(run) / "config.yaml").read_text())
    ax.set_title(f"{cfg['algo'].upper()} on {cfg['env']}: convergence ({window}-episode mean)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episodic reward")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = Path(run) / "convergence.png"
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out
