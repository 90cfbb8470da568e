"""Loading SEKD checkpoints: the authors' format, ours, and the model embedded in the package.

Both formats are ``torch.save({'state_dict': ...})``; ours adds a ``'sekd_sfm'`` entry
with training metadata, which the authors' loader ignores, so our checkpoints load
in their code and theirs in ours.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from ..errors import SekdError
from ..files.atomic import atomic_output
from .lite import ARCHITECTURE as LITE_ARCHITECTURE
from .lite import SEKDLiteNet, build_lite
from .network import SEKDNet

#: The ``architecture`` of the full network; checkpoints without an architecture entry
#: (the authors' release, older runs of this project) are full-network checkpoints.
FULL_ARCHITECTURE = "sekd"
ARCHITECTURES = (FULL_ARCHITECTURE, LITE_ARCHITECTURE)

MODELS_DIR = Path(__file__).parent / "checkpoints"
#: The models carried by the package, by the name ``--model`` takes: ``own`` = trained by this
#: project's ``sekd evolve`` (docs/model_card.md), ``authors`` = the SEKD authors' release
#: (MIT licence in models/LICENSE-authors.txt; docs/model_card_authors.md), ``lite`` = SEKD-Lite,
#: a slim network distilled from ``authors`` (docs/model_card_lite.md).
EMBEDDED_MODELS = {"own": MODELS_DIR / "sekd_own.pth", "authors": MODELS_DIR / "sekd_authors.pth",
                   "lite": MODELS_DIR / "sekd_lite.pth"}
#: The model used when neither --model nor --weights is given: the one that wins on relative
#: pose and SfM (docs/model_card_authors.md has the numbers).
DEFAULT_MODEL = "authors"
EMBEDDED_MODEL = EMBEDDED_MODELS[DEFAULT_MODEL]


@dataclass(frozen=True)
class ModelInfo:
    """Where a model came from: its file, SHA-256 (first 16 hex digits) and any metadata."""

    path: str
    sha256: str
    meta: dict


def file_sha256(path: Path, length: int = 16) -> str:
    """Hex SHA-256 of a file, truncated to ``length`` digits."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:length]


def embedded_model_path(name: str = DEFAULT_MODEL) -> Path:
    """The file of the embedded model ``name`` (``own``, ``authors`` or ``lite``); SekdError if unknown or absent."""
    if name not in EMBEDDED_MODELS:
        raise SekdError(f"unknown model {name!r}; choose one of {', '.join(EMBEDDED_MODELS)} or pass --weights PATH")
    path = EMBEDDED_MODELS[name]
    if not path.is_file():
        raise SekdError(f"{path}: the embedded {name!r} model is missing from this installation; "
                        "reinstall sekd-sfm or pass --weights PATH (for example the authors' sekd.pth)")
    return path


def resolve_weights_path(weights: str | Path | None) -> Path:
    """The checkpoint to load: ``weights`` if given, else the embedded default model."""
    if weights is None:
        return embedded_model_path(DEFAULT_MODEL)
    path = Path(weights).expanduser()
    if not path.is_file():
        raise SekdError(f"{path}: weights file not found; pass --weights with an existing .pth checkpoint")
    return path


def _state_dict_of(checkpoint: object, path: Path) -> dict:
    state = checkpoint.get("state_dict", checkpoint) if isinstance(checkpoint, dict) else None
    if not isinstance(state, dict) or not state:
        raise SekdError(f"{path}: not a SEKD checkpoint (expected a state dict or {{'state_dict': ...}})")
    # Checkpoints saved from DataParallel / DistributedDataParallel prefix every key.
    return {k.removeprefix("module."): v for k, v in state.items()}


def checkpoint_architecture(checkpoint: object, path: Path) -> tuple[str, dict]:
    """``(architecture, constructor config)`` recorded in a checkpoint's ``'sekd_sfm'`` entry (default: full SEKD)."""
    meta = checkpoint.get("sekd_sfm", {}) if isinstance(checkpoint, dict) else {}
    meta = meta if isinstance(meta, dict) else {}
    architecture = meta.get("architecture", FULL_ARCHITECTURE)
    if architecture not in ARCHITECTURES:
        raise SekdError(f"{path}: unknown network architecture {architecture!r} recorded in the checkpoint "
                        f"(this sekd-sfm knows {', '.join(ARCHITECTURES)}); update sekd-sfm or use another checkpoint")
    config = meta.get("config", {}) if architecture == LITE_ARCHITECTURE else {}
    return architecture, dict(config) if isinstance(config, dict) else {}


def _network_for(architecture: str, config: dict, path: Path) -> nn.Module:
    if architecture == FULL_ARCHITECTURE:
        return SEKDNet()
    try:
        return build_lite(config)
    except (ValueError, TypeError, KeyError) as exc:
        raise SekdError(f"{path}: invalid SEKD-Lite configuration {config!r} in the checkpoint ({exc})") from exc


def load_model(weights: str | Path | None = None, architecture: str | None = None) -> tuple[nn.Module, ModelInfo]:
    """Build the network the checkpoint records and load it strictly; returns it in eval mode on the CPU.

    The network is a :class:`SEKDNet` or, for checkpoints recording ``architecture: sekd-lite``,
    a :class:`~sekd_sfm.model.lite.SEKDLiteNet` (both give the same outputs). ``architecture``:
    the one the caller requires (``"sekd"`` where training code builds the full network);
    a checkpoint of the other one is a SekdError naming both.
    """
    path = resolve_weights_path(weights)
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for bad files
        raise SekdError(f"{path}: cannot read checkpoint ({type(exc).__name__}: {exc})".splitlines()[0]) from exc
    found, config = checkpoint_architecture(checkpoint, path)
    if architecture is not None and found != architecture:
        raise SekdError(f"{path}: this is a {_describe(found)} checkpoint, but a {_describe(architecture)} "
                        f"checkpoint is required here; pass one (e.g. --model {'lite' if architecture == LITE_ARCHITECTURE else DEFAULT_MODEL})")
    net = _network_for(found, config, path)
    try:
        net.load_state_dict(_state_dict_of(checkpoint, path), strict=True)
    except RuntimeError as exc:
        raise SekdError(f"{path}: checkpoint does not fit the {_describe(found)} network: {str(exc).splitlines()[0]}") from exc
    meta = checkpoint.get("sekd_sfm", {}) if isinstance(checkpoint, dict) else {}
    return net.eval(), ModelInfo(str(path), file_sha256(path), dict(meta))


def _describe(architecture: str) -> str:
    return "SEKD-Lite (sekd-lite)" if architecture == LITE_ARCHITECTURE else "full SEKD network (sekd)"


def save_checkpoint(net: torch.nn.Module, path: Path, meta: dict | None = None) -> Path:
    """Write ``{'state_dict', 'sekd_sfm': meta}`` atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    meta = dict(meta or {})
    if isinstance(net, SEKDLiteNet):  # the architecture travels with the weights: load_model rebuilds it
        meta.update(architecture=LITE_ARCHITECTURE, config=dict(net.config))
    with atomic_output(path) as tmp:
        torch.save({"state_dict": state, "sekd_sfm": meta}, tmp)
    return path
