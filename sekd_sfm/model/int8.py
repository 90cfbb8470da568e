"""int8 inference: the SEKD network quantized after training (OpenVINO + NNCF), cached per weights.

The network (image -> keypoint probability map + raw descriptor map) is converted to OpenVINO
with a dynamic height and width, quantized by NNCF's post-training quantization on a few
shared COCO photos, and saved as an OpenVINO IR in a user cache folder keyed by the weights'
SHA-256, the calibration settings and the library versions, so it is computed once per
weights and rebuilt when they change. Non-maximum suppression and descriptor sampling stay in
torch (``sekd_sfm.model.inference``), as for fp32 and bf16.

Needs the optional extra: ``pip install "sekd-sfm[int8]"``.
"""
from __future__ import annotations

import hashlib
import importlib.metadata
import json
import logging
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ..errors import SekdError
from ..failures import first_line
from .network import STRIDE, SEKDNet

INSTALL_HINT = 'pip install "sekd-sfm[int8]"'


@dataclass(frozen=True)
class CalibrationConfig:
    """Post-training quantization settings (part of the cache key).

    ``count`` COCO photos, area-resized and centre-cropped to ``height x width`` (the benchmark's
    extraction size). The final softmax stays in floating point: it is OpenVINO's default
    for softmax, and it keeps detector probabilities close to fp32.
    """

    count: int = 32
    height: int = 480
    width: int = 640
    subset_size: int = 300  # NNCF statistics samples (capped by the number of photos)
    #: Layers kept in floating point: the first convolution (its input is the image itself) and the
    #: detector head (its logits feed the softmax whose 0.4 threshold selects keypoints). Both are
    #: small (1 -> 32 and 32 -> 2 channels), so keeping them costs little speed.
    keep_float: tuple[str, ...] = ("conv0", "detector")


def calibration_from_env() -> CalibrationConfig:
    """``SEKD_INT8_CALIBRATION=COUNTxHEIGHTxWIDTH`` (e.g. ``4x64x80``) overrides the defaults, for tests."""
    text = os.environ.get("SEKD_INT8_CALIBRATION")
    if not text:
        return CalibrationConfig()
    try:
        count, height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SekdError(f"SEKD_INT8_CALIBRATION={text!r}: expected COUNTxHEIGHTxWIDTH, e.g. 32x480x640") from None
    if count < 1 or height < STRIDE or width < STRIDE:
        raise SekdError(f"SEKD_INT8_CALIBRATION={text!r}: need at least 1 photo of at least {STRIDE}x{STRIDE} px")
    return CalibrationConfig(count=count, height=height, width=width)


def _import_openvino():
    try:
        import nncf  # noqa: F401
        import openvino
    except ImportError:
        raise SekdError(f"--precision int8 needs OpenVINO and NNCF, which are not installed; run: {INSTALL_HINT}") from None
    return openvino


def available() -> bool:
    """True when OpenVINO and NNCF can be imported."""
    try:
        _import_openvino()
        return True
    except SekdError:
        return False


def cache_root() -> Path:
    """``$SEKD_CACHE/int8`` when set, else ``~/.cache/sekd/int8`` (``$XDG_CACHE_HOME`` honoured)."""
    if os.environ.get("SEKD_CACHE"):
        return Path(os.environ["SEKD_CACHE"]) / "int8"
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "sekd" / "int8"


def weights_sha256(net: SEKDNet) -> str:
    """SHA-256 (16 hex digits) of the network's state: names, shapes, dtypes and values.

    Hashing the tensors rather than the checkpoint file gives the same key for the same weights
    whatever file (or in-memory network) they came from.
    """
    digest = hashlib.sha256()
    for name, tensor in sorted(net.state_dict().items()):
        t = tensor.detach().cpu().contiguous().reshape(-1)  # 1-D: 0-d tensors cannot be viewed as bytes
        digest.update(f"{name}:{tuple(t.shape)}:{t.dtype};".encode())
        digest.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return digest.hexdigest()[:16]


def _versions() -> dict[str, str]:
    return {name: importlib.metadata.version(name) for name in ("openvino", "nncf", "torch")}


def cache_dir(net: SEKDNet, calibration: CalibrationConfig) -> Path:
    """``<cache root>/<weights sha>/<settings sha>/``: one folder per weights, one model per settings."""
    settings = json.dumps({"calibration": asdict(calibration), "versions": _versions()}, sort_keys=True)
    return cache_root() / weights_sha256(net) / hashlib.sha256(settings.encode()).hexdigest()[:12]


def calibration_images(calibration: CalibrationConfig) -> list[np.ndarray]:
    """``1 x 1 x H x W`` float32 inputs in [0, 1] from the shared COCO photos; SekdError if absent."""
    from ..files.images import list_images, read_image
    from ..runtime import shared_dir

    folder = shared_dir() / "data" / "train" / "coco"
    keys = list_images(folder)[: calibration.count] if folder.is_dir() else []
    if not keys:
        raise SekdError(f"{folder}: no calibration photos for int8 quantization; set SEKD_SHARED to the "
                        "project's shared data folder (it holds data/train/coco)")
    h, w = calibration.height, calibration.width
    inputs = []
    for key in keys:
        image = read_image(folder / key)
        scale = max(h / image.shape[0], w / image.shape[1])
        size = (max(w, round(image.shape[1] * scale)), max(h, round(image.shape[0] * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        top, left = (image.shape[0] - h) // 2, (image.shape[1] - w) // 2
        crop = image[top:top + h, left:left + w].astype(np.float32) / 255.0
        inputs.append(np.ascontiguousarray(crop)[None, None])
    return inputs


def quantize(net: SEKDNet, calibration: CalibrationConfig):
    """Convert ``net`` to OpenVINO (dynamic H, W) and quantize it to int8; returns an ``openvino.Model``."""
    ov = _import_openvino()
    import nncf
    from nncf.common.logging import nncf_logger

    nncf_logger.setLevel(logging.WARNING)  # its per-layer INFO lines would bury the progress bar

    net = net.eval().cpu().float()
    example = torch.zeros(1, 1, calibration.height, calibration.width)
    with torch.no_grad():
        model = ov.convert_model(net, example_input=example, input=[(1, 1, -1, -1)])
    inputs = calibration_images(calibration)
    dataset = nncf.Dataset(inputs)
    ignored = nncf.IgnoredScope(patterns=[rf"__module\.{name}/.*" for name in calibration.keep_float], validate=False)
    return nncf.quantize(model, dataset, preset=nncf.QuantizationPreset.PERFORMANCE,
                         subset_size=min(calibration.subset_size, len(inputs)), ignored_scope=ignored)


def load_or_build(net: SEKDNet, calibration: CalibrationConfig | None = None) -> tuple[object, Path]:
    """The quantized ``openvino.Model`` for ``net`` from the cache, built (and saved) if absent.

    Written atomically: the IR is saved under a name carrying this process's id, then both
    files are renamed into place (the .bin first, so a present .xml always has its weights).
    Returns the model and the cached ``.xml`` path.
    """
    ov = _import_openvino()
    calibration = calibration or calibration_from_env()
    folder = cache_dir(net, calibration)
    xml = folder / "sekd_int8.xml"
    core = ov.Core()
    if xml.is_file() and xml.with_suffix(".bin").is_file():
        try:
            return core.read_model(xml), xml
        except RuntimeError:  # a damaged cache entry: rebuild it below
            pass
    model = quantize(net, calibration)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f"sekd_int8.tmp{os.getpid()}.xml"
        ov.save_model(model, tmp, compress_to_fp16=False)
        tmp.with_suffix(".bin").replace(xml.with_suffix(".bin"))
        tmp.replace(xml)
    except OSError as exc:
        raise SekdError(f"{folder}: cannot write the int8 model cache ({exc.strerror or exc}); "
                        "set SEKD_CACHE to a writable folder") from exc
    return model, xml


class Int8SEKD:
    """The quantized network behind FastSEKD's interface: images -> (probability, raw descriptors)."""

    precision = "int8"
    dtype = torch.float32

    def __init__(self, net: SEKDNet, device: str = "auto", num_threads: int | None = None):
        from ..runtime import resolve_device

        if device == "cuda" or (device == "auto" and resolve_device("auto").type == "cuda"):
            raise SekdError("--precision int8 runs on the CPU only; use --device cpu (or --precision fp32 on the GPU)")
        ov = _import_openvino()
        threads = num_threads or torch.get_num_threads()
        # LATENCY: one image at a time, all threads on it (as the torch paths run).
        config = {"INFERENCE_NUM_THREADS": threads, "PERFORMANCE_HINT": "LATENCY"}
        try:
            model, self.cache_path = load_or_build(net)
            self.compiled = ov.Core().compile_model(model, "CPU", config)
        except RuntimeError as exc:  # OpenVINO's own errors: a CPU or build it cannot compile the network for
            raise SekdError(f"--precision int8: OpenVINO could not build the quantized network on this CPU "
                            f"({first_line(exc)}); use --precision auto or fp32") from None
        self.request = self.compiled.create_infer_request()
        self.device = torch.device("cpu")

    def __call__(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``B x 1 x H x W`` float in [0, 1] -> (probability ``B x H x W``, raw descriptors ``B x 128 x H/4 x W/4``)."""
        x = np.ascontiguousarray(images.detach().cpu().float().numpy())
        out = self.request.infer({0: x})
        prob, desc = (torch.from_numpy(np.array(out[self.compiled.output(i)])) for i in range(2))
        return prob[:, 0].contiguous(), desc.contiguous()
