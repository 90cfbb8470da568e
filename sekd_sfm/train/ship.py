"""Ship a trained run's model as the package's embedded default, with its model card.

``python -m sekd_sfm.train.ship RUN [--card docs/model_card.md]`` copies ``RUN/best.pth``
(weights and metadata, fp32) to ``sekd_sfm/model/checkpoints/sekd_own.pth`` and writes a model
card that says what the model was trained on, how, for how long, and its checksum.
``--which`` may also name a weight average of the run's step models
(``python -m sekd_sfm.train.soup``); the card then lists its ingredients. ``ship RUN RUN ...
--which AVERAGE.pth`` ships an average of models from several runs (nested averages and
shipped models among its ingredients), the card listing every run behind it. A run that
started from another model (``init_weights``) records that model's checksum and training
facts, so the lineage travels with the shipped file.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import re
import tempfile
from datetime import datetime
from pathlib import Path

import torch

from ..errors import SekdError
from ..model.network import SEKDNet, count_parameters
from ..model.weights import EMBEDDED_MODELS, file_sha256, load_model
from ..runtime import shared_dir
from .config import TrainConfig, load_run_config, schedule_config
from .report import finished_rounds, ranked_steps, write_atomic

logger = logging.getLogger("sekd")
MAX_BYTES = 3_000_000  # the package carries the model: keep the wheel small
GUARD_PX = 3.0  # v_graffiti 1-2 mean corner error the embedded model must stay under (tests too)
GUARD_SEQUENCE = "data/homography/hpatches/v_graffiti"
_STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),\d+ ")
_START = re.compile(r"(new|resumed) run in ")


def training_wall_seconds(log: Path, until: str | None = None) -> float:
    """Seconds spent training: per process run of ``train.log``, last line minus first, summed.

    A run resumed days later contributes only its own span, not the pause. ``until``: stop at
    the first line containing it (e.g. ``validation after r1_d``: the time to that model).
    """
    total, first, last = 0.0, None, None
    for line in Path(log).read_text().splitlines():
        match = _STAMP.match(line)
        if not match:
            continue
        stamp = datetime.strptime(match.group(1), "%Y-%m-%d %H:%M:%S")
        if _START.search(line) and first is not None:
            total += (last - first).total_seconds()
            first = None
        first, last = first or stamp, stamp
        if until and until in line:
            break
    return total + ((last - first).total_seconds() if first else 0.0)


def evolve_command(config: TrainConfig, run: Path) -> str:
    """The ``sekd evolve`` command that starts this run: schedule, seed and every changed field.

    A starting model (``init_weights``) is shown by file name only: where it sat on the training
    machine means nothing elsewhere; the card's "starts from" row identifies it by checksum.
    """
    base = schedule_config(config.schedule)
    shown = {"init_weights": Path(config.init_weights).name} if config.init_weights else {}
    changed = [f"--set {f.name}={json.dumps(shown.get(f.name, getattr(config, f.name)))}"
               for f in dataclasses.fields(TrainConfig)
               if f.name not in ("schedule", "images", "seed", "num_threads", "num_workers", "progress", "device")
               and getattr(config, f.name) != getattr(base, f.name)]
    return " ".join([f"sekd evolve --images {_display_path(config.images)} --schedule {config.schedule}",
                     f"--seed {config.seed} --out {run}", *changed])


def _validated_line(meta: dict) -> str | None:
    """The log line that ends the training of this model (its validation), if it names a step."""
    return f"validation after {meta['task']}" if meta.get("task") else None


def step_models(runs: list[Path]) -> dict[str, tuple[Path, str]]:
    """``{SHA-256 (64 hex digits): (run, task)}`` for the step models ``run/models/*.pth`` of ``runs``."""
    return {file_sha256(path, 64): (Path(run), path.stem)
            for run in runs for path in sorted((Path(run) / "models").glob("*.pth"))}


def _step_of(steps: dict[str, tuple[Path, str]], sha256: str) -> tuple[Path, str] | None:
    """The ``(run, task)`` whose checksum begins with ``sha256`` (a soup records 16 digits, a starting model 64)."""
    return next((step for full, step in steps.items() if full.startswith(sha256)), None)


def soup_ingredients(run: Path, soup: list[dict]) -> list[dict]:
    """``[{task, sha256, weight}]``: the step models of ``run`` that a weight average is made of.

    ``soup``: the ``soup`` record of a ``python -m sekd_sfm.train.soup`` checkpoint. Ingredients
    are recognised by checksum among ``run/models/*.pth``, wherever the soup was made; SekdError
    for one that is not a step model of the run (the card could not say how it was trained).
    """
    steps = step_models([run])
    ingredients = []
    for item in soup:
        step = _step_of(steps, item["sha256"])
        if step is None:
            raise SekdError(f"{item['file']}: an ingredient of this weight average is not a step model of {run} "
                            "(models/*.pth); ship averages of one run's steps")
        ingredients.append({"task": step[1], "sha256": item["sha256"], "weight": item["weight"]})
    return ingredients


def soup_command(run: Path, ingredients: list[dict]) -> str:
    """The ``python -m sekd_sfm.train.soup`` command that rebuilds the average from the run's step models."""
    files = " ".join(f"{run}/models/{item['task']}.pth" for item in ingredients)
    weights = " ".join(f"{item['weight']:g}" for item in ingredients)
    return f"python -m sekd_sfm.train.soup {files} --weights {weights} -o soup.pth"


def _file_with_sha(path: Path, sha256: str) -> Path | None:
    """``path`` if it holds the checkpoint ``sha256`` names, else the embedded model that does (its
    record may name it relative to another working directory), else None."""
    for candidate in (path, *EMBEDDED_MODELS.values()):
        if candidate.is_file() and file_sha256(candidate) == sha256:
            return candidate
    return None


def average_leaves(soup: list[dict], runs: list[Path], share: float = 1.0,
                   steps: dict[str, tuple[Path, str]] | None = None) -> list[dict]:
    """The trained models a weight average is made of, each with its share of the average.

    ``soup``: the ``soup`` record of a ``python -m sekd_sfm.train.soup`` checkpoint. An ingredient
    is a step model of one of ``runs`` (recognised by checksum among ``run/models/*.pth``), a
    shipped model (its metadata says how it was trained), or itself an average, resolved in turn
    (its share split by its own weights). Returns ``[{weight, sha256, run, task}]`` rows for step
    models and ``[{weight, sha256, file, shipped}]`` for shipped ones (``shipped``: the facts of
    ``starting_model``); the weights sum to ``share``. SekdError for an ingredient that is none of these.
    ``steps``: ``step_models(runs)``, if already computed.
    """
    steps = step_models(runs) if steps is None else steps
    leaves = []
    for item in soup:
        weight = share * item["weight"]
        step = _step_of(steps, item["sha256"])
        if step is not None:
            leaves.append({"weight": weight, "sha256": item["sha256"], "run": str(step[0]), "task": step[1]})
            continue
        path = _file_with_sha(Path(item["file"]), item["sha256"])
        meta = load_model(path)[1].meta if path else {}
        if "soup" in meta:
            leaves += average_leaves(meta["soup"], runs, weight, steps)
        elif "shipped_from" in meta:
            leaves.append({"weight": weight, "sha256": item["sha256"], "file": path.name,
                           "shipped": starting_model(str(path))})
        else:
            raise SekdError(f"{item['file']}: an ingredient of this weight average is neither a step model of "
                            f"{', '.join(Path(r).name for r in runs)} nor a shipped model nor an average of such; "
                            "name the run it comes from")
    return leaves


def average_runs(leaves: list[dict], runs: list[Path],
                 steps: dict[str, tuple[Path, str]] | None = None) -> tuple[list[dict], list[dict]]:
    """The training behind an average's leaves: ``(run rows, shipped models)``, each once.

    A run row ``{run, until, tasks, labels_copied, threads, command, seed, init, wall_seconds}``
    covers the run up to the latest of its steps the average uses (``until``), including the runs
    whose step models other runs start from (``init_weights``); ``wall_seconds`` is its
    ``train.log`` time to there. The shipped models (leaves, or starting models of the runs) come
    with their own recorded facts. ``steps``: ``step_models(runs)``, if already computed.
    """
    steps = step_models(runs) if steps is None else steps
    needed: dict[Path, list[str]] = {}
    starts: dict[Path, tuple[TrainConfig, dict | None]] = {}
    shipped: dict[str, dict] = {leaf["shipped"]["sha256"]: leaf["shipped"] for leaf in leaves if "shipped" in leaf}
    todo = [(Path(leaf["run"]), leaf["task"]) for leaf in leaves if "run" in leaf]
    while todo:
        run, task = todo.pop()
        needed.setdefault(run, []).append(task)
        if run in starts:
            continue
        config = load_run_config(run / "config.yaml")
        init = starting_model(config.init_weights)
        starts[run] = config, init
        made_from = _step_of(steps, init["sha256"]) if init and "sha256" in init else None
        if made_from:
            todo.append(made_from)
        elif init and "shipped_from" in init:
            shipped.setdefault(init["sha256"], init)
    rows = []
    for run, tasks in sorted(needed.items(), key=lambda item: item[0].name):
        config, init = starts[run]
        state = json.loads((run / "state.json").read_text())
        done = state["done"]
        until = max(tasks, key=done.index)
        copied = sorted({t["labels"] for t in state.get("tasks", []) if t.get("labels") and t["labels"] not in done})
        made_from = _step_of(steps, init["sha256"]) if init and "sha256" in init else None
        rows.append({"run": run.name, "until": until, "tasks": done[:done.index(until) + 1],
                     "labels_copied": copied, "threads": config.num_threads,
                     "command": evolve_command(config, run.name), "seed": config.seed,
                     "init": (f"`{made_from[1]}` of `{made_from[0].name}`" if made_from else
                              f"`{init['file']}` (SHA-256 `{init.get('sha256', '?')[:16]}`)" if init else "random weights"),
                     "wall_seconds": round(training_wall_seconds(run / "train.log", f"validation after {until}"))})
    return rows, list(shipped.values())


def starting_model(init_weights: str) -> dict | None:
    """What a run started from: file name, SHA-256 and, for a shipped model, how it was trained.

    The facts of a shipped model (``shipped_from``, ``source``, ``wall_seconds``, ``command``
    and its own ``init``) are copied, so a chain of runs is recorded back to a random start.
    None for a run from random weights; only the name when the file is no longer there.
    """
    if not init_weights:
        return None
    path = Path(init_weights)
    if not path.is_file():
        return {"file": path.name}
    meta = load_model(path)[1].meta
    facts = {"file": path.name, "sha256": file_sha256(path, 64)}
    facts.update({k: meta[k] for k in ("shipped_from", "source", "wall_seconds", "command", "init") if k in meta})
    return facts


def _trained_meta(run: Path, info) -> dict:
    """The training facts of the shipped checkpoint: its own, or for an average those of its ingredients."""
    if "soup" not in info.meta:
        return dict(info.meta, wall_seconds=round(training_wall_seconds(run / "train.log", _validated_line(info.meta))))
    ingredients = soup_ingredients(run, info.meta["soup"])
    first = load_model(run / "models" / f"{ingredients[0]['task']}.pth")[1].meta
    # The average exists once its last-trained ingredient does: the run's time up to that step.
    seconds = max(training_wall_seconds(run / "train.log", f"validation after {item['task']}") for item in ingredients)
    return {**{k: first[k] for k in ("schedule", "seed", "config") if k in first},
            "average": ingredients, "average_command": soup_command(run, ingredients), "wall_seconds": round(seconds)}


def _display_path(path: str) -> str:
    """Paths under the shared data folder as ``../shared/...`` (machine-independent).

    The run's config may have been written on another machine, where the shared folder sat
    elsewhere (``/work/shared`` there, ``/check/work/shared`` here): a path with a ``shared``
    folder is shown from that folder on.
    """
    try:
        return "../shared/" + Path(path).resolve().relative_to(shared_dir().resolve()).as_posix()
    except ValueError:
        parts = Path(path).parts
        if "shared" not in parts:
            return str(path)
        last = len(parts) - 1 - parts[::-1].index("shared")
        return "/".join(("..",) + parts[last:])


def ship_model(run: Path, dest: Path = EMBEDDED_MODELS["own"], card: Path | None = None, which: str = "best.pth",
               reference: Path | None = None, guard: bool = True) -> Path:
    """Copy ``run/which`` to ``dest`` with its training facts; write the model card; return ``dest``.

    ``reference``: another checkpoint (the authors') scored by the run's own validation for the card.
    ``guard``: refuse a checkpoint that fails the package's regression guard (``graffiti_corner_error``).
    ``which="auto"``: the best-validated step model that passes the guard (``best_guarded_step``).
    """
    run = Path(run)
    guard_error = None
    if which == "auto":
        which, guard_error = best_guarded_step(run)
    source = run / which
    net, info = load_model(source)  # refuses anything that is not an exact SEKD checkpoint
    config = load_run_config(run / "config.yaml")
    shown = Path(which).name if Path(which).is_absolute() else which  # an average made outside the run
    meta = dict(_trained_meta(run, info), shipped_from=str(run.name), source=shown,
                source_sha256=info.sha256, command=evolve_command(config, run), data=_display_path(config.images))
    init = starting_model(config.init_weights)
    if init:
        meta["init"] = init
    dest = Path(dest)
    _save_shipped(net, meta, dest, source, config, guard, guard_error)
    if card is not None:
        write_atomic(Path(card), model_card(run, dest, meta, _card_validations(meta, shown, reference, config)))
    return dest


def _card_validations(meta: dict, shown: str, reference: Path | None, config: TrainConfig) -> list[dict]:
    """The card's extra validation rows: the shipped checkpoint, and ``reference`` scored the same way."""
    rows = [{"task": f"`{shown}` (shipped)", **meta["validation"]}]
    if reference:
        rows.append({"task": f"`{Path(reference).name}` (reference)", **validate_net(load_model(reference)[0], config)})
    return rows


def soup_commands(soup: list[dict], output: str, runs: list[Path],
                  steps: dict[str, tuple[Path, str]] | None = None) -> list[str]:
    """The ``python -m sekd_sfm.train.soup`` commands that rebuild a (nested) average, innermost first.

    Step models are named ``RUN/models/TASK.pth`` (RUN: the run folder's name), shipped models
    and inner averages by file name. ``steps``: ``step_models(runs)``, if already computed.
    """
    steps = step_models(runs) if steps is None else steps
    commands, names = [], []
    for item in soup:
        step = _step_of(steps, item["sha256"])
        name = f"{step[0].name}/models/{step[1]}.pth" if step else Path(item["file"]).name
        path = None if step else _file_with_sha(Path(item["file"]), item["sha256"])
        inner = load_model(path)[1].meta.get("soup") if path else None
        if inner:
            commands += soup_commands(inner, name, runs, steps)
        names.append(name)
    weights = " ".join(f"{item['weight']:g}" for item in soup)
    return [*commands, f"python -m sekd_sfm.train.soup {' '.join(names)} --weights {weights} -o {output}"]


def ship_average(runs: list[Path], average: Path, dest: Path = EMBEDDED_MODELS["own"], card: Path | None = None,
                 reference: Path | None = None, guard: bool = True) -> Path:
    """Ship a weight average of models from several runs (and shipped models); write its card; return ``dest``.

    ``average``: a ``python -m sekd_sfm.train.soup`` checkpoint whose ingredients (nested averages
    included) are step models of ``runs`` or shipped models (``average_leaves``). The checkpoint
    records every ingredient's share, the runs behind them (configuration, steps, starting model,
    wall time from ``train.log``) and the commands that rebuild the average.
    """
    runs = [Path(run) for run in runs]
    net, info = load_model(average)
    if "soup" not in info.meta:
        raise SekdError(f"{average}: not a weight average (python -m sekd_sfm.train.soup); ship a run's own model "
                        "with one run folder")
    steps = step_models(runs)
    leaves = average_leaves(info.meta["soup"], runs, steps=steps)
    run_rows, shipped = average_runs(leaves, runs, steps)
    first = next((leaf for leaf in leaves if "run" in leaf), None)
    if first is None:
        raise SekdError(f"{average}: no ingredient is a step model of the runs given; name the runs it comes from")
    config = load_run_config(Path(first["run"]) / "config.yaml")
    seconds = sum(row["wall_seconds"] for row in run_rows)
    seconds += sum(item.get("wall_seconds", 0) + (_lineage_seconds(item.get("init")) or 0) for item in shipped)
    shown = Path(average).name
    meta = {"schedule": config.schedule, "seed": config.seed, "config": config.as_dict(),  # the first run's
            "average_of": leaves, "runs": run_rows, "shipped_ingredients": shipped,
            "average_commands": soup_commands(info.meta["soup"], shown, runs, steps), "wall_seconds": seconds,
            "shipped_from": " + ".join(row["run"] for row in run_rows), "source": shown,
            "source_sha256": info.sha256, "data": _display_path(config.images),
            "command": f"a weight average of {len(leaves)} models (python -m sekd_sfm.train.soup); see its model card"}
    _save_shipped(net, meta, Path(dest), Path(average), config, guard)
    if card is not None:
        write_atomic(Path(card), average_card(Path(dest), meta, _card_validations(meta, shown, reference, config)))
    return Path(dest)


def _share_rows(meta: dict) -> list[str]:
    rows = ["| share | model | trained |", "|---|---|---|"]
    for leaf in meta["average_of"]:
        if "run" in leaf:
            rows.append(f"| {leaf['weight']:.3f} | `{leaf['task']}` of run `{Path(leaf['run']).name}` | see Runs |")
        else:
            facts = leaf["shipped"]
            rows.append(f"| {leaf['weight']:.3f} | `{leaf['file']}`, SHA-256 `{facts['sha256']}`: the model shipped "
                        f"from `{facts.get('shipped_from', '?')}` (`{facts.get('source', '?')}`) | "
                        f"{facts.get('wall_seconds', 0) / 3600:.2f} h, by `{facts.get('command', '?')}` |")
    return rows


def average_card(model: Path, meta: dict, extra: list[dict] = ()) -> str:
    """Markdown card of a shipped multi-run average: shares, runs, commands, wall time, validation, checksum."""
    config = meta["config"]
    lines = [
        "# Model card: `own`, the embedded SEKD model trained by this project (`--model own`)",
        "",
        "Generated by `python -m sekd_sfm.train.ship RUN [RUN ...] --which AVERAGE.pth` from the run folders of",
        "`sekd evolve` training named below (kept out of the repository); every figure below is read from them.",
        "",
        "| | |",
        "|---|---|",
        f"| file | `sekd_sfm/model/checkpoints/{model.name}` ({model.stat().st_size:,} bytes, fp32) |",
        f"| SHA-256 | `{file_sha256(model, 64)}` |",
        f"| network | SEKD (the paper's architecture), {count_parameters(SEKDNet()):,} parameters |",
        (f"| chosen | `{meta['source']}` = a weight average of {len(meta['average_of'])} trained models (below); "
         f"validation MMA@3 {meta['validation']['mma3']:.3f} |"),
        *([(f"| regression guard | v_graffiti 1-2 mean corner error {meta['graffiti_1_2_corner_error']:.2f} px "
            f"(must stay under {GUARD_PX:g} px) |")] if "graffiti_1_2_corner_error" in meta else []),
        f"| data | `{meta['data']}`: 256 unlabeled COCO photos, no labels of any kind |",
        (f"| wall time | {meta['wall_seconds'] / 3600:.2f} h of training on a 2-core CPU (no GPU) from random weights, "
         "summed over the runs below (their threads: below) and the shipped model(s) in it or behind them, "
         "each counted once |"),
        *[f"| average | `{command}` (no training: a weighted mean of the weights) |" for command in meta["average_commands"]],
        "",
        "## Ingredients (their shares of the average)",
        "",
        *_share_rows(meta),
        "",
        "## Runs",
        "",
        "Each run's configuration as `sekd evolve` flags (`config.yaml` in its folder), the steps it ran up to",
        "the model used, and what it started from.",
        "",
        "| run | seed | steps | starts from | threads | wall time | configuration |",
        "|---|---|---|---|---|---|---|",
        *[(f"| `{row['run']}` | {row['seed']} | {', '.join(row['tasks'])}"
           f"{''.join(f' (labels `{name}` copied in from another run)' for name in row['labels_copied'])} | "
           f"{row['init']} | {row['threads']} | {row['wall_seconds'] / 3600:.2f} h | `{row['command']}` |")
          for row in meta["runs"]],
        "",
        "## Validation",
        "",
        (f"Homography sequences of the shared data at long side {config['val_long_side']} px, "
         f"top {config['val_max_keypoints']} keypoints, mutual NN (`train/validate.py`), scored by `ship.py`."),
        "",
        *_validation_rows(None, list(extra)),
        "",
        "Benchmarks against the authors' model, the classics and the kornia peers: below, the README's",
        "Results section and [benchmarks.md](benchmarks.md).",
        "",
    ]
    return "\n".join(lines)


def _save_shipped(net: SEKDNet, meta: dict, dest: Path, source: Path, config: TrainConfig, guard: bool,
                  guard_error: float | None = None) -> None:
    """Write ``dest`` atomically with ``meta`` + its guard error and validation; SekdError if too large or unguarded.

    ``guard_error``: the guard's corner error if already measured (``which="auto"``), else measured here."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f"{dest.name}.{os.getpid()}.tmp")
    torch.save({"state_dict": net.state_dict(), "sekd_sfm": meta}, tmp)  # size first: scoring takes minutes
    size = tmp.stat().st_size
    tmp.unlink()
    if size > MAX_BYTES:
        raise SekdError(f"{source}: {dest.name} would be {size} bytes, over {MAX_BYTES}; ship a smaller model")
    if guard:
        meta["graffiti_1_2_corner_error"] = guard_error if guard_error is not None else _check_guard(source)
    # Score the shipped checkpoint itself: step models (b) carry no validation of their own.
    meta["validation"] = validate_net(net, config)
    torch.save({"state_dict": net.state_dict(), "sekd_sfm": meta}, tmp)
    tmp.replace(dest)


def graffiti_corner_error(weights: Path | None = None) -> float:
    """Mean corner error (px, full resolution) of the homography of v_graffiti pair 1-2.

    The embedded model's regression guard (the easiest viewpoint pair, default benchmark
    settings, fp32); ``weights`` None = the embedded model.
    """
    from ..bench.homography import HomographyConfig, run_homography_benchmark
    from ..bench.methods import Method

    method = Method("candidate", "sekd", str(weights) if weights else None)
    with tempfile.TemporaryDirectory(prefix="sekd_guard_") as work:
        out = run_homography_benchmark([shared_dir() / GUARD_SEQUENCE], [method], Path(work),
                                       HomographyConfig(precision="fp32"))
        pairs = json.loads(out.read_text())["methods"]["candidate"]["pairs"]
    first = next(p for p in pairs if p["pair"] == "1-2")
    return float(first["corner_error"])


def best_guarded_step(run: Path) -> tuple[str, float]:
    """(``models/<task>.pth``, its guard error) of the best-validated step that passes the guard.

    Steps are tried best first by the run's ``best_metric``; SekdError when none passes.
    """
    tried = []
    for task, value in ranked_steps(run):
        error = graffiti_corner_error(run / "models" / f"{task}.pth")
        logger.info("%s: validation %.4f, v_graffiti 1-2 corner error %.2f px", task, value, error)
        if error < GUARD_PX:
            return f"models/{task}.pth", error
        tried.append(f"{task} {error:.2f} px")
    raise SekdError(f"{run}: no step model passes the regression guard ({', '.join(tried) or 'none validated'}; "
                    f"limit {GUARD_PX:g} px)")


def _check_guard(source: Path) -> float:
    error = graffiti_corner_error(source)
    if not error < GUARD_PX:  # also refuses NaN (no homography found)
        raise SekdError(f"{source}: v_graffiti 1-2 mean corner error {error:.2f} px, not under {GUARD_PX:g} px "
                        "(the embedded model's regression guard); ship another checkpoint with --which")
    return error


def validate_net(net: SEKDNet, config: TrainConfig) -> dict:
    """The run's validation (same sequences, size, keypoints) of any network."""
    from .validate import evaluate, find_sequences

    return evaluate(net, find_sequences(config.val_sets), config.val_long_side,
                    config.val_max_keypoints, config.val_threshold, config.val_nms_radius, torch.device("cpu"))


def _validation_rows(run: Path | None, extra: list[dict]) -> list[str]:
    """Validation table rows: the run's ``metrics.json`` (none without a run), then ``extra``."""
    rows = json.loads((run / "metrics.json").read_text()) if run and (run / "metrics.json").is_file() else []
    rows += extra
    lines = ["| after | MMA@3 | MMA@3 i | MMA@3 v | HA@3 | Avg.HA@1:10 | matches |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['task']} | {r['mma3']:.3f} | {r['mma3_i']:.3f} | {r['mma3_v']:.3f} | {r['ha3']:.2f} | "
                     f"{r['ha_avg']:.3f} | {r['matches']:.0f} |")
    return lines


def _label_rows(run: Path) -> list[str]:
    history = json.loads((run / "history.json").read_text())
    lines = ["| labels | keypoints / image | images |", "|---|---|---|"]
    lines += [f"| {r['task']} | {r['keypoints']:.1f} | {r['images']} |" for r in history["labels"]]
    return lines


def _progress(state: dict, config: dict) -> str:
    return f"tasks done: {', '.join(state['done'])} ({finished_rounds(state['done'])} of {config['rounds']} rounds)"


def _fork_rows(state: dict) -> list[str]:
    """A card row saying which run a forked run copied its first steps from (``sekd evolve --fork``)."""
    fork = state.get("forked_from")
    if not fork:
        return []
    return [(f"| forked | from `{Path(fork['run']).name}` after `{fork['after']}` (`sekd evolve --fork`; changed: "
             f"{', '.join(fork['changed'])}): the steps up to there were computed once, for that run, with the "
             "same settings; the command above reproduces the same model |")]


def _chosen_row(meta: dict) -> str:
    """Which checkpoint of the run was shipped: a step model, or a weighted average of steps."""
    score = f"validation MMA@3 {meta['validation']['mma3']:.3f}"
    if "average" in meta:
        parts = " + ".join(f"{item['weight']:g} x `{item['task']}`" for item in meta["average"])
        return f"| chosen | `{meta['source']}` = the weighted average {parts} of the run's step models; {score} |"
    if "task" not in meta:  # a checkpoint that does not say which step made it (e.g. a copied model)
        return f"| chosen | `{meta['source']}`; {score} |"
    return (f"| chosen | `{meta['source']}` = the model after `{meta['task']}` (round {meta['round']}, step "
            f"{meta['step']}); {score} |")


def _lineage_seconds(init: dict | None) -> float | None:
    """Training seconds of the chain of starting models, or None where a link's time is unknown."""
    total = 0.0
    while init:
        if "wall_seconds" not in init:
            return None
        total, init = total + init["wall_seconds"], init.get("init")
    return total


def _wall_row(meta: dict) -> str:
    """Training time up to the shipped model; with shipped starting models, their time added."""
    hours = meta["wall_seconds"] / 3600
    text = f"{hours:.2f} h of training on a 2-core CPU (no GPU) up to this model, summed over the resumed runs"
    earlier = _lineage_seconds(meta.get("init")) if meta.get("init") else None
    if earlier:
        text += (f", after {earlier / 3600:.2f} h for its starting model(s): "
                 f"{hours + earlier / 3600:.2f} h from random weights")
    return f"| wall time | {text} |"


def _init_rows(init: dict | None) -> list[str]:
    """Card rows for the model a run started from, and the one that started from, and so on."""
    rows = []
    while init:
        if "sha256" not in init:
            rows.append(f"| starts from | `{init['file']}` (no longer on disk when this card was written) |")
            break
        made = (f": the model shipped from `{init['shipped_from']}` (`{init.get('source', '?')}`), trained by "
                f"`{init['command']}`" if "shipped_from" in init else "")
        rows.append(f"| starts from | `{init['file']}`, SHA-256 `{init['sha256']}`{made} |")
        init = init.get("init")
    return rows


def model_card(run: Path, model: Path, meta: dict, extra: list[dict] = ()) -> str:
    """Markdown: what, data, schedule, command, wall time, seed, validation per round, checksum."""
    config = meta["config"]
    state = json.loads((run / "state.json").read_text())
    n_params = count_parameters(SEKDNet())
    lines = [
        "# Model card: `own`, the embedded SEKD model trained by this project (`--model own`)",
        "",
        "Generated by `scripts/train_default/ship.sh` (`python -m sekd_sfm.train.ship`) from the run folder",
        f"`{run.name}/` of `sekd evolve` (kept out of the repository; the commands below rebuild it); every",
        "figure below is read from that run folder.",
        "",
        "| | |",
        "|---|---|",
        f"| file | `sekd_sfm/model/checkpoints/{model.name}` ({model.stat().st_size:,} bytes, fp32) |",
        f"| SHA-256 | `{file_sha256(model, 64)}` |",
        f"| network | SEKD (the paper's architecture), {n_params:,} parameters |",
        _chosen_row(meta),
        *([(f"| regression guard | v_graffiti 1-2 mean corner error {meta['graffiti_1_2_corner_error']:.2f} px "
            f"(must stay under {GUARD_PX:g} px) |")] if "graffiti_1_2_corner_error" in meta else []),
        f"| data | `{meta['data']}`: 256 unlabeled COCO photos, no labels of any kind |",
        (f"| schedule | `{config['schedule']}`: {config['rounds']} rounds, subset 1/{config['subset_factor']} of the images "
         f"per round, long side {config['long_side']} px, crops {config['crop_height']}x{config['crop_width']}, "
         f"batch {config['batch_size']}, {config['epochs_desc']} + {config['epochs_det']} epochs per step, "
         f"lr {config['lr']} |"),
        f"| seed | {config['seed']} |",
        f"| progress | {_progress(state, config)} |",
        _wall_row(meta),
        *_init_rows(meta.get("init")),
        f"| command | `{meta['command']}` (resumed with `sekd evolve --resume --out ...`) |",
        *_fork_rows(state),
        *([f"| average | `{meta['average_command']}` (no training: a weighted mean of the weights) |"]
          if "average" in meta else []),
        "",
        "## Validation during training",
        "",
        (f"Homography sequences of the shared data at long side {config['val_long_side']} px, "
         f"top {config['val_max_keypoints']} keypoints, mutual NN (`train/validate.py`), after each training step "
         "the run validated (the rows below); the shipped checkpoint and the reference are scored the same way by `ship.py`."),
        "",
        *_validation_rows(run, list(extra)),
        "",
        "## Self-labelled keypoints per image",
        "",
        *_label_rows(run),
        "",
        "Benchmarks against the authors' model, the classics and the kornia peers: the README's",
        "Results section and [benchmarks.md](benchmarks.md).",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, nargs="+",
                        help="run folder of sekd evolve; several for a weight average of models from several runs "
                             "(--which AVERAGE.pth, whose ingredients may also be shipped models or averages)")
    parser.add_argument("--which", default="best.pth",
                        help="checkpoint in the run folder (default best.pth), auto: the best-validated step "
                             "model that passes the regression guard, or a weight average of the run's step models "
                             "(python -m sekd_sfm.train.soup)")
    parser.add_argument("--dest", type=Path, default=EMBEDDED_MODELS["own"])
    parser.add_argument("--card", type=Path, default=None, help="write the model card here (Markdown)")
    parser.add_argument("--reference", type=Path, default=None,
                        help="checkpoint scored by the same validation for the card (e.g. the authors' sekd.pth)")
    parser.add_argument("--no-guard", action="store_true",
                        help=f"ship even if v_graffiti 1-2 is not within {GUARD_PX:g} px (the tests will fail)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        if len(args.run) > 1:
            dest = ship_average(args.run, Path(args.which), args.dest, args.card, args.reference, guard=not args.no_guard)
        else:
            dest = ship_model(args.run[0], args.dest, args.card, args.which, args.reference, guard=not args.no_guard)
    except SekdError as exc:
        raise SystemExit(f"Error: {exc}") from None
    print(f"{dest}: {dest.stat().st_size:,} bytes, sha256 {file_sha256(dest, 64)}")


if __name__ == "__main__":
    main()
