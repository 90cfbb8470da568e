"""One table and one plot from the three benchmarks' results.json files (homography, pose, SfM).

Each benchmark keeps its own report; this joins them by method label, so every method's
row reads: homography Avg.HA@1:10 overall / i / v (and its mean ± sd over RANSAC runs) and MMA@3,
relative-pose mAA (and its mean ± sd), and SfM
(registered images, pose mAA, median rotation error, wall time).
"""
from __future__ import annotations

import json
from pathlib import Path

from ..files.atomic import write_atomic
from .plotting import save_png

COLUMNS = ("avg_ha_all", "avg_ha_i", "avg_ha_v", "avg_ha_runs", "mma3", "pose_maa", "pose_maa_runs", "sfm_registered",
           "sfm_maa", "sfm_auc1", "sfm_rot_deg", "sfm_time_s")
HEADERS = ("Avg.HA@1:10", "i", "v", "Avg.HA over RANSAC runs", "MMA@3", "pose mAA", "pose mAA over RANSAC runs",
           "SfM registered", "SfM mAA", "SfM AUC@1", "SfM rot. err (deg)", "SfM time (s)")


def _read(path: Path | None) -> dict | None:
    return json.loads(Path(path).read_text()) if path else None


def _homography_rows(results: dict) -> dict[str, dict]:
    rows = {}
    for label, entry in results["methods"].items():
        if "summary" in entry:
            s = entry["summary"]
            rows[label] = {"avg_ha_all": s["avg_ha_all"], "avg_ha_i": s["avg_ha_i"], "avg_ha_v": s["avg_ha_v"],
                           "mma3": s["mma"][2], **_spread(s, "avg_ha_all", "avg_ha_runs")}
    return rows


def _spread(summary: dict, key: str, column: str) -> dict:
    """``{column: (mean, sd)}`` over RANSAC runs when the results have more than one run (older files: {})."""
    if summary.get("ransac_runs", 1) < 2 or summary.get(key + "_mean") is None:
        return {}
    return {column: (summary[key + "_mean"], summary[key + "_sd"])}


def _pose_rows(results: dict) -> dict[str, dict]:
    return {label: {"pose_maa": e["summary"]["maa"], **_spread(e["summary"], "maa", "pose_maa_runs")}
            for label, e in results["methods"].items() if "summary" in e}


def _sfm_rows(results: dict) -> dict[str, dict]:
    images = results["images"]
    return {r["method"]: {"sfm_registered": f"{r['registered_images']}/{images}", "sfm_maa": r.get("maa"),
                          "sfm_auc1": r.get("auc1"), "sfm_rot_deg": r.get("median_rotation_deg"), "sfm_time_s": r["wall_time_s"]}
            for r in results["results"]}


def summary_rows(homography: dict | list | None, pose: dict | list | None, sfm: dict | list | None) -> dict[str, dict]:
    """Method label -> the COLUMNS it has, in the order the methods first appear.

    Each argument is one results dict or a list of them (several runs of one benchmark: a
    later run's row replaces an earlier one's for the same label).
    """
    rows: dict[str, dict] = {}
    for parts, reader in ((homography, _homography_rows), (pose, _pose_rows), (sfm, _sfm_rows)):
        for part in parts if isinstance(parts, list) else [parts] if parts else []:
            for label, values in reader(part).items():
                rows.setdefault(label, {}).update(values)
    return rows


def _cell(key: str, value) -> str:
    if value is None:
        return ""
    if key == "avg_ha_runs":
        return f"{100 * value[0]:.1f} ± {100 * value[1]:.1f}"
    if key == "pose_maa_runs":
        return f"{value[0]:.3f} ± {value[1]:.3f}"
    if key in ("avg_ha_all", "avg_ha_i", "avg_ha_v", "mma3"):
        return f"{100 * value:.1f}"
    if key in ("pose_maa", "sfm_maa", "sfm_auc1", "sfm_rot_deg"):
        return f"{value:.3f}"
    return f"{value:.0f}" if isinstance(value, float) else str(value)


def summary_markdown(rows: dict[str, dict], sources: dict[str, str]) -> str:
    """The joined table; ``sources`` names the results file behind each benchmark."""
    lines = ["| method | " + " | ".join(HEADERS) + " |", "|---|" + "---|" * len(HEADERS)]
    for label, row in rows.items():
        lines.append(f"| {label} | " + " | ".join(_cell(k, row.get(k)) for k in COLUMNS) + " |")
    notes = [f"{name}: {paths}" for name, paths in sources.items() if paths]
    return "\n".join(lines) + "\n\nFrom " + "; ".join(notes) + ".\n"


def plot_summary(rows: dict[str, dict], output: Path, highlight: tuple[str, ...] = ()) -> Path:
    """summary.png: one horizontal bar panel per headline metric, methods in table order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("avg_ha_all", "homography Avg.HA@1:10 (%)", 100), ("mma3", "homography MMA@3 (%)", 100),
              ("pose_maa", "fountain-P11 pose mAA", 1), ("sfm_auc1", "fountain-P11 SfM pose AUC@1", 1)]
    # SfM mAA@1:10 is 1.00 for nearly every method on fountain-P11; AUC@1 still tells them apart.
    labels = list(rows)
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 0.35 * len(labels) + 1.5), sharey=True)
    # Colour-blind-safe (Okabe & Ito): highlighted methods in strong colours, the rest grey.
    accents = dict(zip(highlight, ("#D55E00", "#0072B2", "#009E73", "#CC79A7", "#E69F00")))
    colours = [accents.get(m, "#999999") for m in labels]
    for ax, (key, title, scale) in zip(axes, panels):
        values = [scale * rows[m][key] if rows[m].get(key) is not None else 0.0 for m in labels]
        ax.barh(range(len(labels)), values, color=colours)
        for y, value in enumerate(values):
            if value:
                ax.text(value, y, f" {value:.{0 if scale == 100 else 2}f}", va="center", fontsize=7)
        ax.set_xlim(0, 1.15 * max(values + [1e-9]))
        ax.set_title(title, fontsize=10)
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(range(len(labels)), labels)
    axes[0].invert_yaxis()
    fig.tight_layout()
    path = Path(output) / "summary.png"
    save_png(fig, path, dpi=110)
    plt.close(fig)
    return path


def _paths(value: Path | list | tuple | None) -> list[Path]:
    return [Path(v) for v in value] if isinstance(value, (list, tuple)) else [Path(value)] if value else []


def write_summary(output: Path, homography=None, pose=None, sfm=None, highlight: tuple[str, ...] = ()) -> Path:
    """summary.md and summary.png in ``output``; returns summary.md.

    ``homography``, ``pose``, ``sfm``: a results.json path, or a list of them (later runs
    replace earlier rows of the same method).
    """
    sources = {"homography": _paths(homography), "pose": _paths(pose), "SfM": _paths(sfm)}
    rows = summary_rows(*([_read(p) for p in paths] for paths in sources.values()))
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    path = output / "summary.md"
    write_atomic(path, summary_markdown(rows, {k: ", ".join(f"`{p}`" for p in v) for k, v in sources.items()}))
    plot_summary(rows, output, highlight)
    return path
