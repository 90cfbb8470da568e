"""Fork a run: a new run that changes step (b) or training-pair settings, or the rounds, and reuses everything before.

Labelling steps (a), (c) and the detector step (d) never read the step-(b) settings, so a
run that differs from another only in those starts identical to it up to the first (b)
step: ``sekd evolve --fork SRC --out NEW --set spread_weight=1`` copies the finished
tasks before that point (labels, models, history, log), records where it came from, and
continues from there with ``--resume``. The training steps' shared settings (the pairs'
``perspective``, ``train_precision``) are read by both (b) and (d), so a fork that changes
them reuses what precedes the first training step (round 0's labels (c)). Nothing is
recomputed and nothing is guessed: settings that other steps read are refused.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
from pathlib import Path

from ..errors import SekdError
from .config import RUNTIME_FIELDS, TrainConfig, apply, differing_fields
from .config import validate as validate_config
from .evolve import RunFolder, Task, evolve_tasks
from .report import rank_validation, write_atomic

#: Settings only step (b) reads (docs/method.md "Training" and the descriptor-step extensions).
DESC_STEP_FIELDS = ("epochs_desc", "desc_loss", "ratio_threshold", "margin", "margin_normalise",
                    "neg_min_distance", "neg_self_penalty", "neg_min_pixels", "spread_weight",
                    "alpha", "det_preserve_on")
#: Settings of both training steps, (b) and (d), never read by the labelling steps (a), (c):
#: the training pairs' warp and the precision of the training forward passes.
TRAINING_FIELDS = ("perspective", "train_precision")
#: Settings that change no finished task: rounds only append or drop later tasks.
FREE_FIELDS = ("rounds",) + RUNTIME_FIELDS


def reusable_tasks(tasks: list[Task], done: list[str], changed: list[str]) -> list[Task]:
    """The leading finished tasks a run with ``changed`` settings would repeat exactly."""
    others = sorted(set(changed) - set(DESC_STEP_FIELDS) - set(TRAINING_FIELDS) - set(FREE_FIELDS))
    if others:
        raise SekdError(f"--fork can change only step (b) settings ({', '.join(DESC_STEP_FIELDS)}), training-step "
                        f"settings ({', '.join(TRAINING_FIELDS)}) and rounds; {', '.join(others)} change steps the "
                        "source already ran: start a new run instead")
    desc_changed = bool(set(changed) & set(DESC_STEP_FIELDS))
    training_changed = bool(set(changed) & set(TRAINING_FIELDS))
    reused = []
    for task in tasks:
        if task.id not in done or (desc_changed and task.kind == "b") or (training_changed and task.training):
            break
        reused.append(task)
    return reused


def fork_run(source: Path, out: Path, overrides: dict) -> Path:
    """Create run folder ``out`` from run ``source`` with ``overrides``; returns ``out`` (run it with --resume)."""
    src, dst = RunFolder(source), RunFolder(out)
    dst.check_new()
    old_config, old_tasks, old_state = src.read(None)
    config = apply(old_config, dict(overrides), "--fork")
    validate_config(config)
    changed = differing_fields(old_config, config)
    reused = reusable_tasks(old_tasks, old_state["done"], changed)
    tasks = evolve_tasks(config)
    reused = reused[:len(tasks)]  # fewer rounds: the later finished tasks are not part of the fork
    if [t.id for t in tasks[:len(reused)]] != [t.id for t in reused]:
        raise SekdError(f"{source}: not a `sekd evolve` run of this schedule; --fork continues evolve runs only")
    ids = (["start"] if "start" in old_state["done"] else []) + [t.id for t in reused]
    history = _history_upto(src.root, ids)
    best = _best(history, config)
    _copy_outputs(src, dst, reused, best)
    state = {"tasks": [dataclasses.asdict(t) for t in tasks], "done": ids, "best": best,
             "forked_from": {"run": _relative(source, dst.root), "after": ids[-1], "changed": changed},
             "images": old_state.get("images")}
    write_atomic(dst.root / "config.yaml", config.to_yaml())
    write_atomic(dst.root / "history.json", json.dumps(history, indent=1))
    write_atomic(dst.root / "train.log", _log_upto(src.root / "train.log", reused, source, changed, config))
    dst.save_state(state)  # last: the folder is a run only once everything else is in place
    return dst.root


def _relative(source: Path, fork: Path) -> str:
    """``source`` relative to the fork's folder, so the record holds in any clone of the repository."""
    return Path(os.path.relpath(Path(source).resolve(), Path(fork).resolve())).as_posix()


def _copy_outputs(src: RunFolder, dst: RunFolder, reused: list[Task], best: dict | None) -> None:
    for sub in ("labels", "models", "checkpoints"):
        (dst.root / sub).mkdir(parents=True, exist_ok=True)
    for task in reused:
        path = src.model_path(task.id) if task.training else src.labels_path(task.id)
        target = dst.model_path(task.id) if task.training else dst.labels_path(task.id)
        if not path.is_file():
            raise SekdError(f"{path}: missing, so {task.id} of {src.root} cannot be reused")
        shutil.copy2(path, target)
    trained = [t for t in reused if t.training]
    if trained:  # last.pth: the latest reused model until the fork trains its own
        shutil.copy2(src.model_path(trained[-1].id), dst.root / "last.pth")
    if best is not None:  # best.pth: the model the state names best (the fork's own steps may beat it)
        shutil.copy2(src.model_path(best["task"]), dst.root / "best.pth")


def _history_upto(run: Path, ids: list[str]) -> dict:
    path = run / "history.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    return {key: [r for r in rows if r.get("task") in ids] for key, rows in data.items()}


def _best(history: dict, config: TrainConfig) -> dict | None:
    """The state's ``best`` record for the reused validations (None when only the start was validated)."""
    ranked = rank_validation(history.get("validation", []), config.best_metric)
    return {"task": ranked[0][0], "metric": config.best_metric, "value": ranked[0][1]} if ranked else None


def _task_marker(task: Task) -> re.Pattern:
    """The log line that closes ``task``: its labels summary or its validation."""
    if task.training:
        return re.compile(rf"validation after {task.id}:")
    return re.compile(rf"round {task.round} labels \({task.kind}\):")


_NEXT_TASK = re.compile(r"step \w+ epoch |labels \(|(new|resumed) run in |interrupted|resuming ")


def _log_upto(log: Path, reused: list[Task], source: Path, changed: list[str], config: TrainConfig) -> str:
    """The source's log up to the last reused task (so training times add up), then the fork line."""
    lines = log.read_text().splitlines() if log.is_file() else []
    end = 0
    if reused:
        marker = _task_marker(reused[-1])
        hits = [i for i, line in enumerate(lines) if marker.search(line)]
        end = hits[-1] + 1 if hits else 0
        while end < len(lines) and not _NEXT_TASK.search(lines[end]):
            end += 1  # lines that still belong to it (new best model, threshold notes)
    stamp = lines[end - 1][:23] if end else "1970-01-01 00:00:00,000"
    setting = " ".join(f"{k}={json.dumps(getattr(config, k))}" for k in changed)
    note = f"{stamp} INFO forked from {Path(source).resolve()} after {reused[-1].id if reused else 'nothing'}: {setting}"
    return "\n".join(lines[:end] + [note]) + "\n"
