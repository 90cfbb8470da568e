"""The self-evolving outer loop (docs/method.md "Training"), the run folder, checkpoints and resume.

A run is a list of tasks: labelling steps (a0 random, a detector, c reliability) and
training steps (b descriptor, d detector), each tagged with its round. ``sekd evolve``
runs all rounds; ``sekd train`` runs one labelling step and one training step. After
every task the run folder records it as done; training steps also save their state
after every epoch, so ``--resume`` continues a crashed or interrupted run and reaches
the same model as an uninterrupted one. ``state.json`` records the image list (count and
checksum of names and sizes): a resume on a changed image folder is refused, since labels
are stored by image index.

Run folder::

    config.yaml  state.json  train.log  history.json  losses.csv  labels.csv
    metrics.json  metrics.csv  curves.png  best.pth  last.pth
    .lock (held by the running process: a second run on the folder is refused)
    labels/r{k}_{a0|a|c}.npz       models/r{k}_{b|d}.pth
    labels/r{k}_{a0|a|c}.parts/    (chunks of a labelling step not finished yet)
    checkpoints/r{k}_{b|d}_e{n}.pth  checkpoints/resume.pt
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from ..errors import SekdError
from ..files.images import list_images
from ..files.locking import exclusive_lock
from ..runtime import allocator_tuned
from .config import RUNTIME_FIELDS, TrainConfig, apply, check_memory, load_run_config
from .config import validate as validate_config
from .data import TrainImages, subset_indices
from .distributed import Context, barrier, setup, teardown
from .labels import Labels, label_images
from .model import export, initial_network, use_fast_deconv
from .report import History, write_atomic
from .steps import train_step
from .validate import evaluate, find_sequences

logger = logging.getLogger("sekd.train")
KEYPOINT_SOURCES = {"random": "a0", "detector": "a", "reliability": "c"}
STEPS = {"desc": "b", "det": "d"}


@dataclass(frozen=True)
class Task:
    """One step of a run. Training tasks name the labelling task whose keypoints they learn from."""

    round: int
    kind: str                # a0, a, c (labelling) or b, d (training)
    labels: str = ""
    validate: bool = False

    @property
    def id(self) -> str:
        return "start" if self.kind == "start" else f"r{self.round}_{self.kind}"

    @property
    def training(self) -> bool:
        return self.kind in ("b", "d")


@dataclass(frozen=True)
class RunResult:
    folder: Path
    best: Path
    last: Path
    validation: list


def evolve_tasks(cfg: TrainConfig) -> list[Task]:
    """All rounds: round 0 = (c), (d) [code] or (a0), (b), (c), (d) [paper]; later rounds (a)-(d).

    Both training steps validate, so the best model may be one whose last step was (b) (a
    better descriptor on the previous round's detector).
    """
    tasks = []
    for k in range(cfg.rounds):
        if k > 0 or cfg.round0_random:
            first = "a" if k > 0 else "a0"
            tasks += [Task(k, first), Task(k, "b", labels=f"r{k}_{first}", validate=True)]
        tasks += [Task(k, "c"), Task(k, "d", labels=f"r{k}_c", validate=True)]
    return tasks


def step_tasks(step: str, keypoints: str, round_index: int = 0) -> list[Task]:
    """One training step (``desc`` or ``det``) on keypoints from ``detector``, ``reliability`` or ``random``."""
    if step not in STEPS or keypoints not in KEYPOINT_SOURCES:
        raise SekdError(f"step must be one of {sorted(STEPS)} and keypoints one of {sorted(KEYPOINT_SOURCES)}")
    label = Task(round_index, KEYPOINT_SOURCES[keypoints])
    return [label, Task(round_index, STEPS[step], labels=label.id, validate=True)]


class RunFolder:
    """Paths and persistent state of a run folder."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.state_path = self.root / "state.json"

    def labels_path(self, task_id: str) -> Path:
        return self.root / "labels" / f"{task_id}.npz"

    def label_parts(self, task_id: str) -> Path:
        """Chunk files of a labelling step still running (or interrupted): what its resume reuses."""
        return self.root / "labels" / f"{task_id}.parts"

    def model_path(self, task_id: str) -> Path:
        return self.root / "models" / f"{task_id}.pth"

    @property
    def resume_path(self) -> Path:
        return self.root / "checkpoints" / "resume.pt"

    def check_new(self) -> None:
        if self.state_path.exists():
            raise SekdError(f"{self.root}: already holds a run; pass --resume to continue it or choose another --out")

    def read(self, runtime: dict | None) -> tuple[TrainConfig, list[Task], dict]:
        """Config, tasks and state of an existing run; ``runtime`` may change hardware fields only."""
        if not self.state_path.is_file():
            raise SekdError(f"{self.root}: no run to resume (state.json not found); start one without --resume")
        not_runtime = sorted(set(runtime or {}) - set(RUNTIME_FIELDS))
        if not_runtime:
            raise SekdError(f"--resume keeps the run's config; only {', '.join(RUNTIME_FIELDS)} may change "
                            f"(got {', '.join(not_runtime)})")
        config = apply(load_run_config(self.root / "config.yaml"), dict(runtime or {}), "resume override")
        state = json.loads(self.state_path.read_text())
        return config, [Task(**t) for t in state["tasks"]], state

    def create(self, config: TrainConfig, tasks: list[Task], images: dict | None = None) -> dict:
        for sub in ("labels", "models", "checkpoints"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        write_atomic(self.root / "config.yaml", config.to_yaml())
        state = {"tasks": [asdict(t) for t in tasks], "done": [], "best": None, "images": images}
        self.save_state(state)
        return state

    def save_state(self, state: dict) -> None:
        write_atomic(self.state_path, json.dumps(state, indent=1))

    def load_resume(self, task: Task, device: torch.device) -> dict | None:
        """The epoch state saved by an interrupted ``task``, if any."""
        if not self.resume_path.is_file():
            return None
        state = torch.load(self.resume_path, map_location=device, weights_only=True)
        return state if state.get("task") == task.id else None

    def save_epoch(self, task: Task, epoch: int, state: dict, net, cfg: TrainConfig) -> None:
        if cfg.keep_epoch_checkpoints:
            export(net, self.root / "checkpoints" / f"{task.id}_e{epoch + 1}.pth", meta_of(task, cfg, epoch))
        tmp = self.resume_path.with_name(f"resume.pt.{os.getpid()}.tmp")
        torch.save({**state, "task": task.id}, tmp)
        os.replace(tmp, self.resume_path)


def meta_of(task: Task | None, cfg: TrainConfig, epoch: int | None = None, **extra) -> dict:
    """Metadata stored in exported checkpoints."""
    meta = {"schedule": cfg.schedule, "seed": cfg.seed, "config": cfg.as_dict(), **extra}
    if task is not None:
        meta.update(task=task.id, round=task.round, step=task.kind)
    if epoch is not None:
        meta["epoch"] = epoch + 1
    return meta


class Runner:
    """Executes the tasks of one run folder in one process of a (possibly distributed) job."""

    def __init__(self, folder: RunFolder, cfg: TrainConfig, tasks: list[Task], state: dict, ctx: Context):
        self.folder, self.cfg, self.tasks, self.state, self.ctx = folder, cfg, tasks, state, ctx
        self.images = TrainImages(cfg.images, cfg.long_side, cfg.size_multiple, cfg.cache_images)
        if len(self.images) < cfg.subset_factor:
            raise SekdError(f"{cfg.images}: {len(self.images)} images cannot fill {cfg.subset_factor} round subsets")
        self.history = History(folder.root)
        self.val_sets = find_sequences(cfg.val_sets) if cfg.validate else []
        self.net = self._current_model()

    def _current_model(self):
        done = [t for t in self.tasks if t.training and t.id in self.state["done"]]
        net = initial_network(self.cfg.init_weights, self.cfg.seed)
        if done:  # resume: the model after the last finished training step
            net.load_state_dict(torch.load(self.folder.model_path(done[-1].id), map_location="cpu",
                                           weights_only=True)["state_dict"])
        if self.cfg.fast_deconv:
            use_fast_deconv(net)
        return net.to(self.ctx.device).eval()

    def run(self) -> None:
        if self.cfg.validate and self.cfg.validate_start and "start" not in self.state["done"]:
            self._validate(Task(-1, "start"))
            self._mark_done("start")
        for task in self.tasks:
            if task.id in self.state["done"]:
                continue
            self._train(task) if task.training else self._label(task)
            if task.validate and self.cfg.validate:
                self._validate(task)
            elif task.validate and self.ctx.main:
                export(self.net, self.folder.root / "last.pth", meta_of(task, self.cfg))
            self._mark_done(task.id)
        if self.ctx.main:
            self._finish()
        barrier(self.ctx)

    def _label(self, task: Task) -> None:
        indices = subset_indices(len(self.images), self.cfg.subset_factor, task.round)
        parts = self.folder.label_parts(task.id)
        labels = label_images(self.net, self.images, indices, task.kind, task.round, self.cfg, self.ctx,
                              self.cfg.progress, parts)
        n = labels.mean_keypoints
        logger.info("round %d labels (%s): %.1f keypoints per image over %d images, background weight %.3g%s",
                    task.round, task.kind, n, len(indices), labels.bg_weight,
                    "" if labels.threshold is None else f", score threshold {labels.threshold:.4g}")
        if task.kind == "c" and labels.threshold is not None and labels.threshold < self.cfg.rel_threshold:
            logger.info("rel_threshold %.4g lowered to %.4g to keep %g keypoints per image (rel_min_keypoints)",
                        self.cfg.rel_threshold, labels.threshold, self.cfg.rel_min_keypoints)
        if task.kind != "a0" and n < 0.2 * self.cfg.max_keypoints:
            logger.warning("few keypoints per image (%.1f); consider lowering %s", n,
                           "det_threshold" if task.kind == "a" else "rel_threshold or raising rel_min_keypoints")
        if self.ctx.main:
            labels.save(self.folder.labels_path(task.id))
            shutil.rmtree(parts, ignore_errors=True)  # after the save: a crash in between only keeps spare files
            self.history.add("labels", {"task": task.id, "round": task.round, "kind": task.kind,
                                        "keypoints": n, "images": len(indices), "bg_weight": labels.bg_weight,
                                        "threshold": labels.threshold})
            self.history.save(plot=False)
        barrier(self.ctx)

    def _train(self, task: Task) -> None:
        labels = Labels.load(self.folder.labels_path(task.labels))
        alpha = self.cfg.alpha_round0 if labels.kind == "a0" else self.cfg.alpha
        resume = self.folder.load_resume(task, self.ctx.device)
        if resume is not None:
            logger.info("resuming %s after epoch %d", task.id, resume["epoch"] + 1)
            self._record_epochs(task, resume["history"])

        def checkpoint(epoch: int, state: dict) -> None:
            if self.ctx.main:  # history first: a crash in between only repeats a (keyed) record
                self._record_epochs(task, state["history"][-1:])
                self.folder.save_epoch(task, epoch, state, self.net, self.cfg)

        train_step(self.net, task.kind, labels, self.images, self.cfg, self.ctx, task.round, resume, checkpoint, alpha)
        if self.ctx.main:
            export(self.net, self.folder.model_path(task.id), meta_of(task, self.cfg))

    def _record_epochs(self, task: Task, records: list[dict]) -> None:
        if self.ctx.main:
            for record in records:
                self.history.add("epochs", {**record, "task": task.id})
            self.history.save(plot=False)  # curves are redrawn after validation and at the end

    def _validate(self, task: Task) -> None:
        if self.ctx.main:
            cfg = self.cfg
            metrics = evaluate(self.net, self.val_sets, cfg.val_long_side, cfg.val_max_keypoints,
                               cfg.val_threshold, cfg.val_nms_radius, self.ctx.device)
            logger.info("validation after %s: %s", task.id,
                        " ".join(f"{k}={v:.4g}" for k, v in metrics.items() if isinstance(v, float)))
            self.history.add("validation", {"task": task.id, "round": task.round, **metrics})
            self.history.save()
            if task.kind != "start":
                self._export_best_last(task, metrics)
        barrier(self.ctx)

    def _export_best_last(self, task: Task, metrics: dict) -> None:
        key, best = self.cfg.best_metric, self.state.get("best")
        export(self.net, self.folder.root / "last.pth", meta_of(task, self.cfg, validation=metrics))
        if best is None or metrics[key] > best["value"]:
            export(self.net, self.folder.root / "best.pth", meta_of(task, self.cfg, validation=metrics, best_by=key))
            self.state["best"] = {"task": task.id, "metric": key, "value": metrics[key]}
            logger.info("new best model (%s = %.4f) after %s", key, metrics[key], task.id)

    def _mark_done(self, task_id: str) -> None:
        self.state["done"].append(task_id)
        if self.ctx.main:
            self.folder.save_state(self.state)
            self.folder.resume_path.unlink(missing_ok=True)
        barrier(self.ctx)

    def _finish(self) -> None:
        last = [t for t in self.tasks if t.training][-1]
        root = self.folder.root
        if not self.cfg.validate:  # nothing to rank models by: best = last
            export(self.net, root / "best.pth", meta_of(last, self.cfg, best_by="none (validation off)"))
        self.history.save()
        logger.info("run finished: %s (best %s)", root, self.state.get("best"))


def run_tasks(out: Path, config: TrainConfig | None, tasks: list[Task] | None, resume: bool = False,
              runtime: dict | None = None) -> RunResult:
    """Run (or, with ``resume``, continue) the tasks of the run folder ``out``.

    New runs need ``config`` and ``tasks``; resumed runs read both from the folder, and
    ``runtime`` may change only the hardware fields (device, threads, workers, progress).
    """
    folder = RunFolder(out)
    if resume and not folder.state_path.is_file():
        folder.read(runtime)  # SekdError: nothing to resume (before creating anything)
    with _run_lock(folder.root):
        return _run_locked(folder, config, tasks, resume, runtime)


def _run_lock(root: Path):
    """The run folder's exclusive lock, taken by the first process of a (possibly distributed) job.

    A second ``sekd evolve``/``train`` on the same folder is refused with the holder's PID
    (it would interleave checkpoints and history writes).
    """
    if int(os.environ.get("RANK", "0")) != 0:
        return contextlib.nullcontext()
    Path(root).mkdir(parents=True, exist_ok=True)  # so the lock is always <folder>/.lock
    return exclusive_lock(root, what="run folder")


def image_fingerprint(root: str | Path) -> dict:
    """Count and SHA-256 of the sorted image keys with their sizes in bytes: what labels are indexed by."""
    root = Path(root)
    digest = hashlib.sha256()
    keys = list_images(root)
    for key in keys:
        digest.update(f"{key}\t{(root / key).stat().st_size}\n".encode())
    return {"count": len(keys), "sha256": digest.hexdigest()}


def _check_images(folder: RunFolder, config: TrainConfig, state: dict) -> dict:
    """Refuse to resume on a changed image folder (labels are stored by image index); record the list if new."""
    current = image_fingerprint(config.images)
    saved = state.get("images")
    if saved is not None and saved != current:
        what = (f"{saved['count']} images then, {current['count']} now" if saved["count"] != current["count"]
                else f"the same {current['count']} images in number, but files renamed or changed")
        raise SekdError(
            f"{config.images}: the training images changed since this run started ({what}); its labels are "
            f"indexed by the old list: restore the images or start a new run in another --out")
    return current


def _run_locked(folder: RunFolder, config: TrainConfig | None, tasks: list[Task] | None, resume: bool,
                runtime: dict | None) -> RunResult:
    if resume:
        config, tasks, state = folder.read(runtime)
    else:
        folder.check_new()
        validate_config(config)
        state = None
    _check_inputs(config, tasks)
    check_memory(config)
    images = _check_images(folder, config, state or {})
    ctx = setup(config.device, config.num_threads)
    try:
        return _run_in_group(folder, config, tasks, state, images, resume, ctx)
    finally:
        teardown()  # a torchrun process leaves its group, so a library caller may start another run


def _run_in_group(folder: RunFolder, config: TrainConfig, tasks: list[Task], state: dict | None, images: dict,
                  resume: bool, ctx: Context) -> RunResult:
    if config.batch_size % ctx.world:
        raise SekdError(f"batch_size {config.batch_size} must be a multiple of the {ctx.world} processes")
    barrier(ctx)  # every process has checked the folder before the first one writes to it
    if state is None:
        state = folder.create(config, tasks, images) if ctx.main else {"tasks": [asdict(t) for t in tasks], "done": [],
                                                                       "best": None, "images": images}
    elif state.get("images") is None:  # a run started before image lists were recorded: record it now
        state["images"] = images
        if ctx.main:
            folder.save_state(state)
    barrier(ctx)
    handler = _log_to_file(folder.root / "train.log") if ctx.main else None
    try:
        logger.info("%s run in %s: %d process(es) on %s, %d threads each", "resumed" if resume else "new",
                    folder.root, ctx.world, ctx.device, torch.get_num_threads())
        runner = Runner(folder, config, tasks, state, ctx)
        # On the CPU freed buffers stay in the heap for the next step (runtime.allocator_tuned).
        with allocator_tuned() if ctx.device.type == "cpu" else contextlib.nullcontext():
            runner.run()
    except KeyboardInterrupt:
        logger.warning("interrupted; continue with --resume")
        raise
    finally:
        if handler is not None:
            logging.getLogger("sekd.train").removeHandler(handler)
            handler.close()
    return RunResult(folder.root, folder.root / "best.pth", folder.root / "last.pth",
                     runner.history.data["validation"])


def _check_inputs(config: TrainConfig, tasks: list[Task]) -> None:
    images = Path(config.images)
    if not config.images or not images.is_dir():
        raise SekdError(f"{config.images or '(none)'}: training image folder not found; pass --images DIR")
    if config.init_weights and not Path(config.init_weights).expanduser().is_file():
        raise SekdError(f"{config.init_weights}: starting weights not found")
    if not any(t.training for t in tasks):
        raise SekdError("nothing to train: the run has no training step")


def _log_to_file(path: Path) -> logging.Handler:
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log = logging.getLogger("sekd.train")
    log.addHandler(handler)
    if log.getEffectiveLevel() > logging.INFO:
        log.setLevel(logging.INFO)
    return handler


def evolve(out: Path, config: TrainConfig | None = None, resume: bool = False,
           runtime: dict | None = None) -> RunResult:
    """``sekd evolve``: all rounds of the self-evolving loop."""
    return run_tasks(out, config, None if config is None else evolve_tasks(config), resume, runtime)


def train_one_step(out: Path, config: TrainConfig | None, step: str = "det", keypoints: str = "reliability",
                   round_index: int = 0, resume: bool = False, runtime: dict | None = None) -> RunResult:
    """``sekd train``: one labelling step and one training step from ``config.init_weights``."""
    tasks = None if resume else step_tasks(step, keypoints, round_index)
    return run_tasks(out, config, tasks, resume, runtime)
