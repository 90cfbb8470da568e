"""Run history: per-epoch losses, labelling statistics and validation, as JSON, CSV and a PNG of curves.

Records are keyed (a resumed run that repeats an epoch replaces its record), and every
file is written atomically.
"""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from ..files.atomic import (
    write_atomic,  # also imported from here by the training modules
)
from .config import load_run_config

SECTIONS = {"epochs": ("round", "kind", "epoch"), "labels": ("task",), "validation": ("task",)}


def csv_text(rows: list[dict]) -> str:
    """Rows of dicts as CSV; columns in first-seen order."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


class History:
    """``history.json`` of a run folder plus its CSV and PNG renderings."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        path = self.folder / "history.json"
        self.data = json.loads(path.read_text()) if path.is_file() else {name: [] for name in SECTIONS}

    def add(self, section: str, record: dict) -> None:
        """Append ``record`` to ``section``, replacing a record with the same key."""
        key = tuple(record[k] for k in SECTIONS[section])
        rows = [r for r in self.data[section] if tuple(r[k] for k in SECTIONS[section]) != key]
        self.data[section] = rows + [dict(record)]

    def save(self, plot: bool = True) -> None:
        write_atomic(self.folder / "history.json", json.dumps(self.data, indent=1))
        write_atomic(self.folder / "losses.csv", csv_text(self.data["epochs"]))
        write_atomic(self.folder / "labels.csv", csv_text(self.data["labels"]))
        write_atomic(self.folder / "metrics.csv", csv_text(self.data["validation"]))
        write_atomic(self.folder / "metrics.json", json.dumps(self.data["validation"], indent=1))
        if plot:
            write_atomic(self.folder / "curves.png", plot_curves(self.data))


def validation_position(record: dict) -> float:
    """x position of a validation record: its round, half a round later after a detector step (d)."""
    return record["round"] + (0.5 if str(record["task"]).endswith("_d") else 0.0)


def plot_curves(data: dict) -> bytes:
    """PNG: training loss per epoch (descriptor and detector steps), validation per round, keypoints per image."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for kind, name in (("b", "descriptor step (b)"), ("d", "detector step (d)")):
        rows = [(i, r["total"]) for i, r in enumerate(data["epochs"]) if r["kind"] == kind]
        if rows:
            axes[0].plot(*zip(*rows), "o-", label=name)
    axes[0].set(xlabel="epoch (all steps in order)", ylabel="mean loss", title="training loss", yscale="log")
    val = sorted(data["validation"], key=validation_position)
    for metric, style in (("mma3", "o-"), ("mma_avg", "o-"), ("ha_avg", "o-"), ("desc_cos", "x--")):
        rows = [r for r in val if metric in r]  # desc_cos: runs validated before it existed lack it
        if rows:
            axes[1].plot([validation_position(r) for r in rows], [r[metric] for r in rows], style, label=metric)
    axes[1].set(xlabel="round (-1 = start; (b) at k, (d) at k + 0.5)", ylabel="accuracy", title="validation",
                ylim=(0, 1))
    for kind in ("a0", "a", "c"):
        rows = [(r["round"], r["keypoints"]) for r in data["labels"] if r["kind"] == kind]
        if rows:
            axes[2].plot(*zip(*rows), "o-", label=f"labels ({kind})")
    axes[2].set(xlabel="round", ylabel="keypoints per image", title="labels")
    for ax in axes:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return buffer.getvalue()


def rounds_done(run: Path) -> int:
    """Rounds of the run folder ``run`` whose detector step (d) has finished."""
    return finished_rounds(json.loads((Path(run) / "state.json").read_text())["done"])


def finished_rounds(done: list[str]) -> int:
    """Rounds whose detector step (d) is among the finished task ids ``done`` (``r1_d``, ...)."""
    return len({task.split("_")[0] for task in done if task.endswith("_d")})


def ranked_steps(run: Path, max_round: int | None = None, metric: str | None = None) -> list[tuple[str, float]]:
    """Validated training steps of the run folder ``run`` as (task, value), best first.

    ``metric``: the run's ``best_metric`` unless given; ``max_round``: only rounds up to it.
    The untrained start never counts.
    """
    metric = metric or load_run_config(Path(run) / "config.yaml").best_metric
    path = Path(run) / "metrics.json"
    return rank_validation(json.loads(path.read_text()) if path.is_file() else [], metric, max_round)


def rank_validation(rows: list[dict], metric: str, max_round: int | None = None) -> list[tuple[str, float]]:
    """Validation rows as (task, value) of ``metric``, best first (ties keep their order); the start is skipped."""
    rows = [r for r in rows if r["task"] != "start" and (max_round is None or r["round"] <= max_round)]
    return [(r["task"], float(r[metric])) for r in sorted(rows, key=lambda r: -r[metric])]
