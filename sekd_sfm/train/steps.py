"""Training steps (b) descriptor update and (d) detector update (docs/method.md "Training").

A step trains all parameters for a number of epochs with a fresh Adam optimiser and
reduce-on-plateau scheduler, against a frozen copy of the network as it was when the step
began. After every epoch the caller's ``checkpoint`` callback saves model, optimiser,
scheduler and loss history, and a step resumes from that state exactly.
"""
from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable
from functools import partial

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.data import DataLoader
from tqdm import tqdm

from ..runtime import cpu_has_fast_bf16
from .config import TrainConfig
from .data import PairDataset, TrainImages, rng_for
from .distributed import Context, check_in_sync, shard, sum_across, sync_buffers, wrap
from .labels import Labels
from .losses import (
    focal_loss,
    preservation_mse,
    repeatability_paper,
    repeatability_weighted,
    spatial_neighbours,
    spread_out,
    triplet_loss,
)
from .model import frozen_copy

logger = logging.getLogger("sekd.train")
#: Image index of the per-epoch batch-order stream (no real image has it).
ORDER_STREAM = 2**31 - 1


class PairForward(nn.Module):
    """Both views through the network in one call, so DistributedDataParallel sees one forward per backward."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, image0: torch.Tensor, image1: torch.Tensor):
        return self.net.forward_train(image0), self.net.forward_train(image1)


def sample_upsampled(desc: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Unit descriptors at integer pixels of the map bilinearly upsampled to ``height x width``.

    Equals ``normalise(interpolate(desc, (h, w), bilinear, align_corners=False))[:, rows, cols]``
    without building the full-resolution map: ``C x h/4 x w/4`` -> ``N x C``.
    """
    grid = torch.stack([(2 * cols + 1) / width - 1, (2 * rows + 1) / height - 1], dim=-1).to(desc)
    # Border padding reproduces the edge clamping of interpolate().
    out = F.grid_sample(desc[None], grid[None, None], mode="bilinear", padding_mode="border", align_corners=False)
    return F.normalize(out[0, :, 0].t(), dim=1)


def matched_keypoints(label0: torch.Tensor, corr: torch.Tensor, dense: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """View-0 pixels (keypoints of ``label0``, or all when ``dense``) with a correspondence, and that
    correspondence: two ``N x 2`` long tensors of (row, col)."""
    valid = corr[..., 0] >= 0
    if not dense:
        valid &= label0 > 0.5
    p = torch.nonzero(valid)
    return p, corr[p[:, 0], p[:, 1]]


def descriptor_loss(outputs, reference, batch: dict, cfg: TrainConfig, alpha: float) -> tuple[torch.Tensor, dict]:
    """L1 = Ldesc + alpha Lpres (§4), plus ``spread_weight`` x spread-out term when set, for a batch.

    ``outputs``/``reference``: forward_train results of both views. Ldesc and the spread term are
    summed over the samples with at least 2 correspondences and divided by the batch size.
    """
    (l0, d0, _), (l1, d1, _) = outputs
    (r0, _, _), (r1, _, _) = reference
    if cfg.det_preserve_on == "prob":
        l0, l1, r0, r1 = (F.softmax(t, dim=1)[:, 1] for t in (l0, l1, r0, r1))
    pres = preservation_mse((l0, l1), (r0, r1))
    h, w = batch["label0"].shape[-2:]
    desc, spread, used = l0.new_zeros(()), l0.new_zeros(()), 0
    for b in range(l0.shape[0]):
        p, q = matched_keypoints(batch["label0"][b], batch["corr"][b])
        if len(p) < 2:
            continue
        a = sample_upsampled(d0[b], p[:, 0], p[:, 1], h, w)
        pos = sample_upsampled(d1[b], q[:, 0], q[:, 1], h, w)
        near = spatial_neighbours(p, cfg.neg_min_pixels) if cfg.neg_min_pixels > 0 else None
        desc = desc + triplet_loss(a, pos, cfg.desc_loss, cfg.ratio_threshold, cfg.margin, cfg.margin_normalise,
                                   cfg.neg_min_distance, cfg.neg_self_penalty, near)
        if cfg.spread_weight > 0:
            spread = spread + spread_out(a, pos)
        used += 1
    desc, spread = desc / l0.shape[0], spread / l0.shape[0]
    total = desc + cfg.spread_weight * spread + alpha * pres
    parts = {"total": total.item(), "desc": desc.item(), "pres": pres.item(), "used": used / l0.shape[0]}
    if cfg.spread_weight > 0:
        parts["spread"] = spread.item()
    return total, parts


def detector_loss(outputs, reference, batch: dict, cfg: TrainConfig, bg_weight: float) -> tuple[torch.Tensor, dict]:
    """L2 = Ldet + beta Lrep + lambda Lkeep for a batch (§6)."""
    (l0, d0, _), (l1, d1, _) = outputs
    (_, e0, _), (_, e1, _) = reference
    det = 0.5 * (focal_loss(l0, batch["label0"], bg_weight, cfg.focal_gamma)
                 + focal_loss(l1, batch["label1"], bg_weight, cfg.focal_gamma))
    keep = preservation_mse((F.normalize(d0, dim=1), F.normalize(d1, dim=1)),
                            (F.normalize(e0, dim=1), F.normalize(e1, dim=1)))
    rep_fn = repeatability_weighted if cfg.rep_loss == "weighted" else repeatability_paper
    u_all, v_all = F.softmax(l0, dim=1), F.softmax(l1, dim=1)
    rep = l0.new_zeros(())
    for b in range(l0.shape[0]):
        p, q = matched_keypoints(batch["label0"][b], batch["corr"][b], dense=cfg.rep_loss == "weighted")
        if len(p) < 2:
            continue
        rep = rep + rep_fn(u_all[b][:, p[:, 0], p[:, 1]].t(), v_all[b][:, q[:, 0], q[:, 1]].t())
    rep = rep / l0.shape[0]
    beta = 0.0 if cfg.no_det_rep else cfg.beta
    total = det + beta * rep + cfg.lambda_keep * keep
    return total, {"total": total.item(), "det": det.item(), "rep": rep.item(), "keep": keep.item()}


def epoch_batches(count: int, cfg: TrainConfig, round_index: int, kind: str, epoch: int, ctx: Context) -> list[list[int]]:
    """This process's share of each global batch of one epoch (dataset positions, seeded shuffle).

    With several processes a short last batch is filled up from the start of the order so
    that every process runs the same number of iterations.
    """
    order = rng_for(cfg.seed, round_index, kind, epoch, ORDER_STREAM).permutation(count).tolist()
    size = cfg.batch_size
    batches = [order[i:i + size] for i in range(0, count, size)]
    if ctx.distributed and len(batches[-1]) < size:
        batches[-1] = (batches[-1] + order * size)[:size]
    return [shard(ctx, b) for b in batches]


def _to(batch: dict, device: torch.device, memory_format: torch.memory_format) -> dict:
    """The batch on ``device``; the network's inputs (``image0``, ``image1``) in ``memory_format``."""
    return {k: v.to(device, non_blocking=True, memory_format=memory_format) if k.startswith("image")
            else v.to(device, non_blocking=True) for k, v in batch.items()}


def autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of the training steps' forward passes: bf16, or None for plain fp32.

    ``auto`` picks bf16 only where the device computes it natively (CPUs with AVX512-BF16 or
    AMX, CUDA GPUs with bf16): elsewhere bf16 is emulated and slower than fp32. Unlike
    inference's ``runtime.resolve_precision``, which keeps CUDA at fp32 for exact keypoints,
    training takes bf16 on CUDA too: bf16 training validates as fp32 does.
    """
    if precision == "fp32":
        return None
    if precision == "auto":
        native = torch.cuda.is_bf16_supported() if device.type == "cuda" else cpu_has_fast_bf16()
        return torch.bfloat16 if native else None
    return torch.bfloat16


def training_memory_format(amp: torch.dtype | None) -> torch.memory_format:
    """Channels-last under bf16 autocast (oneDNN's bf16 convolutions want it), else the usual layout."""
    return torch.channels_last if amp is not None else torch.contiguous_format


def _as_float(outputs):
    """Network outputs (nested tuples of tensors) in fp32, so every loss is computed in fp32."""
    if isinstance(outputs, torch.Tensor):
        return outputs.float()
    return tuple(_as_float(o) for o in outputs)


def run_epoch(model: nn.Module, frozen: nn.Module, loader: DataLoader, loss_fn: Callable, optimizer,
              ctx: Context, bar_label: str, progress: bool, amp: torch.dtype | None = None) -> dict:
    """One pass over ``loader``: forward, loss, backward, Adam step. Returns the mean of each loss part.

    ``amp``: forward passes under autocast to this dtype, inputs in ``training_memory_format``;
    weights, gradients, optimiser state and losses stay fp32.
    """
    sums: dict[str, float] = defaultdict(float)
    memory_format = training_memory_format(amp)
    bar = tqdm(loader, desc=bar_label, disable=not (progress and ctx.main), leave=False, dynamic_ncols=True)
    for n, batch in enumerate(bar, start=1):
        batch = _to(batch, ctx.device, memory_format)
        with torch.autocast(ctx.device.type, dtype=amp or torch.bfloat16, enabled=amp is not None):
            outputs = model(batch["image0"], batch["image1"])
            with torch.no_grad():
                reference = (frozen.forward_train(batch["image0"]), frozen.forward_train(batch["image1"]))
        if amp is not None:
            outputs, reference = _as_float(outputs), _as_float(reference)
        loss, parts = loss_fn(outputs, reference, batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        for key, value in parts.items():
            sums[key] += value
        bar.set_postfix({k: f"{v / n:.4f}" for k, v in sums.items() if k != "used"})
    keys = sorted(sums)
    totals = sum_across(ctx, torch.tensor([sums[k] for k in keys] + [float(len(loader))]))
    return {k: float(totals[i] / totals[-1]) for i, k in enumerate(keys)}


class HalfwayDrop(torch.optim.lr_scheduler.LambdaLR):
    """The learning rate times 1 for the first half of ``epochs`` (rounded up), times ``factor`` after.

    Rounded up so that a one-epoch step runs at the learning rate, not wholly at ``factor`` times it.
    ``step`` takes (and ignores) the epoch's loss, as ReduceLROnPlateau's does."""

    def __init__(self, optimizer, epochs: int, factor: float):
        half = (epochs + 1) // 2
        super().__init__(optimizer, lambda epoch: 1.0 if epoch < half else factor)

    def step(self, metrics: float | None = None) -> None:
        super().step()


def _optimiser(net: nn.Module, cfg: TrainConfig, epochs: int):
    """A fresh Adam and scheduler (the learning rate restarts every step of ``epochs`` epochs)."""
    optimizer = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    if cfg.lr_schedule == "halfway":
        return optimizer, HalfwayDrop(optimizer, epochs, cfg.plateau_factor)
    scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
        optimizer, mode="min", factor=cfg.plateau_factor, patience=cfg.plateau_patience,
        threshold=cfg.plateau_threshold, threshold_mode="rel")
    return optimizer, scheduler


def _restore(state: dict | None, net: nn.Module, optimizer, scheduler) -> tuple[list[dict], int]:
    """Load an epoch checkpoint of this step; returns (history, first epoch to run)."""
    if state is None:
        return [], 0
    net.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    torch.random.set_rng_state(state["torch_rng"].cpu())
    return list(state["history"]), state["epoch"] + 1


def _loss_function(kind: str, labels: Labels, cfg: TrainConfig, alpha: float) -> Callable:
    if kind == "b":
        return partial(descriptor_loss, cfg=cfg, alpha=alpha)
    return partial(detector_loss, cfg=cfg, bg_weight=labels.bg_weight)


def train_step(net: nn.Module, kind: str, labels: Labels, images: TrainImages, cfg: TrainConfig, ctx: Context,
               round_index: int, resume_state: dict | None, checkpoint: Callable, alpha: float = 1.0) -> list[dict]:
    """Train ``net`` in place for step ``kind`` ('b' descriptor, 'd' detector); returns the epoch history.

    ``resume_state``: the state ``checkpoint`` saved after an epoch of this step, or None.
    ``checkpoint(epoch, state)`` is called after every epoch with everything needed to resume.
    """
    amp = autocast_dtype(cfg.train_precision, ctx.device)
    net.to(memory_format=training_memory_format(amp))  # in place: the same Parameters, other strides
    frozen = frozen_copy(net)  # the network as this step began (before any resumed state)
    epochs = cfg.epochs_desc if kind == "b" else cfg.epochs_det
    optimizer, scheduler = _optimiser(net, cfg, epochs)
    history, start = _restore(resume_state, net, optimizer, scheduler)
    loss_fn = _loss_function(kind, labels, cfg, alpha)
    indices = sorted(labels.keypoints)
    model = wrap(PairForward(net), ctx)
    net.train()
    for epoch in range(start, epochs):
        dataset = PairDataset(images, indices, labels.keypoints, cfg, round_index, kind, epoch)
        batches = epoch_batches(len(indices), cfg, round_index, kind, epoch, ctx)
        loader = DataLoader(dataset, batch_sampler=batches, num_workers=cfg.num_workers)
        label = f"round {round_index} ({kind}) epoch {epoch + 1}/{epochs}"
        means = run_epoch(model, frozen, loader, loss_fn, optimizer, ctx, label, cfg.progress, amp)
        history.append({"round": round_index, "kind": kind, "epoch": epoch,
                        "lr": optimizer.param_groups[0]["lr"], **means})
        scheduler.step(means["total"])
        logger.info("round %d step %s epoch %d/%d: %s", round_index, kind, epoch + 1, epochs,
                    " ".join(f"{k}={v:.5g}" for k, v in means.items()))
        checkpoint(epoch, {"model": net.state_dict(), "optimizer": optimizer.state_dict(),
                           "scheduler": scheduler.state_dict(), "history": history, "epoch": epoch,
                           "torch_rng": torch.random.get_rng_state()})
    if ctx.distributed:
        sync_buffers(ctx, net)
        logger.info("round %d step %s: weights identical on all %d processes (checksum %.10g)",
                    round_index, kind, ctx.world, check_in_sync(ctx, net))
    net.to(memory_format=torch.contiguous_format)  # labelling and validation run as in fp32 runs
    net.eval()
    return history
