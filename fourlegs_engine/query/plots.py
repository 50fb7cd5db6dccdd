"""The s_t plots of a temporal localization (matplotlib, written atomically)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

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


def write_scores_plot(path: str | Path, scores: Sequence[float], positive: Sequence[bool],
                      segment: Optional[Sequence[int]], peak: Optional[int], query: str) -> None:
    """PNG of s_t per timestep as bars (positive ones highlighted), the threshold 1/T, segment and peak:
    the main job's scores.png, drawn from a plan's ``localization``. Replaces ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = list(scores)
    T = len(s)
    fig, ax = plt.subplots(figsize=(8, 3), dpi=100)
    try:
        colours = ["tab:orange" if p else "tab:gray" for p in positive]
        ax.bar(range(T), s, color=colours, width=0.9)
        if T:
            ax.axhline(1.0 / T, color="black", lw=0.8, ls="--", label="k = 1/T")
        if segment is not None:
            ax.axvspan(segment[0] - 0.5, segment[1] + 0.5, color="tab:blue", alpha=0.15, label="segment")
        if peak is not None:
            ax.axvline(peak, color="tab:red", lw=1.2, label="peak")
        ax.set_xlabel("timestep t")
        ax.set_ylabel("s_t")
        ax.set_title(f"temporal relevancy: {query!r}")
        ax.legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        with atomic_path(Path(path)) as tmp:
            fig.savefig(tmp)
    finally:
        plt.close(fig)
