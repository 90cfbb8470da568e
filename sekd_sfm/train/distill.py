"""Distillation of SEKD-Lite from a full SEKD model (``sekd distill``, docs/model_card_lite.md).

The teacher (a full SEKD checkpoint, fp32, eval mode) and the student (:class:`SEKDLiteNet`)
see the same augmented grayscale crops of training photos: a random perspective warp of a
random window at a random scale, then photometric jitter (gain, bias, gamma, blur, noise).
The student learns to reproduce the teacher's outputs:

- detector: squared error between the student's and the teacher's keypoint logits
  (``log p / (1 - p)``). The teacher's probabilities lie within a few hundredths of 0.5
  almost everywhere and extraction keeps the local maxima above 0.4, so what must be
  copied is the fine ranking of nearby pixels: the logit spreads it ~4x wider than the
  probability, and a cross-entropy against targets near 0.5 would be almost flat. Pixels
  where the teacher has a keypoint (local maximum over 9 x 9 above 0.4, as extraction
  finds them) weigh ``1 + peak_weight``;
- descriptor: ``1 - cos`` between the L2-normalised student and teacher descriptors at every
  1/4-resolution cell, cells holding a teacher keypoint weighted ``1 + peak_weight``
  (descriptors are sampled at keypoints);
- matching (``pair_weight`` > 0, off by default): the batch holds pairs of views of one photo
  window related by a known homography (a second rotation, scale and perspective warp), and
  the student's descriptors at the teacher's keypoints of the first view and at their
  positions in the second view enter the triplet loss ``evolve`` trains with (hardest
  in-view negative, the authors' ratio form). Copying the teacher optimises closeness to
  it; a 64-channel student cannot copy 128 dimensions exactly, and this term spends what it
  can copy on telling points apart across viewpoints, which is what matching needs.

Run folder (glue-factory style): ``config.json`` (every setting), ``state.pt`` (student,
optimiser, step; written atomically every few minutes and at the end), ``last.pth`` (the
student as a loadable checkpoint, same times), ``metrics.jsonl`` (training losses and
validation numbers against the teacher on held-out photos), ``student.pth`` (final model).
Every random draw depends only on (seed, step, sample), so ``resume=True`` continues an
interrupted run exactly where its last state left it.
"""
from __future__ import annotations

import copy
import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..errors import SekdError
from ..evaluation.samplers import (
    jitter_gray,
    random_view_change,
    random_window_homography,
)
from ..files.atomic import atomic_output, write_atomic
from ..files.locking import exclusive_lock
from ..model.fused import fp32_eval_forward
from ..model.inference import nms_keypoints, sample_descriptors
from ..model.lite import DEFAULT_CONFIG, SEKDLiteNet, build_lite
from ..model.network import SEKDNet, use_fast_deconv
from ..model.weights import (
    DEFAULT_MODEL,
    FULL_ARCHITECTURE,
    LITE_ARCHITECTURE,
    embedded_model_path,
    file_sha256,
    load_model,
    save_checkpoint,
)
from ..runtime import allocator_tuned, set_num_threads, shared_dir
from .config import CHOICES
from .data import TrainImages
from .losses import triplet_loss
from .steps import autocast_dtype

#: The training precisions `evolve` takes, the same for the student here.
TRAIN_PRECISIONS = CHOICES["train_precision"]

CONFIG_NAME, STATE_NAME, LAST_NAME, FINAL_NAME, METRICS_NAME = (
    "config.json", "state.pt", "last.pth", "student.pth", "metrics.jsonl")


@dataclass
class DistillConfig:
    """Every setting of a distillation run (saved as ``config.json`` in the run folder)."""

    teacher: str = DEFAULT_MODEL          # embedded model name or checkpoint path (full SEKD network)
    photos: str = ""                      # folder of training photos ("" = shared COCO photos)
    student: dict = field(default_factory=lambda: copy.deepcopy(DEFAULT_CONFIG))  # SEKDLiteNet config
    #: Student to start from: ``lite`` (the embedded SEKD-Lite) or a SEKD-Lite checkpoint; "" = random
    #: initialisation. Continuing a distillation with a new schedule (more steps, another teacher or
    #: augmentation) costs a fraction of a run from scratch; the student's channels are the checkpoint's.
    init: str = ""
    #: Student training: fp32, or bf16 mixed precision (autocast; fp32 weights, optimiser and losses;
    #: the teacher stays fp32), or auto = bf16 where the CPU computes it natively (as `evolve`).
    train_precision: str = "fp32"
    steps: int = 3000
    batch_size: int = 8
    crop: list = field(default_factory=lambda: [192, 256])  # height, width (multiples of 4)
    long_side: int = 512                  # photos are resized to this long side before cropping
    scale_range: list = field(default_factory=lambda: [0.5, 1.0])  # crop scale relative to long_side
    perspective: float = 0.15             # max corner displacement, fraction of the crop size
    rotation_deg: float = 20.0
    lr: float = 3e-3
    lr_min: float = 3e-5                  # cosine decay from lr to lr_min over the steps
    warmup_steps: int = 100
    weight_decay: float = 1e-5
    peak_weight: float = 20.0
    detector_weight: float = 10.0         # total loss = detector_weight * detector + descriptor_weight * descriptor
    descriptor_weight: float = 1.0        #              + pair_weight * matching
    #: Weight of the cross-view matching term (module docstring); 0 = plain distillation. When > 0 the
    #: batch is batch_size / 2 view pairs (same cost per step), so batch_size must be even.
    pair_weight: float = 0.0
    # The second view of a pair relative to the first (stronger than the single-view warp: the
    # student's descriptors fall behind the teacher's as the viewpoint change grows).
    pair_scale_range: list = field(default_factory=lambda: [0.7, 1.4])
    pair_perspective: float = 0.3
    pair_rotation_deg: float = 30.0
    pair_keypoints: int = 256             # teacher keypoints per pair entering the matching term (strongest first)
    val_photos: int = 16                  # the last photos (sorted names) are held out for validation
    val_every: int = 250                  # steps between validations
    save_every_s: float = 180.0           # seconds between state writes
    seed: int = 0

    def check(self) -> None:
        """SekdError for settings that cannot run."""
        if self.steps < 1 or self.batch_size < 1:
            raise SekdError(f"--steps and --batch-size must be >= 1 (got {self.steps}, {self.batch_size})")
        if len(self.crop) != 2 or any(c < 16 or c % 4 for c in self.crop):
            raise SekdError(f"--crop must be HEIGHT WIDTH, multiples of 4 and >= 16 (got {self.crop})")
        if self.train_precision not in TRAIN_PRECISIONS:
            raise SekdError(f"train_precision must be one of {', '.join(TRAIN_PRECISIONS)} (got {self.train_precision!r})")
        if not 0 < self.scale_range[0] <= self.scale_range[1]:
            raise SekdError(f"scale_range must satisfy 0 < low <= high (got {self.scale_range})")
        if self.pair_weight < 0 or (self.pair_weight > 0 and self.batch_size % 2):
            raise SekdError(f"--pair-weight must be >= 0, and > 0 needs an even --batch-size "
                            f"(got {self.pair_weight}, {self.batch_size})")
        if not 0 < self.pair_scale_range[0] <= self.pair_scale_range[1] or self.pair_keypoints < 2:
            raise SekdError(f"pair_scale_range must satisfy 0 < low <= high and pair_keypoints >= 2 "
                            f"(got {self.pair_scale_range}, {self.pair_keypoints})")
        try:
            build_lite(self.student)
        except (ValueError, TypeError, KeyError) as exc:
            raise SekdError(f"invalid student configuration {self.student}: {exc}") from exc


# --- data --------------------------------------------------------------------------------

def photo_folder(config: DistillConfig) -> Path:
    """The training photo folder: ``config.photos`` or the shared COCO photos."""
    return Path(config.photos).expanduser() if config.photos else shared_dir() / "data" / "train" / "coco"


def split_photos(count: int, val_photos: int) -> tuple[list[int], list[int]]:
    """(training, validation) indices: the last ``val_photos`` photos validate, never more than half."""
    val = min(val_photos, count // 2)
    return list(range(count - val)), list(range(count - val, count))


def _random_window(rng: np.random.Generator, image_hw: tuple[int, int], crop_hw: tuple[int, int],
                   config: DistillConfig) -> np.ndarray:
    """3x3 map from crop pixels to image pixels: a random window at a random scale, rotated and
    perspective-distorted (``samplers.random_window_homography`` with the run's ranges)."""
    return random_window_homography(rng, image_hw, crop_hw, config.scale_range, config.perspective,
                                    config.rotation_deg)


def _view(gray: np.ndarray, homography: np.ndarray, rng: np.random.Generator, crop_hw: tuple[int, int]) -> np.ndarray:
    """The ``crop_hw`` float32 view in [0, 1] whose pixel x shows ``gray`` at ``homography @ x``, jittered."""
    ch, cw = crop_hw
    warped = cv2.warpPerspective(gray, homography, (cw, ch), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REFLECT_101)
    return jitter_gray(warped.astype(np.float64) / 255, rng).astype(np.float32)


def make_sample(gray: np.ndarray, rng: np.random.Generator, config: DistillConfig) -> np.ndarray:
    """One augmented ``crop_h x crop_w`` float32 view in [0, 1] of an ``H x W`` uint8 photo."""
    crop = tuple(config.crop)
    return _view(gray, _random_window(rng, gray.shape, crop, config), rng, crop)


def make_pair(gray: np.ndarray, rng: np.random.Generator, config: DistillConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two augmented views of one window of ``gray`` and the 3x3 map from view-0 pixels to view-1 pixels."""
    crop = tuple(config.crop)
    to_image = _random_window(rng, gray.shape, crop, config)
    one_to_zero = random_view_change(rng, crop, config.pair_scale_range, config.pair_perspective,
                                     config.pair_rotation_deg)
    view0 = _view(gray, to_image, rng, crop)
    view1 = _view(gray, to_image @ one_to_zero, rng, crop)
    return view0, view1, np.linalg.inv(one_to_zero)


class GrayPhotos:
    """Grayscale uint8 photos resized to ``long_side`` (cached), read through the training loader."""

    def __init__(self, folder: Path, long_side: int):
        if not folder.is_dir():
            raise SekdError(f"{folder}: photo folder not found; pass --photos with a folder of images")
        self.images = TrainImages(folder, long_side, multiple=4)
        if len(self.images) < 2:
            raise SekdError(f"{folder}: distillation needs at least 2 photos, found {len(self.images)}")

    def __len__(self) -> int:
        return len(self.images)

    def gray(self, index: int) -> np.ndarray:
        return cv2.cvtColor(self.images.rgb(index), cv2.COLOR_RGB2GRAY)


def batch_for(photos: GrayPhotos, indices: list[int], step: int, config: DistillConfig
              ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The training batch of ``step``, depending only on (seed, step): ``B x 1 x h x w`` views and, with
    ``pair_weight`` > 0, the ``B/2 x 3 x 3`` maps from view ``2i``'s pixels to view ``2i + 1``'s (else None)."""
    rng = np.random.default_rng([config.seed, 1, step])
    if config.pair_weight <= 0:
        chosen = rng.choice(indices, size=config.batch_size, replace=len(indices) < config.batch_size)
        views = [make_sample(photos.gray(int(i)), np.random.default_rng([config.seed, 2, step, k]), config)
                 for k, i in enumerate(chosen)]
        return torch.from_numpy(np.stack(views))[:, None], None
    pairs = config.batch_size // 2
    chosen = rng.choice(indices, size=pairs, replace=len(indices) < pairs)
    made = [make_pair(photos.gray(int(i)), np.random.default_rng([config.seed, 4, step, k]), config)
            for k, i in enumerate(chosen)]
    views = [view for view0, view1, _ in made for view in (view0, view1)]
    maps = np.stack([m for _, _, m in made]).astype(np.float32)
    return torch.from_numpy(np.stack(views))[:, None], torch.from_numpy(maps)


def validation_batch(photos: GrayPhotos, indices: list[int], config: DistillConfig) -> torch.Tensor:
    """Fixed validation views (one per held-out photo, seed-independent)."""
    views = [make_sample(photos.gray(i), np.random.default_rng([12345, 3, i]), config) for i in indices]
    return torch.from_numpy(np.stack(views))[:, None]


def validation_pairs(photos: GrayPhotos, indices: list[int], config: DistillConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed validation view pairs (one per held-out photo, seed-independent): ``2N x 1 x h x w``, ``N x 3 x 3``."""
    made = [make_pair(photos.gray(i), np.random.default_rng([12345, 5, i]), config) for i in indices]
    views = np.stack([view for view0, view1, _ in made for view in (view0, view1)])
    return torch.from_numpy(views)[:, None], torch.from_numpy(np.stack([m for _, _, m in made]).astype(np.float32))


# --- losses ------------------------------------------------------------------------------

def teacher_peaks(teacher_logit: torch.Tensor, radius: int = 4, threshold: float = 0.4) -> torch.Tensor:
    """``B x 1 x H x W`` float mask of the teacher's keypoints: local maxima over (2r+1)^2 above ``threshold``."""
    pooled = F.max_pool2d(teacher_logit, 2 * radius + 1, stride=1, padding=radius)
    return ((teacher_logit == pooled) & (teacher_logit > math.log(threshold / (1 - threshold)))).float()


def distill_losses(logits: torch.Tensor, desc: torch.Tensor, teacher_logit: torch.Tensor, teacher_desc: torch.Tensor,
                   peak_weight: float) -> dict[str, torch.Tensor]:
    """Detector logit squared error and descriptor ``1 - cos``, both peak-weighted (see the module docstring).

    ``logits`` B x 2 x H x W (student), ``teacher_logit`` B x 1 x H x W (``logit1 - logit0``),
    ``desc``/``teacher_desc`` B x 128 x H/4 x W/4 raw.
    """
    peaks = teacher_peaks(teacher_logit)
    weight = 1 + peak_weight * peaks
    error = (logits[:, 1:2] - logits[:, 0:1] - teacher_logit) ** 2
    detector = (weight * error).sum() / weight.sum()
    cos = (F.normalize(desc, dim=1) * F.normalize(teacher_desc, dim=1)).sum(1, keepdim=True)
    cell_weight = 1 + peak_weight * F.max_pool2d(peaks, 4)
    descriptor = (cell_weight * (1 - cos)).sum() / cell_weight.sum()
    return {"detector": detector, "descriptor": descriptor}


def map_points(homography: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """``N x 2`` pixels (x, y) through a 3x3 homography -> ``N x 2``."""
    mapped = torch.cat([xy, xy.new_ones(len(xy), 1)], 1) @ homography.t()
    return mapped[:, :2] / mapped[:, 2:]


def pair_correspondences(teacher_logit: torch.Tensor, maps: torch.Tensor, max_keypoints: int,
                         border: int = 4) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per view pair (views 2i, 2i+1 of ``teacher_logit`` B x 1 x H x W; ``maps`` B/2 x 3 x 3, view-0
    pixels -> view-1 pixels): (``N x 2`` view-0 pixels, ``N x 2`` view-1 pixels) of the teacher's
    keypoints in view 0 (strongest ``max_keypoints``) whose position in view 1 lies at least
    ``border`` px inside it."""
    h, w = teacher_logit.shape[-2:]
    peaks = teacher_peaks(teacher_logit)
    found = []
    for i, homography in enumerate(maps):
        rows, cols = torch.nonzero(peaks[2 * i, 0], as_tuple=True)
        strongest = teacher_logit[2 * i, 0, rows, cols].argsort(descending=True)[:max_keypoints]
        xy0 = torch.stack([cols[strongest], rows[strongest]], 1).float()
        xy1 = map_points(homography, xy0)
        inside = ((xy1[:, 0] >= border) & (xy1[:, 0] <= w - 1 - border)
                  & (xy1[:, 1] >= border) & (xy1[:, 1] <= h - 1 - border))
        found.append((xy0[inside], xy1[inside]))
    return found


def _pair_descriptors(desc: torch.Tensor, i: int, xy0: torch.Tensor, xy1: torch.Tensor,
                      height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit descriptors of pair ``i`` at its correspondences: view 2i at ``xy0``, view 2i+1 at ``xy1``."""
    return (sample_descriptors(desc[2 * i], xy0, height, width),
            sample_descriptors(desc[2 * i + 1], xy1, height, width))


def pair_loss(desc: torch.Tensor, correspondences: list[tuple[torch.Tensor, torch.Tensor]],
              height: int, width: int) -> torch.Tensor:
    """Triplet loss (``evolve``'s ratio form) of the student's descriptors across each view pair.

    ``desc`` B x 128 x H/4 x W/4 raw student descriptors of B/2 pairs (views 2i, 2i+1) of
    ``height x width`` px, ``correspondences`` from :func:`pair_correspondences`. Pairs with
    fewer than 2 correspondences count 0; the mean over pairs.
    """
    total = desc.new_zeros(())
    for i, (xy0, xy1) in enumerate(correspondences):
        if len(xy0) >= 2:
            total = total + triplet_loss(*_pair_descriptors(desc, i, xy0, xy1, height, width))
    return total / len(correspondences)


def pair_accuracy(desc: torch.Tensor, correspondences: list[tuple[torch.Tensor, torch.Tensor]],
                  height: int, width: int) -> float:
    """Share of the correspondences whose view-0 descriptor's nearest view-1 descriptor (among the
    corresponding points) is its own: a cheap proxy of matching accuracy (arguments as ``pair_loss``)."""
    right = total = 0
    for i, (xy0, xy1) in enumerate(correspondences):
        if len(xy0):
            a, b = _pair_descriptors(desc, i, xy0, xy1, height, width)
            right += int(((a @ b.t()).argmax(1) == torch.arange(len(xy0))).sum())
            total += len(xy0)
    return right / max(total, 1)


class Teacher:
    """The full SEKD network in fp32 eval mode, prepared for speed (block-diagonal deconvolutions, channels-last)."""

    def __init__(self, net: SEKDNet):
        self.net = use_fast_deconv(copy.deepcopy(net).eval()).to(memory_format=torch.channels_last)
        for p in self.net.parameters():
            p.requires_grad_(False)
        self.forward = fp32_eval_forward(self.net, torch.device("cpu"))  # the fused forward where it applies

    @torch.no_grad()  # not inference_mode: its outputs are loss targets that autograd must save
    def __call__(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``B x 1 x H x W`` -> (keypoint logit ``logit1 - logit0`` B x 1 x H x W, raw descriptors B x 128 x H/4 x W/4)."""
        logits, desc, _ = self.forward(images.contiguous(memory_format=torch.channels_last))
        return (logits[:, 1:2] - logits[:, 0:1]).contiguous(), desc.contiguous()


@torch.no_grad()
def validate(student: SEKDLiteNet, teacher: Teacher, images: torch.Tensor, peak_weight: float,
             max_keypoints: int = 500, pairs: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, float]:
    """Student vs teacher on fixed held-out views.

    ``repeatability``: share of the teacher's top ``max_keypoints`` keypoints the student
    detects within 2 px (same NMS as extraction); ``cosine_median``: median descriptor cosine at
    the teacher's keypoints (descriptors sampled as at extraction); plus both losses. With
    ``pairs`` (views, maps of ``validation_pairs``): ``pair_accuracy`` of the student and
    ``teacher_pair_accuracy`` (the same measure for the teacher's descriptors, its reference).
    """
    was_training = student.training
    student.eval()
    logits, desc, _ = student.forward_train(images)
    t_logit, t_desc = teacher(images)
    t_prob = torch.sigmoid(t_logit)  # = the softmax probability of the keypoint class
    losses = {k: float(v) for k, v in distill_losses(logits, desc, t_logit, t_desc, peak_weight).items()}
    s_prob = F.softmax(logits, dim=1)[:, 1]
    hits, total, cosines = 0, 0, []
    h, w = images.shape[-2:]
    for b in range(images.shape[0]):
        t_xy, _ = nms_keypoints(t_prob[b, 0], 4, 0.4, max_keypoints)
        s_xy, _ = nms_keypoints(s_prob[b], 4, 0.4, max_keypoints)
        if len(t_xy):
            total += len(t_xy)
            if len(s_xy):
                hits += int((torch.cdist(t_xy.float(), s_xy.float()).min(1).values <= 2).sum())
            cos = (sample_descriptors(desc[b], t_xy.float(), h, w) * sample_descriptors(t_desc[b], t_xy.float(), h, w)).sum(1)
            cosines.append(cos)
    extra = {}
    if pairs is not None:
        views, maps = pairs
        _, pair_desc, _ = student.forward_train(views)
        pair_logit, teacher_pair_desc = teacher(views)
        found = pair_correspondences(pair_logit, maps, max_keypoints)  # once for both scores
        size = views.shape[-2:]
        extra = {"pair_accuracy": pair_accuracy(pair_desc, found, *size),
                 "teacher_pair_accuracy": pair_accuracy(teacher_pair_desc, found, *size)}
    student.train(was_training)
    cos = torch.cat(cosines) if cosines else torch.zeros(1)
    return {**losses, "repeatability": hits / max(total, 1), "cosine_median": float(cos.median()),
            "teacher_keypoints": total / images.shape[0], **extra}


# --- the run -----------------------------------------------------------------------------

def learning_rate(step: int, config: DistillConfig) -> float:
    """Linear warm-up, then cosine decay from ``lr`` to ``lr_min`` at the last step."""
    if step < config.warmup_steps:
        return config.lr * (step + 1) / config.warmup_steps
    t = (step - config.warmup_steps) / max(config.steps - config.warmup_steps, 1)
    return config.lr_min + 0.5 * (config.lr - config.lr_min) * (1 + math.cos(math.pi * min(t, 1.0)))


def _model_path(name: str, option: str) -> Path:
    """The file of an embedded model's name or of a checkpoint path; SekdError naming ``option`` otherwise."""
    try:
        return embedded_model_path(name)
    except SekdError:
        if Path(name).expanduser().is_file():
            return Path(name).expanduser()
        raise SekdError(f"{option} {name}: neither an embedded model nor an existing checkpoint file") from None


def _teacher_path(config: DistillConfig) -> Path:
    return _model_path(config.teacher, "--teacher")


def init_student(config: DistillConfig) -> tuple[Path, dict] | None:
    """``(path, state dict)`` of the checkpoint ``config.init`` names (None without one), with
    ``config.student`` set to its architecture; SekdError for a file that is not SEKD-Lite."""
    if not config.init:
        return None
    path = _model_path(config.init, "--init")
    net, info = load_model(path, architecture=LITE_ARCHITECTURE)
    config.student = dict(info.meta.get("config", config.student))
    return path, net.state_dict()


def _write_json(path: Path, data: dict) -> None:
    write_atomic(path, json.dumps(data, indent=2) + "\n")


def _save_state(folder: Path, student: SEKDLiteNet, state: dict, meta: dict) -> None:
    """Student checkpoint, then the training state (both atomic): a kill between them loses nothing needed.

    ``state``: ``{'student', 'optimizer', 'step'}`` taken at the end of a step (never mid-step:
    a forward pass in training mode already moves the BatchNorm statistics).
    """
    net = copy.deepcopy(student)
    net.load_state_dict(state["student"])
    save_checkpoint(net, folder / LAST_NAME, {**meta, "step": state["step"]})
    with atomic_output(folder / STATE_NAME) as tmp:
        torch.save(state, tmp)


def _snapshot(student: SEKDLiteNet, optimizer: torch.optim.Optimizer, step: int) -> dict:
    """A copy of the training state after ``step`` steps (the student is small: a copy costs ~1 ms)."""
    return {"student": copy.deepcopy(student.state_dict()), "optimizer": copy.deepcopy(optimizer.state_dict()),
            "step": step}


def _trim_metrics(folder: Path, step: int) -> None:
    """Drop records after ``step`` (written after the last saved state by a run that was killed) before resuming."""
    path = folder / METRICS_NAME
    if not path.is_file():
        return
    kept = [line for line in path.read_text().splitlines() if line.strip() and json.loads(line).get("step", 0) <= step]
    write_atomic(path, "".join(line + "\n" for line in kept))


def _log(folder: Path, record: dict) -> None:
    with open(folder / METRICS_NAME, "a") as f:
        f.write(json.dumps(record) + "\n")


def resumed_config(folder: Path) -> DistillConfig:
    """The recorded configuration of the run in ``folder``; SekdError if there is none."""
    path = folder / CONFIG_NAME
    if not path.is_file():
        raise SekdError(f"{folder}: no distillation to resume ({CONFIG_NAME} not found); start one without --resume")
    try:
        data = json.loads(path.read_text())
        known = {f.name for f in fields(DistillConfig)}
        return DistillConfig(**{k: v for k, v in data["config"].items() if k in known})
    except (ValueError, KeyError, TypeError) as exc:
        raise SekdError(f"{path}: unreadable run configuration ({exc}); start a new run in another folder") from exc


def distill(output: str | Path, config: DistillConfig | None = None, resume: bool = False,
            num_threads: int | None = 1, progress: bool = True) -> Path:
    """Train SEKD-Lite from ``config.teacher`` into the run folder ``output``; returns the final ``student.pth``.

    ``resume``: continue the run recorded in ``output`` (its ``config.json``; ``config`` is ignored).
    """
    folder = Path(output).expanduser()
    if resume:
        config = resumed_config(folder)
    else:
        config = config or DistillConfig()
        if (folder / CONFIG_NAME).exists():
            raise SekdError(f"{folder}: a distillation run already lives here; continue it with --resume "
                            "or choose another output folder")
    config.check()
    folder.mkdir(parents=True, exist_ok=True)
    threads, cv_threads = torch.get_num_threads(), cv2.getNumThreads()
    set_num_threads(num_threads)
    cv2.setNumThreads(1)  # augmentation stays on the threads given to torch
    try:
        with allocator_tuned():  # CPU training: freed buffers stay in the heap for the next step
            return _run(folder, config, resume, progress)
    finally:  # a library call must not change the caller's thread or allocator settings
        torch.set_num_threads(threads)
        cv2.setNumThreads(cv_threads)


def _run(folder: Path, config: DistillConfig, resume: bool, progress: bool) -> Path:
    with exclusive_lock(folder, "run folder"):
        teacher_path = _teacher_path(config)
        teacher_net, _ = load_model(teacher_path, architecture=FULL_ARCHITECTURE)
        # A resumed run continues from its state: its --init file is neither read nor needed.
        start = None if resume else init_student(config)
        photos = GrayPhotos(photo_folder(config), config.long_side)
        if not resume:
            _write_json(folder / CONFIG_NAME, {"config": asdict(config), "teacher_file": str(teacher_path),
                                               "teacher_sha256": file_sha256(teacher_path),
                                               "init_sha256": file_sha256(start[0]) if start else None,
                                               "photo_count": len(photos)})
        return _train(folder, config, Teacher(teacher_net), photos, teacher_path, progress,
                      start[1] if start else None, _recorded_init_sha256(folder))


def _recorded_init_sha256(folder: Path) -> str | None:
    """The SHA-256 of the run's --init checkpoint as its config.json recorded it (None without one)."""
    return json.loads((folder / CONFIG_NAME).read_text()).get("init_sha256")


def _train(folder: Path, config: DistillConfig, teacher: Teacher, photos: GrayPhotos, teacher_path: Path,
           progress: bool, initial: dict | None = None, init_sha256: str | None = None) -> Path:
    torch.manual_seed(config.seed)
    student = build_lite(config.student).train()
    if initial is not None:  # a resumed run's state, loaded below, replaces it
        student.load_state_dict(initial)
    amp = autocast_dtype(config.train_precision, torch.device("cpu"))
    optimizer = torch.optim.AdamW(student.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    step = 0
    if (folder / STATE_NAME).is_file():
        try:
            state = torch.load(folder / STATE_NAME, map_location="cpu", weights_only=True)
            student.load_state_dict(state["student"])
            optimizer.load_state_dict(state["optimizer"])
            step = int(state["step"])
        except Exception as exc:  # a state file written by another version or damaged
            raise SekdError(f"{folder / STATE_NAME}: cannot resume from this state ({type(exc).__name__}: "
                            f"{str(exc).splitlines()[0] if str(exc) else ''}); start a new run in another folder") from exc
    _trim_metrics(folder, step)
    train_idx, val_idx = split_photos(len(photos), config.val_photos)
    val_images, val_pairs = validation_batch(photos, val_idx, config), validation_pairs(photos, val_idx, config)
    meta = {"teacher": Path(teacher_path).name, "teacher_sha256": file_sha256(teacher_path),
            "distill_config": asdict(config), "photos": len(train_idx), "init_sha256": init_sha256}
    last_save = time.monotonic()
    done = _snapshot(student, optimizer, step)
    bar = tqdm(total=config.steps, initial=step, desc="distill", unit="step", disable=not progress)
    try:
        while step < config.steps:
            images, maps = batch_for(photos, train_idx, step, config)
            t_logit, t_desc = teacher(images)
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(step, config)
            with torch.autocast("cpu", dtype=amp or torch.bfloat16, enabled=amp is not None):
                logits, desc, _ = student.forward_train(images)
            losses = distill_losses(logits.float(), desc.float(), t_logit, t_desc, config.peak_weight)
            loss = config.detector_weight * losses["detector"] + config.descriptor_weight * losses["descriptor"]
            if maps is not None:
                found = pair_correspondences(t_logit, maps, config.pair_keypoints)
                losses["pair"] = pair_loss(desc.float(), found, *images.shape[-2:])
                loss = loss + config.pair_weight * losses["pair"]
            losses = {k: v.detach() for k, v in losses.items()}  # scalars for the log, outside the graph
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            loss = loss.detach()
            optimizer.step()
            step += 1
            done = _snapshot(student, optimizer, step)
            bar.update(1)
            bar.set_postfix(det=f"{float(losses['detector']):.5f}", desc=f"{float(losses['descriptor']):.3f}")
            record = {"step": step, "lr": learning_rate(step - 1, config), "loss": float(loss),
                      **{k: float(v) for k, v in losses.items()}}
            _log(folder, {**record, "time": time.time()})
            if step % config.val_every == 0 or step == config.steps:
                val = validate(student, teacher, val_images, config.peak_weight, pairs=val_pairs)
                _log(folder, {"step": step, "val": val, "time": time.time()})
                bar.write(f"step {step}: " + ", ".join(f"{k} {v:.4f}" for k, v in val.items()))
            if time.monotonic() - last_save >= config.save_every_s or step == config.steps:
                _save_state(folder, student, done, meta)
                last_save = time.monotonic()
    except KeyboardInterrupt:
        _save_state(folder, student, done, meta)
        raise SekdError(f"interrupted at step {done['step']}; continue with: sekd distill -o {folder} --resume") from None
    finally:
        bar.close()
    final = folder / FINAL_NAME
    save_checkpoint(student.eval(), final, {**meta, "step": step})
    return final
