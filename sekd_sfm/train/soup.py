"""Weight averages of checkpoints from one training run ("model soups", Wortsman et al. 2022).

``python -m sekd_sfm.train.soup A.pth B.pth --weights 0.7 0.3 -o soup.pth`` writes the
weighted mean of the checkpoints' parameters and BatchNorm statistics: no training, one
forward pass per image as before. It is meaningful for checkpoints on one training path
(consecutive steps of a run, or a run and its forks), whose weights stay close enough for
their average to be a good network; docs/experiments.md, section 15, measures such averages
of `sekd evolve` steps. The output records each ingredient's file, SHA-256 and weight.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..errors import SekdError
from ..model.lite import SEKDLiteNet
from ..model.weights import (
    FULL_ARCHITECTURE,
    LITE_ARCHITECTURE,
    file_sha256,
    load_model,
    save_checkpoint,
)


def _checked_weights(count: int, weights: list[float] | None) -> list[float]:
    """``weights`` normalised to sum 1 (uniform when None); SekdError unless ``count`` finite positive ones."""
    if count < 2:
        raise SekdError(f"averaging needs at least 2 checkpoints (got {count})")
    weights = [1.0] * count if weights is None else list(weights)
    if len(weights) != count:
        raise SekdError(f"--weights gives {len(weights)} weights for {count} checkpoints; give one per checkpoint")
    if not all(math.isfinite(w) and w > 0 for w in weights):
        raise SekdError(f"--weights must be positive numbers (got {weights})")
    total = sum(weights)
    return [w / total for w in weights]


def average_checkpoints(checkpoints: list[Path], output: Path, weights: list[float] | None = None) -> Path:
    """Write the ``weights``-weighted mean of ``checkpoints`` (all one architecture) to ``output``; returns it.

    Floating-point tensors are averaged in float64 and stored in their own dtype; integer
    tensors (BatchNorm's ``num_batches_tracked``) are taken from the first checkpoint. SekdError
    for fewer than two checkpoints, bad weights, or checkpoints of different networks.
    """
    weights = _checked_weights(len(checkpoints), weights)
    first, _ = load_model(checkpoints[0])
    architecture = LITE_ARCHITECTURE if isinstance(first, SEKDLiteNet) else FULL_ARCHITECTURE
    states = [first.state_dict()]
    for path in checkpoints[1:]:
        net, _ = load_model(path, architecture=architecture)
        if getattr(net, "config", None) != getattr(first, "config", None):
            raise SekdError(f"{path}: a SEKD-Lite of other channels ({net.config}) than {checkpoints[0]} "
                            f"({first.config}); average checkpoints of one network")
        states.append(net.state_dict())
    averaged = {}
    for key, value in states[0].items():
        if value.is_floating_point():
            mean = sum(w * state[key].double() for w, state in zip(weights, states))
            averaged[key] = mean.to(value.dtype)
        else:
            averaged[key] = value
    first.load_state_dict(averaged)
    ingredients = [{"file": str(Path(p)), "sha256": file_sha256(Path(p)), "weight": w}
                   for p, w in zip(checkpoints, weights)]
    return save_checkpoint(first, Path(output), {"soup": ingredients})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", type=Path, nargs="+", help="checkpoints of one network (.pth)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the averaged checkpoint to write")
    parser.add_argument("--weights", type=float, nargs="+", default=None,
                        help="one weight per checkpoint, normalised to sum 1 (default: equal weights)")
    args = parser.parse_args(argv)
    try:
        out = average_checkpoints(args.checkpoints, args.output, args.weights)
    except SekdError as exc:
        raise SystemExit(f"Error: {exc}") from None
    print(f"{out}: sha256 {file_sha256(out, 64)}")


if __name__ == "__main__":
    main()
