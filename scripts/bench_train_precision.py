"""Seconds per training step in fp32 and in bf16 mixed precision (``train_precision``), side by side.

Runs the training steps' own loop (``sekd_sfm.train.steps.run_epoch``: both views through the
network, the frozen reference forward, backward, Adam) on random crops with a stand-in loss
(the mean square of every output), alternating fp32 and bf16 epochs ``--rounds`` times so both
see the same machine load; prints the best epoch's seconds per step of each and their ratio.
The real losses add the same work to both precisions (they run in fp32 either way).

``--compare allocator`` instead alternates glibc's default allocator settings with the ones
training runs under (``runtime.allocator_tuned``: freed buffers stay in the heap), both in
``--precision``, and also reports the minor page faults and the share of CPU time spent in the
kernel per step.

Usage: python scripts/bench_train_precision.py [--crops 192 384] [--batch 4] [--steps 4]
       [--rounds 2] [--num-threads N] [--compare precision|allocator] [--precision bf16]
"""
from __future__ import annotations

import argparse
import contextlib
import resource
import time
from collections.abc import Callable
from functools import partial
from typing import Any, TypeVar

import torch

from sekd_sfm.model.network import SEKDNet, use_fast_deconv
from sekd_sfm.runtime import allocator_tuned, cpu_description
from sekd_sfm.train.distributed import Context
from sekd_sfm.train.model import frozen_copy
from sekd_sfm.train.steps import (
    PairForward,
    autocast_dtype,
    run_epoch,
    training_memory_format,
)

T = TypeVar("T")


def stand_in_loss(outputs, reference, batch):
    """Mean square of every network output: a scalar that depends on all of them."""
    loss = sum(t.square().mean() for view in outputs for t in view)
    return loss, {"total": loss.item()}


def seconds_per_step(precision: str, crop: int, batch: int, steps: int, ctx: Context) -> float:
    """One epoch of ``steps`` steps on a fresh network; seconds per step, the first step excluded (warm-up)."""
    torch.manual_seed(0)
    net = use_fast_deconv(SEKDNet()).train()
    amp = autocast_dtype(precision, ctx.device)
    net.to(memory_format=training_memory_format(amp))  # as train_step prepares the network
    frozen = frozen_copy(net)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-4)
    batches = [{"image0": torch.rand(batch, 1, crop, crop), "image1": torch.rand(batch, 1, crop, crop)}
               for _ in range(steps + 1)]
    run_epoch(PairForward(net), frozen, batches[:1], stand_in_loss, optimizer, ctx, "", False, amp)
    start = time.perf_counter()
    run_epoch(PairForward(net), frozen, batches[1:], stand_in_loss, optimizer, ctx, "", False, amp)
    return (time.perf_counter() - start) / steps


def allocator_step(tuned: bool, precision: str, crop: int, batch: int, steps: int,
                   ctx: Context) -> tuple[float, float, float]:
    """``seconds_per_step`` under glibc's defaults or ``allocator_tuned``; also minor page faults
    per step and the kernel's share of this process's CPU time (both over the whole epoch pair)."""
    before = resource.getrusage(resource.RUSAGE_SELF)
    with allocator_tuned() if tuned else contextlib.nullcontext():
        seconds = seconds_per_step(precision, crop, batch, steps, ctx)
    after = resource.getrusage(resource.RUSAGE_SELF)
    system, user = after.ru_stime - before.ru_stime, after.ru_utime - before.ru_utime
    return seconds, (after.ru_minflt - before.ru_minflt) / (steps + 1), system / max(system + user, 1e-9)


def best_alternating(rounds: int, variants: tuple, measure: Callable[[Any], T]) -> dict[Any, T]:
    """``measure`` of each variant, the variants alternated ``rounds`` times so all see the same
    machine load; the smallest result of each (tuples compare on their first item, the seconds)."""
    best: dict[Any, T] = {}
    for _ in range(rounds):
        for variant in variants:
            result = measure(variant)
            best[variant] = min(best[variant], result) if variant in best else result
    return best


def compare_allocator(args: argparse.Namespace, ctx: Context) -> None:
    """Print, per crop, the best seconds per step with glibc's defaults and tuned, and their ratio."""
    for crop in args.crops:
        best = best_alternating(args.rounds, (False, True),
                                partial(allocator_step, precision=args.precision, crop=crop, batch=args.batch, steps=args.steps,
                                        ctx=ctx))
        line = ", ".join(f"{name} {s:.3f} s/step ({faults:,.0f} page faults/step, {kernel:.0%} in kernel)"
                         for name, (s, faults, kernel) in (("glibc defaults", best[False]), ("tuned", best[True])))
        print(f"crop {crop} {args.precision}: {line}; tuned {best[False][0] / best[True][0]:.2f}x faster")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--crops", type=int, nargs="+", default=[192, 384])
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--num-threads", type=int, default=0)
    parser.add_argument("--compare", choices=("precision", "allocator"), default="precision")
    parser.add_argument("--precision", choices=("fp32", "bf16"), default="bf16", help="for --compare allocator")
    args = parser.parse_args()
    if args.num_threads:
        torch.set_num_threads(args.num_threads)
    ctx = Context(device=torch.device("cpu"))
    cpu = cpu_description()
    present = " ".join(name for name, has in cpu["features"].items() if has)
    print(f"cpu: {cpu['model']} ({present}; torch kernels {cpu['torch_kernels']}); {torch.get_num_threads()} threads; "
          f"batch {args.batch} pairs")
    if args.compare == "allocator":
        compare_allocator(args, ctx)
        return
    for crop in args.crops:
        best = best_alternating(args.rounds, ("fp32", "bf16"),
                                partial(seconds_per_step, crop=crop, batch=args.batch, steps=args.steps, ctx=ctx))
        print(f"crop {crop}: fp32 {best['fp32']:.3f} s/step, bf16 {best['bf16']:.3f} s/step, "
              f"bf16 {best['fp32'] / best['bf16']:.2f}x faster")


if __name__ == "__main__":
    main()
