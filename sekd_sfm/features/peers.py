"""Learned peers through kornia, with LOCAL weights (never downloaded): DISK, ALIKED-N16, XFeat.

Each is wrapped in the extractor interface: ``extract(rgb uint8 H x W x 3, mask=None)`` returns
keypoints in OpenCV pixel-centre convention, scores, unit descriptors ``N x D`` (float32).
With a mask, every candidate keypoint is computed (no cap), those on ignored pixels are
dropped, then the strongest ``max_keypoints`` are kept: a masked photo keeps its budget.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ..errors import SekdError
from ..files.images import kept_at
from ..runtime import shared_dir

#: Default weight files, relative to the shared folder.
PEER_WEIGHTS = {
    "disk": "weights/peers/disk/depth-save.pth",
    "aliked": "weights/peers/aliked/aliked-n16.pth",
    "xfeat": "weights/peers/xfeat/xfeat.pt",
}
PEER_FEATURES = tuple(PEER_WEIGHTS)
_DIMS = {"disk": 128, "aliked": 128, "xfeat": 64}
#: The keypoint cap of a masked photo's candidates: ALIKED's own limit in threshold mode (kornia's
#: ``n_limit_max``); DISK takes ``n=None`` and XFeat keeps every local maximum below any cap this high.
UNCAPPED = 20000


def peer_weights_path(name: str, weights: str | Path | None) -> Path:
    """The weight file of a peer; SekdError naming the file when it is absent."""
    path = Path(weights) if weights else shared_dir() / PEER_WEIGHTS[name]
    if not path.is_file():
        raise SekdError(f"{path}: {name} weights not found; pass --weights PATH to a local {name} checkpoint")
    return path


def _load_state(path: Path) -> dict:
    """The tensors of a checkpoint (``weights_only``: a file cannot run code); SekdError naming a bad file."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except OSError:
        raise  # permission denied, I/O error: the top-level handler names the file and the cause
    except Exception as exc:  # torch raises RuntimeError, UnpicklingError, EOFError, ... for bad files
        raise SekdError(f"{path}: not a readable PyTorch checkpoint ({_first_line(exc)}); "
                        "pass --weights PATH to a valid local checkpoint") from exc
    if not isinstance(state, dict):
        raise SekdError(f"{path}: holds a {type(state).__name__}, not a checkpoint's dictionary of tensors")
    return state


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    if "Weights only load failed" in text:  # torch's advice there (weights_only=False) would run the file's code
        return "not a tensors-only PyTorch file; files that hold code are refused"
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return " ".join(lines[:2])[:200] or type(exc).__name__


def _build(name: str, path: Path, max_keypoints: int) -> torch.nn.Module:
    """The kornia model with the weights of ``path``; SekdError when they do not fit ``name``."""
    try:
        return _build_unchecked(name, path, max_keypoints)
    except SekdError:
        raise
    except (KeyError, RuntimeError, TypeError, ValueError, AttributeError) as exc:
        raise SekdError(f"{path}: not {name} weights ({_first_line(exc)}); "
                        f"pass --weights PATH to a local {name} checkpoint") from exc


def _build_unchecked(name: str, path: Path, max_keypoints: int) -> torch.nn.Module:
    import kornia.feature as KF

    state = _load_state(path)
    if name == "disk":
        model = KF.DISK()
        model.load_state_dict(state["extractor"])
    elif name == "aliked":
        model = KF.ALIKED("aliked-n16", max_num_keypoints=max_keypoints)
        # Only the derived buffer dkd.hw_grid is absent from the file.
        missing = model.load_state_dict(state, strict=False).missing_keys
        if any(not k.endswith("hw_grid") for k in missing):
            raise SekdError(f"{path}: not ALIKED-N16 weights (missing {missing[:3]})")
    else:
        model = KF.XFeat(top_k=max_keypoints)
        model.net.load_state_dict(state)
    return model.eval()


class KorniaPeer:
    """A kornia feature model with local weights; input is RGB (``color = True``)."""

    binary = False
    color = True

    def __init__(self, name: str, max_keypoints: int, weights: str | Path | None = None, device: str = "cpu"):
        self.name, self.max_keypoints = name, max_keypoints
        self.descriptor_dim = _DIMS[name]
        self.weights_path = peer_weights_path(name, weights)
        self.device = torch.device(device)
        self.model = _build(name, self.weights_path, max_keypoints).to(self.device)

    @torch.inference_mode()
    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """``mask``: ``H x W`` bool, True = detect there (None: everywhere)."""
        rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
        x = torch.from_numpy(rgb).permute(2, 0, 1)[None].float().div(255).to(self.device)
        keypoints, scores, descriptors = self._run(x, uncapped=mask is not None)
        if mask is not None:  # before the cut below, so the budget goes to the kept pixels
            kept = torch.from_numpy(kept_at(mask, keypoints.cpu().numpy())).to(keypoints.device)
            keypoints, scores, descriptors = keypoints[kept], scores[kept], descriptors[kept]
        order = torch.argsort(scores, descending=True, stable=True)[: self.max_keypoints]
        return {"keypoints": keypoints[order].cpu().numpy().astype(np.float32),
                "scores": scores[order].cpu().numpy().astype(np.float32),
                "descriptors": descriptors[order].cpu().numpy().astype(np.float32)}

    def _run(self, x: torch.Tensor, uncapped: bool = False):
        """Keypoints ``N x 2`` (pixel centres), scores ``N`` and descriptors ``N x D``: at most ``max_keypoints``,
        or every candidate the model finds when ``uncapped`` (a masked photo's)."""
        if self.name == "disk":
            n = None if uncapped else self.max_keypoints
            f = self.model(x, n=n, window_size=5, score_threshold=0.0, pad_if_not_divisible=True)[0]
            return f.keypoints.float(), f.detection_scores, f.descriptors
        if self.name == "aliked":
            with _aliked_limit(self.model, UNCAPPED) if uncapped else contextlib.nullcontext():
                f = self.model(x)[0]
            return f.keypoints, f.keypoint_scores, f.descriptors
        h, w = x.shape[2:]
        f = self.model.detectAndCompute(x, top_k=UNCAPPED if uncapped else self.max_keypoints)[0]
        # kornia reports XFeat keypoints of the /32-resized image at i * r; the centre is (i + 0.5) r - 0.5.
        ratio = torch.tensor([w / (w // 32 * 32), h / (h // 32 * 32)], device=x.device)
        return f["keypoints"] + 0.5 * ratio - 0.5, f["scores"], f["descriptors"]


@contextlib.contextmanager
def _aliked_limit(model: torch.nn.Module, cap: int) -> Iterator[None]:
    """ALIKED's keypoint limit set to ``cap`` for one call (kornia's DKD keeps it as ``n_limit``, the limit of its
    threshold mode, which ``KF.ALIKED`` uses; ``top_k`` in its top-k mode)."""
    dkd = model.dkd
    saved = dkd.n_limit, dkd.top_k
    dkd.n_limit, dkd.top_k = cap, (cap if dkd.top_k > 0 else dkd.top_k)
    try:
        yield
    finally:
        dkd.n_limit, dkd.top_k = saved
