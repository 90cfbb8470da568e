"""``sekd bench speed``: images/s at a fixed size for plain fp32, the fast path, int8 (optional extra),
SEKD-Lite (fast fp32, the precision ``auto`` picks, int8) and OpenCV SIFT.

All methods run in the same process on the same decoded images, so their ratios are
meaningful on a noisy machine. The plain path runs first, before the fast path tunes
the process's allocator, so the baseline is the straightforward PyTorch forward.
"""
from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from ..files.images import list_images, read_image
from ..model.inference import (
    SEKDConfig,
    SEKDExtractor,
    nms_keypoints,
    sample_descriptors,
)
from ..model.network import SEKDNet
from ..runtime import cpu_description, package_versions, run_record, set_num_threads


def count_macs(net: nn.Module, height: int, width: int) -> int:
    """Multiply-accumulates of one forward at ``height x width`` (convolutions only, groups honoured)."""
    total = 0

    def hook(module, inputs, output):
        nonlocal total
        kernel = module.weight.shape[2] * module.weight.shape[3]
        c_in_per_group = module.in_channels // module.groups
        # Transposed convolutions: each input pixel scatters into c_out/groups outputs.
        pixels = inputs[0].shape[2] * inputs[0].shape[3] if isinstance(module, nn.ConvTranspose2d) else output.shape[2] * output.shape[3]
        channels = module.out_channels if not isinstance(module, nn.ConvTranspose2d) else module.in_channels
        per_channel = c_in_per_group if not isinstance(module, nn.ConvTranspose2d) else module.out_channels // module.groups
        total += pixels * channels * per_channel * kernel

    handles = [m.register_forward_hook(hook) for m in net.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))]
    with torch.inference_mode():
        net(torch.zeros(1, 1, height, width))
    for h in handles:
        h.remove()
    return total


def load_bench_images(image_dir: Path, count: int, height: int, width: int) -> list[np.ndarray]:
    """``count`` grayscale images resized (area) and centre-cropped to exactly ``height x width``."""
    images = []
    for key in list_images(image_dir)[:count]:
        image = read_image(image_dir / key)
        scale = max(height / image.shape[0], width / image.shape[1])
        image = cv2.resize(image, (round(image.shape[1] * scale + 0.5), round(image.shape[0] * scale + 0.5)),
                           interpolation=cv2.INTER_AREA)
        top, left = (image.shape[0] - height) // 2, (image.shape[1] - width) // 2
        images.append(np.ascontiguousarray(image[top:top + height, left:left + width]))
    return images


class PlainSEKD:
    """The straightforward path: the network as written, fp32, default layout, then the same post-processing."""

    def __init__(self, net: SEKDNet, config: SEKDConfig):
        self.net, self.config = net.eval(), config

    @torch.inference_mode()
    def extract(self, image: np.ndarray) -> dict[str, np.ndarray]:
        prob, raw = self.net(torch.from_numpy(image.astype(np.float32) / 255)[None, None])
        xy, scores = nms_keypoints(prob[0, 0], self.config.nms_radius, self.config.threshold, self.config.max_keypoints)
        desc = sample_descriptors(raw[0], xy.float(), *image.shape)
        return {"keypoints": xy.float().numpy(), "scores": scores.numpy(), "descriptors": desc.numpy()}


class SiftExtractor:
    def __init__(self, max_keypoints: int):
        self.sift = cv2.SIFT_create(nfeatures=max_keypoints)

    def extract(self, image: np.ndarray):
        return self.sift.detectAndCompute(image, None)


def time_method(extractor, images: list[np.ndarray], repeats: int) -> tuple[float, list]:
    """Images/s over ``repeats`` passes after one warm-up image; also the outputs of the last pass."""
    extractor.extract(images[0])
    start = time.perf_counter()
    for _ in range(repeats):
        outputs = [extractor.extract(image) for image in images]
    return repeats * len(images) / (time.perf_counter() - start), outputs


def agreement(reference: list[dict], other: list[dict]) -> dict[str, float]:
    """Share of reference keypoints found at the same pixel, and descriptor cosine there."""
    same, total, cosines = 0, 0, []
    for ref, out in zip(reference, other):
        index = {tuple(p): i for i, p in enumerate(np.round(out["keypoints"]).astype(int))}
        for i, p in enumerate(np.round(ref["keypoints"]).astype(int)):
            j = index.get(tuple(p))
            if j is not None:
                same += 1
                cosines.append(float(ref["descriptors"][i] @ out["descriptors"][j]))
        total += len(ref["keypoints"])
    cos = np.array(cosines) if cosines else np.zeros(1)
    return {"same_pixel": same / max(total, 1), "cosine_median": float(np.median(cos)), "cosine_min": float(cos.min())}


def embedded_lite() -> nn.Module | None:
    """The embedded SEKD-Lite network, or None when this installation has none."""
    from ..model.weights import EMBEDDED_MODELS, load_model

    path = EMBEDDED_MODELS.get("lite")
    return load_model(path)[0] if path is not None and path.is_file() else None


def benchmark_speed(net: SEKDNet, image_dir: Path, count: int = 8, height: int = 480, width: int = 640,
                    repeats: int = 2, max_keypoints: int = 2000, num_threads: int | None = None,
                    lite: nn.Module | None | str = "embedded") -> dict:
    """Run every method on the same images; returns rates, ratios, GFLOP/s and fast-vs-fp32 agreement.

    ``lite``: the SEKD-Lite network timed beside ``net`` ("embedded": the packaged one when
    present; None: no Lite rows). Its agreement is measured against its own fp32 output.
    """
    threads = set_num_threads(num_threads)
    images = load_bench_images(image_dir, count, height, width)
    gflop = 2 * count_macs(net, height, width) / 1e9
    lite = embedded_lite() if isinstance(lite, str) else lite
    # Integer keypoints: the agreement columns compare the networks' outputs, which sub-pixel
    # offsets (fitted on each path's own probability map) would blur; their cost is negligible.
    config = SEKDConfig(max_keypoints=max_keypoints, device="cpu", subpixel=False)
    # Built lazily and in this order: the fast path tunes the allocator process-wide.
    factories = {
        "sekd plain fp32": lambda: PlainSEKD(net, config),
        "sekd fast fp32": lambda: SEKDExtractor(net, SEKDConfig(**{**config.as_dict(), "precision": "fp32"})),
        "sekd fast auto": lambda: SEKDExtractor(net, config),
        "opencv sift": lambda: SiftExtractor(max_keypoints),
    }
    from ..failures import first_line
    from ..model import int8
    if int8.available():  # optional extra; its one-time calibration runs before timing (cached per weights)
        factories["sekd int8"] = lambda: SEKDExtractor(net, SEKDConfig(**{**config.as_dict(), "precision": "int8"}))
    if lite is not None:
        factories["sekd lite fp32"] = lambda: SEKDExtractor(lite, SEKDConfig(**{**config.as_dict(), "precision": "fp32"}))
        factories["sekd lite auto"] = lambda: SEKDExtractor(lite, config)
        if int8.available():  # Lite quantized like the full network (its own calibration, cached)
            factories["sekd lite int8"] = lambda: SEKDExtractor(lite, SEKDConfig(**{**config.as_dict(),
                                                                                   "precision": "int8"}))
    rates, outputs, methods, failed = {}, {}, {}, {}
    for name, factory in factories.items():
        try:
            methods[name] = factory()
            rates[name], outputs[name] = time_method(methods[name], images, repeats)
        except Exception as exc:
            if "int8" not in name:
                raise
            # The optional int8 runtime (OpenVINO) can refuse a CPU or a build it does not
            # support; the other paths' figures still stand, and the report says why int8 has none.
            failed[name] = f"{type(exc).__name__}: {first_line(exc)}"
    fast = "sekd fast auto"
    extra = {}
    if "sekd int8" in rates:
        extra = {"int8_vs_fast_fp32": rates["sekd int8"] / rates["sekd fast fp32"],
                 "int8_vs_sift": rates["sekd int8"] / rates["opencv sift"],
                 "agreement_int8": agreement(outputs["sekd plain fp32"], outputs["sekd int8"])}
    gflop_of = {name: gflop for name in rates}
    if lite is not None:
        lite_gflop = 2 * count_macs(lite, height, width) / 1e9
        gflop_of.update({name: lite_gflop for name in rates if name.startswith("sekd lite")})
        extra.update({"lite_gflop_per_image": lite_gflop, "precision_lite_auto": methods["sekd lite auto"].model.precision,
                      "lite_vs_sift": rates["sekd lite auto"] / rates["opencv sift"],
                      "lite_fp32_vs_sift": rates["sekd lite fp32"] / rates["opencv sift"],
                      "agreement_lite_auto": agreement(outputs["sekd lite fp32"], outputs["sekd lite auto"])})
        if "sekd lite int8" in rates:
            extra.update({"lite_int8_vs_lite_fp32": rates["sekd lite int8"] / rates["sekd lite fp32"],
                          "agreement_lite_int8": agreement(outputs["sekd lite fp32"], outputs["sekd lite int8"])})
    return {
        "images": count, "size": [height, width], "threads": threads, "gflop_per_image": gflop,
        "precision_auto": methods[fast].model.precision,
        # The fast paths' forward (sekd_sfm.model.fused; SEKD_FUSED=0 turns it off): it changes their rates.
        "fast_forward": "fused" if methods[fast].model.fused is not None else "eager",
        "images_per_s": rates,
        "failed": failed,  # path -> error, for optional paths that could not run here
        "gflop_per_s": {k: v * gflop_of[k] for k, v in rates.items() if k.startswith("sekd")},
        "fast_vs_plain": rates[fast] / rates["sekd plain fp32"],
        "fast_vs_sift": rates[fast] / rates["opencv sift"],
        "agreement_fast_fp32": agreement(outputs["sekd plain fp32"], outputs["sekd fast fp32"]),
        "agreement_fast_auto": agreement(outputs["sekd plain fp32"], outputs[fast]),
        **extra,
        "cpu": cpu_description(),  # which machine type the rates belong to
        "versions": package_versions(),
        "record": run_record(),
    }
