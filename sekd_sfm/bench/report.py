"""Markdown tables and PNG plots of benchmark results."""
from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

from ..evaluation.metrics import THRESHOLDS
from ..files.atomic import write_atomic
from .plotting import save_png


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
    runs = config.get("ransac_runs", 1)
    if runs > 1:
        title += (f" Avg.HA@1:10 is the paper's single RANSAC run; mean ± sd: over {runs} RANSAC runs on shuffled "
                  "orders of the same matches, to rank methods whose single runs differ by RANSAC's luck.")
    columns = ["Avg.HA@1:10", "i", "v", f"mean ± sd ({runs} runs)", "HA@1", "HA@3", "HA@5", "MMA@3", "rep@3",
               "matches", "ms/image"]

    def cells(entry: dict) -> list[str]:
        s = entry["summary"]
        ha = s["ha_all"]
        spread = (f"{_pct(s['avg_ha_all_mean'])} ± {_pct(s['avg_ha_all_sd'])}" if s.get("avg_ha_all_mean") is not None
                  else "-")
        return [_pct(s["avg_ha_all"]), _pct(s["avg_ha_i"]), _pct(s["avg_ha_v"]), spread, _pct(ha[0]), _pct(ha[2]),
                _pct(ha[4]), _pct(s["mma"][2]), _pct(s["repeatability"]), f"{s['matches']:.0f}",
                f"{1000 * entry['seconds_per_image']:.0f}"]

    return _method_table(results, title, *_spread_columns_if_runs(columns, cells, (3,), runs))


# Okabe & Ito's colour-blind-safe palette (black first for contrast). Combined with line
# styles and markers, so two methods never look alike even past 8 methods or in grey print.
PALETTE = ("#000000", "#E69F00", "#56B4E9", "#009E73", "#D55E00", "#0072B2", "#CC79A7", "#F0E442")
LINESTYLES = ("-", "--", "-.", ":")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def line_style(index: int) -> dict:
    """Matplotlib kwargs of the ``index``-th method: colour, line style, marker (32 distinct combinations)."""
    colour = PALETTE[index % len(PALETTE)]
    style = LINESTYLES[(index // len(PALETTE)) % len(LINESTYLES)]
    marker = MARKERS[(index + index // len(PALETTE)) % len(MARKERS)]
    return {"color": colour, "linestyle": style, "marker": marker, "ms": 4, "lw": 1.6}


def _legend_below(fig, handles: list, labels: list[str], title: str | None = None) -> None:
    """One legend for the figure, under the axes, so it never hides a curve."""
    ncol = min(4 if len(labels) > 3 else 3, max(1, len(labels)))
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=ncol, fontsize=8,
               frameon=False, title=title, title_fontsize=8)


def _save(fig, path: Path) -> Path:
    return save_png(fig, path, dpi=110, bbox_inches="tight")  # "tight" keeps the legend below the axes in the PNG


def plot_curves(results: dict, output: Path) -> list[Path]:
    """homography_accuracy.png (overall / i / v, as the paper's Fig. 4) and mma.png; legends below the axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = {k: v["summary"] for k, v in results["methods"].items() if "summary" in v}
    styles = {label: line_style(i) for i, label in enumerate(methods)}
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), sharey=True)
    for ax, subset, title in zip(axes, ("all", "i", "v"), ("Overall", "Illumination", "Viewpoint")):
        for label, s in methods.items():
            if s[f"pairs_{subset}"]:
                ax.plot(THRESHOLDS, s[f"ha_{subset}"], **styles[label])
        ax.set(title=title, xlabel="corner error threshold (px)", ylim=(0, 1.02))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("homography accuracy")
    # Avg.HA@1:10 overall / i / v in the legend: the numbers of the results table.
    handles = [plt.Line2D([], [], **styles[label]) for label in methods]
    pct = lambda v: "-" if v is None else f"{100 * v:.1f}"  # None: no pair of that subset (one sequence)
    _legend_below(fig, handles, [f"{label} ({pct(s['avg_ha_all'])} / {pct(s['avg_ha_i'])} / "
                                 f"{pct(s['avg_ha_v'])})" for label, s in methods.items()],
                  "method (Avg.HA@1:10 overall / illumination / viewpoint, %)")
    paths = [output / "homography_accuracy.png", output / "mma.png"]
    fig.tight_layout()
    _save(fig, paths[0])
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, s in methods.items():
        ax.plot(THRESHOLDS, s["mma"], **styles[label])
    ax.set(xlabel="threshold (px)", ylabel="mean matching accuracy", ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    _legend_below(fig, handles, [f"{label} ({100 * s['mma'][2]:.1f})" for label, s in methods.items()],
                  "method (MMA@3, %)")
    fig.tight_layout()
    _save(fig, paths[1])
    plt.close(fig)
    return paths


def pose_markdown(results: dict) -> str:
    """One row per method: mAA@1:10, AUC@5/10/20, median errors, matches, inliers."""
    config = results["config"]
    title = (f"Relative pose on all image pairs of {', '.join(results['scenes'])} (up to {config['max_keypoints']} "
             f"keypoints, long side <= {config['resize_max'] or 'full'} px for extraction, ratio test for float / "
             "mutual NN for binary descriptors, essential matrix RANSAC).")
    runs = config.get("ransac_runs", 1)
    if runs > 1:
        title += (f" mAA@1:10 and AUC: one RANSAC run on the matches in order; mean ± sd: over {runs} RANSAC runs "
                  "on shuffled orders of the same matches, to rank methods whose single runs differ by RANSAC's luck.")
    columns = ["pairs", "mAA@1:10", f"mAA mean ± sd ({runs} runs)", "AUC@5", "AUC@5 mean ± sd", "AUC@10",
               "AUC@20", "median rot (deg)", "median trans (deg)", "matches", "inliers"]

    def spread(s: dict, key: str) -> str:
        return f"{s[key + '_mean']:.3f} ± {s[key + '_sd']:.3f}" if s.get(key + "_mean") is not None else "-"

    def cells(entry: dict) -> list[str]:
        s = entry["summary"]
        return [str(s["pairs"]), f"{s['maa']:.3f}", spread(s, "maa"), f"{s['auc5']:.3f}", spread(s, "auc5"),
                f"{s['auc10']:.3f}", f"{s['auc20']:.3f}",
                f"{s['median_rotation_deg']:.2f}", f"{s['median_translation_deg']:.2f}", f"{s['matches']:.0f}",
                f"{s['inliers']:.0f}"]

    return _method_table(results, title, *_spread_columns_if_runs(columns, cells, (2, 4), runs))


def _spread_columns_if_runs(columns: list[str], cells, spread: tuple[int, ...], runs: int):
    """``(columns, cells)`` without the mean ± sd columns (indices ``spread``) for a single RANSAC run
    (``--ransac-runs 1``, or results written before there were runs): they would repeat the single run."""
    if runs > 1:
        return columns, cells
    keep = [i for i in range(len(columns)) if i not in spread]
    return [columns[i] for i in keep], lambda entry: [cells(entry)[i] for i in keep]


def plot_pose(results: dict, output: Path) -> Path:
    """pose_accuracy.png: fraction of pairs with pose error below each threshold (1..10 deg); legend below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    handles, labels = [], []
    methods = [(label, e["summary"]) for label, e in results["methods"].items() if "summary" in e]
    for i, (label, s) in enumerate(methods):
        handles += ax.plot(THRESHOLDS, s["accuracy"], **line_style(i))
        labels.append(f"{label} ({s['maa']:.3f})")
    ax.set(xlabel="pose error threshold (deg)", ylabel="accuracy", ylim=(0, 1.02))
    ax.grid(alpha=0.3)
    _legend_below(fig, handles, labels, "method (mAA@1:10)")
    fig.tight_layout()
    path = _save(fig, output / "pose_accuracy.png")
    plt.close(fig)
    return path


def write_results(results: dict, output: Path, markdown: Callable[[dict], str], plot: Callable[[dict, Path], object]) -> Path:
    """results.json (atomically), results.md and the plots of one benchmark run; returns the JSON path."""
    output.mkdir(parents=True, exist_ok=True)
    path = output / "results.json"
    write_atomic(path, results_json(results))
    (output / "results.md").write_text(markdown(results))
    plot(results, output)
    return path


def results_json(results: dict) -> str:
    """``results`` as JSON: one key per line, but lists of numbers on one line, and the per-pair
    values of every RANSAC run (``*_runs``) to 0.01 (px or deg): 50 runs x 25 pairs x 15 methods
    stay a file of some 100 kB. Summaries are computed before, from the unrounded values."""
    rounded = {**results, "methods": {label: _rounded_runs(entry) for label, entry in results["methods"].items()}}
    text = json.dumps(rounded, indent=1, default=float)
    return _NUMBER_LIST.sub(lambda m: re.sub(r"\s+", "", m.group(0)).replace(",", ", "), text)


_NUMBER_LIST = re.compile(r"\[(?:\s*(?:-?[0-9][0-9.eE+-]*|-?Infinity|NaN)\s*,)*\s*(?:-?[0-9][0-9.eE+-]*|-?Infinity|NaN)\s*\]")


def _rounded_runs(entry: dict) -> dict:
    if "pairs" not in entry:
        return entry
    pairs = [{k: [round(x, 2) for x in v] if k.endswith("_runs") else v for k, v in pair.items()} for pair in entry["pairs"]]
    return {**entry, "pairs": pairs}


# --- Regenerating every plot of a results tree -------------------------------------------

FIGURES_FILE = "figures.json"


def merge_results(parts: list[dict]) -> dict:
    """Several runs of one benchmark as one results dict: a later run's method replaces an
    earlier one's of the same label (in place); new labels are appended. Config and data
    come from the first run."""
    merged = dict(parts[0], methods=dict(parts[0]["methods"]))
    for part in parts[1:]:
        merged["methods"].update(part["methods"])
    return merged


def _kind(results: dict) -> str | None:
    """``homography``, ``pose`` or None (SfM and unknown results have no curves)."""
    if "methods" not in results:
        return None
    return "homography" if "sequences" in results else "pose" if "scenes" in results else None


def _plot(kind: str, results: dict, folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    return plot_curves(results, folder) if kind == "homography" else [plot_pose(results, folder)]


def regenerate_plots(root: Path) -> list[Path]:
    """Redraw every benchmark plot under ``root`` from the results there; returns the PNGs written.

    A folder with a ``results.json`` of ``bench homography`` or ``bench pose`` gets its plots
    from it. ``root/figures.json`` names figures built from several runs, folder -> sources
    (paths relative to ``root``):

        {"homography": {"homography": ["homography/results.json", "later/homography/results.json"]},
         "summary": {"summary": {"homography": [...], "pose": [...], "sfm": [...], "highlight": ["sekd_ours"]}}}

    A later source's rows replace earlier ones of the same method, as in ``bench summary``.
    """
    from ..errors import SekdError
    from .summary import write_summary

    root = Path(root)
    if not root.is_dir():
        raise SekdError(f"{root}: not a folder; give the folder holding the benchmark results (e.g. docs/results)")
    figures = {}
    manifest = root / FIGURES_FILE
    if manifest.is_file():
        try:
            figures = json.loads(manifest.read_text())
        except json.JSONDecodeError as exc:
            raise SekdError(f"{manifest}: not valid JSON ({exc}); fix or remove it") from None
    written = []
    for path in sorted(root.rglob("results.json")):
        folder = path.parent.relative_to(root).as_posix()
        if folder in figures:
            continue
        results = _load_json(path)
        kind = _kind(results)
        if kind:
            written += _plot(kind, results, path.parent)
    for folder, spec in figures.items():
        for kind, sources in spec.items():
            if kind == "summary":
                paths = {k: [root / p for p in sources.get(k, [])] for k in ("homography", "pose", "sfm")}
                _check_exist(manifest, [p for group in paths.values() for p in group])
                md = write_summary(root / folder, paths["homography"], paths["pose"], paths["sfm"],
                                   tuple(sources.get("highlight", ())))
                written.append(md.with_suffix(".png"))
            elif kind in ("homography", "pose"):
                _check_exist(manifest, [root / p for p in sources])
                written += _plot(kind, merge_results([_load_json(root / p) for p in sources]), root / folder)
            else:
                raise SekdError(f"{manifest}: unknown figure kind {kind!r} for {folder!r}; "
                                "use homography, pose or summary")
    return written


def _load_json(path: Path) -> dict:
    from ..errors import SekdError

    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SekdError(f"{path}: cannot read benchmark results ({exc})") from None


def _check_exist(manifest: Path, paths: list[Path]) -> None:
    from ..errors import SekdError

    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise SekdError(f"{manifest}: missing results file(s) {', '.join(missing)}")
