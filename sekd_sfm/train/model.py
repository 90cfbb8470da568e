"""The network as training uses it: creation, fast grouped deconvolutions, frozen copies, export.

State-dict names never change, so every model saved here loads with
``sekd_sfm.model.weights.load_model`` and runs in ``sekd extract``.
"""
from __future__ import annotations

import copy
from pathlib import Path

import torch
from torch import nn

from ..model.network import BlockDiagonalConvTranspose2d, SEKDNet, use_fast_deconv  # noqa: F401 - re-exported
from ..model.weights import FULL_ARCHITECTURE, load_model, save_checkpoint


def new_network(seed: int) -> SEKDNet:
    """A randomly initialised network (PyTorch default init) that depends only on ``seed``."""
    state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        return SEKDNet()
    finally:
        torch.random.set_rng_state(state)


def initial_network(weights: str, seed: int) -> SEKDNet:
    """The starting model: a checkpoint when ``weights`` is set, else a seeded random network."""
    if weights:
        return load_model(Path(weights).expanduser(), architecture=FULL_ARCHITECTURE)[0]  # training builds SEKDNet: refuse a Lite checkpoint
    return new_network(seed)


def frozen_copy(net: nn.Module) -> nn.Module:
    """A deep copy in eval mode without gradients: the reference of the preservation losses."""
    frozen = copy.deepcopy(net).eval()
    for p in frozen.parameters():
        p.requires_grad_(False)
    return frozen


def plain_copy(net: nn.Module) -> SEKDNet:
    """An ordinary ``SEKDNet`` on the CPU with the same weights (for inference code and export)."""
    plain = SEKDNet()
    plain.load_state_dict({k: v.detach().cpu() for k, v in net.state_dict().items()})
    return plain.eval()


def export(net: nn.Module, path: Path, meta: dict) -> Path:
    """Write ``{'state_dict', 'sekd_sfm': meta}`` atomically (the format ``sekd extract --weights`` reads)."""
    return save_checkpoint(net, path, meta)
