"""The s_t plot of a temporal localization (matplotlib, written atomically)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..fileio import atomic_path
from .results import TemporalResult


def plot_temporal(result: TemporalResult, path: str | Path, *, query: str = "", overwrite: bool = False) -> Path:
    """PNG of s_t over time with the threshold 1/T, the positive segments and the peak."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = np.asarray(result.scores, dtype=np.float64)
    T = len(s)
    fig, ax = plt.subplots(figsize=(8, 3), dpi=100)
    try:
        ax.plot(np.arange(T), s, color="tab:blue", lw=1.5, label="$s_t$")
        if T:
            ax.axhline(1.0 / T, color="gray", ls="--", lw=1, label="threshold 1/T")
        for i, (a, b) in enumerate(result.segments):
            ax.axvspan(a - 0.5, b + 0.5, color="tab:orange", alpha=0.15 if (a, b) != result.segment else 0.35,
                       label="segment" if (a, b) == result.segment else ("other segments" if i == 0 else None))
        if result.peak is not None:
            ax.axvline(result.peak, color="tab:red", lw=1.2, label=f"peak t={result.peak}")
        ax.set_xlim(-0.5, max(T - 0.5, 0.5))
        ax.set_xlabel("timestep t")
        ax.set_ylabel("$s_t$")
        title = f'"{query}"' if query else "temporal localization"
        ax.set_title(title if result.found else f"{title}: not found")
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            ax.legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        path = Path(path)
        with atomic_path(path, overwrite=overwrite) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return path
