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

from .errors import SekdError
from .network import SEKDNet

MODELS_DIR = Path(__file__).parent / "models"
#: The models carried by the package, by the name ``--model`` takes: ``own`` = trained by this
#: project's ``sekd evolve`` (docs/model_card.md), ``authors`` = the SEKD authors' release
#: (MIT licence in models/LICENSE-authors.txt; docs/model_card_authors.md).
EMBEDDED_MODELS = {"own": MODELS_DIR / "sekd_own.pth", "authors": MODELS_DIR / "sekd_authors.pth"}
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
    """The file of the embedded model ``name`` (``own`` or ``authors``); SekdError if unknown or absent."""
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


def load_model(weights: str | Path | None = None) -> tuple[SEKDNet, ModelInfo]:
    """Build the network and load a checkpoint strictly; returns it in eval mode on the CPU."""
    path = resolve_weights_path(weights)
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for bad files
        raise SekdError(f"{path}: cannot read checkpoint ({type(exc).__name__}: {exc})".splitlines()[0]) from exc
    net = SEKDNet()
    try:
        net.load_state_dict(_state_dict_of(checkpoint, path), strict=True)
    except RuntimeError as exc:
        raise SekdError(f"{path}: checkpoint does not fit the SEKD network: {str(exc).splitlines()[0]}") from exc
    meta = checkpoint.get("sekd_sfm", {}) if isinstance(checkpoint, dict) else {}
    return net.eval(), ModelInfo(str(path), file_sha256(path), dict(meta))


def save_checkpoint(net: torch.nn.Module, path: Path, meta: dict | None = None) -> Path:
    """Write ``{'state_dict', 'sekd_sfm': meta}`` atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    torch.save({"state_dict": state, "sekd_sfm": dict(meta or {})}, tmp)
    tmp.replace(path)
    return path
