"""Markdown tables and PNG plots of benchmark results."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .metrics import THRESHOLDS


def _pct(value) -> str:
    return "-" if value is None else f"{100 * value:.2f}"


def homography_markdown(results: dict) -> str:
    """One row per method: Avg.HA@1:10 overall / i / v, HA@1/3/5, MMA@3, repeatability, matches, time."""
    config = results["config"]
    lines = [
        f"Homography estimation on {len(results['sequences'])} sequences "
        f"(long side <= {config['resize_max'] or 'full'} px, top {config['max_keypoints']} keypoints, mutual NN, "
        "OpenCV RANSAC). Percentages.",
        "",
        "| method | Avg.HA@1:10 | i | v | HA@1 | HA@3 | HA@5 | MMA@3 | rep@3 | matches | ms/image |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, entry in results["methods"].items():
        if "error" in entry:
            lines.append(f"| {label} | failed: {entry['error']} |" + " |" * 9)
            continue
        s = entry["summary"]
        ha = s["ha_all"]
        lines.append(
            f"| {label} | {_pct(s['avg_ha_all'])} | {_pct(s['avg_ha_i'])} | {_pct(s['avg_ha_v'])} | "
            f"{_pct(ha[0])} | {_pct(ha[2])} | {_pct(ha[4])} | {_pct(s['mma'][2])} | {_pct(s['repeatability'])} | "
            f"{s['matches']:.0f} | {1000 * entry['seconds_per_image']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def plot_curves(results: dict, output: Path) -> list[Path]:
    """homography_accuracy.png (overall / i / v, as the paper's Fig. 4) and mma.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = {k: v["summary"] for k, v in results["methods"].items() if "summary" in v}
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), sharey=True)
    for ax, subset, title in zip(axes, ("all", "i", "v"), ("Overall", "Illumination", "Viewpoint")):
        for label, s in methods.items():
            if s[f"pairs_{subset}"]:
                ax.plot(THRESHOLDS, s[f"ha_{subset}"], marker="o", ms=3, label=f"{label} ({100 * s[f'avg_ha_{subset}']:.1f})")
        ax.set(title=title, xlabel="corner error threshold (px)", ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=7)
    axes[0].set_ylabel("homography accuracy")
    paths = [output / "homography_accuracy.png", output / "mma.png"]
    fig.tight_layout()
    fig.savefig(paths[0], dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 4))
    for label, s in methods.items():
        ax.plot(THRESHOLDS, s["mma"], marker="o", ms=3, label=label)
    ax.set(xlabel="threshold (px)", ylabel="mean matching accuracy", ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(paths[1], dpi=110)
    plt.close(fig)
    return paths
