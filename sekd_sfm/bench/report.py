"""Markdown tables and PNG plots of benchmark results."""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from .metrics import THRESHOLDS


def _pct(value) -> str:
    return "-" if value is None else f"{100 * value:.2f}"


def _method_table(results: dict, title: str, columns: list[str], cells) -> str:
    """Markdown: ``title``, then one row per method of ``results`` (``cells(entry)``; failed methods say why)."""
    lines = [title, "", "| method | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for label, entry in results["methods"].items():
        if "error" in entry:
            lines.append(f"| {label} | failed: {entry['error']} |" + " |" * (len(columns) - 1))
        else:
            lines.append(f"| {label} | " + " | ".join(cells(entry)) + " |")
    return "\n".join(lines) + "\n"


def homography_markdown(results: dict) -> str:
    """One row per method: Avg.HA@1:10 overall / i / v, HA@1/3/5, MMA@3, repeatability, matches, time."""
    config = results["config"]
    title = (f"Homography estimation on {len(results['sequences'])} sequences "
             f"(long side <= {config['resize_max'] or 'full'} px, top {config['max_keypoints']} keypoints, mutual NN, "
             "OpenCV RANSAC). Percentages.")
    columns = ["Avg.HA@1:10", "i", "v", "HA@1", "HA@3", "HA@5", "MMA@3", "rep@3", "matches", "ms/image"]

    def cells(entry: dict) -> list[str]:
        s = entry["summary"]
        ha = s["ha_all"]
        return [_pct(s["avg_ha_all"]), _pct(s["avg_ha_i"]), _pct(s["avg_ha_v"]), _pct(ha[0]), _pct(ha[2]),
                _pct(ha[4]), _pct(s["mma"][2]), _pct(s["repeatability"]), f"{s['matches']:.0f}",
                f"{1000 * entry['seconds_per_image']:.0f}"]

    return _method_table(results, title, columns, cells)


def _distinct_colours(ax) -> None:
    """20 distinct colours (the default cycle repeats after 10 methods)."""
    import matplotlib.pyplot as plt

    ax.set_prop_cycle(color=plt.cm.tab20.colors)


def plot_curves(results: dict, output: Path) -> list[Path]:
    """homography_accuracy.png (overall / i / v, as the paper's Fig. 4) and mma.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = {k: v["summary"] for k, v in results["methods"].items() if "summary" in v}
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), sharey=True)
    for ax, subset, title in zip(axes, ("all", "i", "v"), ("Overall", "Illumination", "Viewpoint")):
        _distinct_colours(ax)
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
    _distinct_colours(ax)
    for label, s in methods.items():
        ax.plot(THRESHOLDS, s["mma"], marker="o", ms=3, label=label)
    ax.set(xlabel="threshold (px)", ylabel="mean matching accuracy", ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(paths[1], dpi=110)
    plt.close(fig)
    return paths


def pose_markdown(results: dict) -> str:
    """One row per method: mAA@1:10, AUC@5/10/20, median errors, matches, inliers."""
    config = results["config"]
    title = (f"Relative pose on all image pairs of {', '.join(results['scenes'])} (up to {config['max_keypoints']} "
             f"keypoints, long side <= {config['resize_max'] or 'full'} px for extraction, ratio test for float / "
             "mutual NN for binary descriptors, essential matrix RANSAC).")
    columns = ["pairs", "mAA@1:10", "AUC@5", "AUC@10", "AUC@20", "median rot (deg)", "median trans (deg)",
               "matches", "inliers"]

    def cells(entry: dict) -> list[str]:
        s = entry["summary"]
        return [str(s["pairs"]), f"{s['maa']:.3f}", f"{s['auc5']:.3f}", f"{s['auc10']:.3f}", f"{s['auc20']:.3f}",
                f"{s['median_rotation_deg']:.2f}", f"{s['median_translation_deg']:.2f}", f"{s['matches']:.0f}",
                f"{s['inliers']:.0f}"]

    return _method_table(results, title, columns, cells)


def plot_pose(results: dict, output: Path) -> Path:
    """pose_accuracy.png: fraction of pairs with pose error below each threshold (1..10 deg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    _distinct_colours(ax)
    for label, entry in results["methods"].items():
        if "summary" in entry:
            ax.plot(THRESHOLDS, entry["summary"]["accuracy"], marker="o", ms=3, label=f"{label} ({entry['summary']['maa']:.3f})")
    ax.set(xlabel="pose error threshold (deg)", ylabel="accuracy", ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = output / "pose_accuracy.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_results(results: dict, output: Path, markdown: Callable[[dict], str], plot: Callable[[dict, Path], object]) -> Path:
    """results.json (atomically), results.md and the plots of one benchmark run; returns the JSON path."""
    output.mkdir(parents=True, exist_ok=True)
    path = output / "results.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(results, indent=1, default=float))
    tmp.replace(path)
    (output / "results.md").write_text(markdown(results))
    plot(results, output)
    return path
