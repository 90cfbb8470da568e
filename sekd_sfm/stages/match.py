"""Stage 3: features.h5 + pairs.txt -> matches.h5 (``sekd match``).

Nearest-neighbour matching of descriptors, batched in torch (CPU, or a GPU when present):

* ``mnn``: mutual nearest neighbours: j is i's nearest neighbour and no descriptor of the
  first image is strictly nearer to j than i;
* ``ratio``: Lowe's ratio test, ``d1 < ratio * d2`` with d1, d2 the distances to i's two
  nearest neighbours in the other image (strict, so equal distances never pass);
* ``both``: the two tests together (the default).

Float descriptors use the L2 distance (RootSIFT's Hellinger distance for SIFT), binary
ones (uint8 bytes: ORB, AKAZE, BRISK) the Hamming distance. Ties go to the lowest index
(i's nearest among equals; j's partner among rows tying for it), so results are
deterministic. The score of a match is ``1 - d1/d2``, in [0, 1], higher = more distinctive.
"""
from __future__ import annotations

import json
import logging
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch

from ..errors import SekdError
from ..execution import Executor, RayOptions, Result, Stage, using
from ..files import features as ff
from ..files import locking, partstore
from ..files import matches as mf
from ..runtime import exact_sqrt, package_versions, resolve_device, set_num_threads
from .pairs import Pair, read_pairs

logger = logging.getLogger("sekd")
MATCH_MODES = ("mnn", "ratio", "both")
#: Default ratio per match mode and feature type, measured with ``sekd bench ratios`` on
#: fountain-P11 (34 pairs, images <= 1600 px, 4000 keypoints; figures in docs/matching.md):
#: the ratio (0.60..1.00, step 0.05) giving the most matches consistent with the ground-truth
#: epipolar geometry among those whose precision is >= 0.9.
DEFAULT_RATIO = {
    "both": {"sekd": 0.9, "sift": 0.85, "orb": 0.7, "akaze": 0.7, "brisk": 0.7, "kaze": 0.7,
             "disk": 1.0, "aliked": 0.95, "xfeat": 0.7},
    "ratio": {"sekd": 0.85, "sift": 0.8, "orb": 0.65, "akaze": 0.7, "brisk": 0.7, "kaze": 0.6,
              "disk": 0.9, "aliked": 0.9, "xfeat": 0.65},
}
#: For a feature type not measured yet: Lowe's value.
FALLBACK_RATIO = 0.8
#: Features whose descriptors are gradient histograms, matched as RootSIFT by default.
ROOTSIFT_FEATURES = ("sift",)
#: Images whose prepared descriptors stay in memory while matching (exhaustive pairs reuse them).
CACHE_IMAGES = 256
#: Pairs per part chunk file (~32 KB of results per pair at 4000 keypoints: ~32 MB a chunk).
PART_PAIRS = 1024


@dataclass
class MatchConfig:
    """How to match: ``mode`` in MATCH_MODES; ``ratio`` None = the feature type's DEFAULT_RATIO;
    ``rootsift`` None = RootSIFT (Hellinger distance) for SIFT descriptors only.

    ``max_elements`` bounds the distance entries computed at once (4 bytes each), and
    so the memory; it does not change the result.
    """

    mode: str = "both"
    ratio: float | None = None
    rootsift: bool | None = None
    device: str = "auto"
    max_elements: int = 1 << 25


def describe_config(config: MatchConfig, feature_type: str, binary: bool) -> dict:
    """The settings that determine the matches (recorded in, and compared with, the match file)."""
    if config.mode not in MATCH_MODES:
        raise SekdError(f"unknown match mode {config.mode!r}; choose from {', '.join(MATCH_MODES)}")
    ratio = None
    if config.mode != "mnn":
        ratio = config.ratio if config.ratio is not None else DEFAULT_RATIO[config.mode].get(feature_type, FALLBACK_RATIO)
        if not 0 < ratio <= 1:
            raise SekdError(f"the ratio must be in (0, 1], got {ratio}")
    rootsift = feature_type in ROOTSIFT_FEATURES if config.rootsift is None else config.rootsift
    if rootsift and binary:
        raise SekdError("RootSIFT applies to histogram descriptors (SIFT), not to binary ones")
    return {"mode": config.mode, "ratio": ratio, "metric": "hamming" if binary else "l2", "rootsift": rootsift}


def prepare_descriptors(descriptors: np.ndarray, binary: bool, rootsift: bool = False) -> torch.Tensor:
    """``N x D`` descriptors as float32 rows: unpacked to 8 D bits (0/1) if binary, RootSIFT if asked, else as they are.

    RootSIFT (L1-normalise, square root; Arandjelovic & Zisserman 2012) turns L2 into the
    Hellinger distance between the gradient histograms, which matches SIFT better.
    """
    if binary:
        return torch.from_numpy(np.unpackbits(np.ascontiguousarray(descriptors, np.uint8), axis=1).astype(np.float32))
    d = np.ascontiguousarray(descriptors, np.float32)
    if rootsift:
        d = np.sqrt(np.maximum(d, 0) / np.maximum(np.abs(d).sum(1, keepdims=True), 1e-12)).astype(np.float32)
    return torch.from_numpy(d)


def augment_rows(d: torch.Tensor) -> torch.Tensor:
    """Left factor ``N x (D+2)``: rows ``[a, |a|^2, 1]`` of the prepared descriptors ``d`` (N x D)."""
    sq = (d * d).sum(1, keepdim=True)
    return torch.cat([d, sq, torch.ones_like(sq)], dim=1)


def augment_cols(d: torch.Tensor) -> torch.Tensor:
    """Right factor ``(D+2) x N``: columns ``[-2b, 1, |b|^2]``, contiguous (a faster CPU matmul than a transposed view)."""
    sq = (d * d).sum(1, keepdim=True)
    return torch.cat([-2 * d, torch.ones_like(sq), sq], dim=1).T.contiguous()


def stack_rows(factors: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch left factors (N_i x K) into B x max N x K; padding rows ``[0, inf, 1]`` have infinite distances."""
    counts = torch.tensor([len(f) for f in factors], device=factors[0].device)
    if len(factors) == 1:
        return factors[0][None], counts
    out = factors[0].new_zeros((len(factors), max(1, int(counts.max())), factors[0].shape[1]))
    out[:, :, -2] = torch.inf
    out[:, :, -1] = 1
    for i, f in enumerate(factors):
        out[i, : len(f)] = f
    return out, counts


def stack_cols(factors: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch right factors (K x N_i) into B x K x max N; padding columns ``[0, 1, inf]`` have infinite distances."""
    counts = torch.tensor([f.shape[1] for f in factors], device=factors[0].device)
    if len(factors) == 1:
        return factors[0][None], counts
    out = factors[0].new_zeros((len(factors), factors[0].shape[0], max(1, int(counts.max()))))
    out[:, -2, :] = 1
    out[:, -1, :] = torch.inf
    for i, f in enumerate(factors):
        out[i, :, : f.shape[1]] = f
    return out, counts


def distances(a0: torch.Tensor, a1t: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """``B x N0 x N1`` distances by one batched matmul of augmented factors, no further pass over the matrix.

    ``a0`` B x N0 x (D+2) rows ``[a, |a|^2, 1]`` and ``a1t`` B x (D+2) x N1 columns
    ``[-2b, 1, |b|^2]`` multiply to ``|a|^2 + |b|^2 - 2 a.b``: the squared L2 distance, or for
    0/1 bit rows the Hamming distance (exact integers in float32). Squared L2 may come out
    slightly negative by rounding. Padding (an infinite norm, zeros elsewhere, so that no
    0 x inf product arises) gives infinite distances. ``out``: a ``B x N0 x N1`` tensor to
    write them into (a reused buffer) instead of a new one.
    """
    return torch.bmm(a0, a1t, out=out)


def _nearest_two(dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per row: best distance, its column (the lowest on ties), second-best distance. Overwrites ``dist``."""
    best, arg = dist.min(2)
    second = dist.scatter_(2, arg[..., None], torch.inf).min(2).values
    return best, arg, second


def match_batch(a0: torch.Tensor, a1t: torch.Tensor, n0: torch.Tensor, binary: bool, mode: str,
                ratio: float | None, max_elements: int = 1 << 25,
                workspace: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Match a batch of pairs given as augmented factors (``stack_rows`` / ``stack_cols``).

    ``a0`` B x N0 x (D+2), ``a1t`` B x (D+2) x N1, ``n0`` (B) the real row counts. Rows are
    processed in chunks of at most ``max_elements`` distances. ``workspace``: a 1-D tensor
    (``a0``'s dtype and device) the distances are computed into when they fit, kept by the
    caller from batch to batch (``DescriptorCache.workspace``). Returns ``matches0`` B x N0
    (long, -1 = unmatched) and ``scores0`` B x N0 = 1 - d1/d2 for kept matches, else 0.
    """
    B, N0, N1 = a0.shape[0], a0.shape[1], a1t.shape[2]
    if N0 == 0 or N1 == 0:
        return torch.full((B, N0), -1, dtype=torch.long, device=a0.device), a0.new_zeros((B, N0))
    rows = max(1, max_elements // max(1, B * N1))
    best, second = a0.new_full((B, N0), torch.inf), a0.new_full((B, N0), torch.inf)
    arg = torch.zeros((B, N0), dtype=torch.long, device=a0.device)
    col_best = a0.new_full((B, N1), torch.inf)
    for r0 in range(0, N0, rows):
        chunk = a0[:, r0:r0 + rows]
        size = B * chunk.shape[1] * N1
        fits = workspace is not None and size <= workspace.numel()
        dist = distances(chunk, a1t, workspace[:size].view(B, chunk.shape[1], N1) if fits else None)
        col_best = torch.minimum(col_best, dist.amin(1))
        best[:, r0:r0 + rows], arg[:, r0:r0 + rows], second[:, r0:r0 + rows] = _nearest_two(dist)
    return _select(best, arg, second, col_best, binary, mode, ratio)


def _mutual(best: torch.Tensor, arg: torch.Tensor, col_best: torch.Tensor) -> torch.Tensor:
    """Rows whose nearest column has no strictly nearer row; among rows tying for a column, the lowest wins."""
    rows = torch.arange(best.shape[1], device=best.device).expand_as(arg)
    candidate = torch.isfinite(best) & (best <= col_best.gather(1, arg))
    first = torch.full_like(col_best, best.shape[1], dtype=torch.long)
    first.scatter_reduce_(1, arg, torch.where(candidate, rows, best.shape[1]), "amin")
    return candidate & (first.gather(1, arg) == rows)


def _select(best, arg, second, col_best, binary, mode, ratio):
    keep = torch.isfinite(best)
    if mode in ("mnn", "both"):
        keep &= _mutual(best, arg, col_best)
    d1, d2 = (best, second) if binary else (exact_sqrt(best), exact_sqrt(second))
    if mode in ("ratio", "both"):
        keep &= d1 < ratio * d2
    # Score = ratio margin; an unmatched second neighbour (d2 = inf) gives 1, equal distances 0.
    scores = torch.where(d2 > 0, 1 - d1 / d2, torch.zeros_like(d1)).nan_to_num_(0.0)
    return torch.where(keep, arg, -1), torch.where(keep, scores, torch.zeros_like(scores))


def match_descriptors(desc0: np.ndarray, desc1: np.ndarray, mode: str = "both", ratio: float | None = 0.8,
                      rootsift: bool = False, device: str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Match one pair: ``desc0`` N0 x D, ``desc1`` N1 x D (float32 = L2, or uint8 bytes = binary/Hamming).

    Returns ``matches0`` (N0 int32, index into desc1 or -1) and ``scores0`` (N0 float32).
    """
    if desc0.dtype != desc1.dtype or desc0.shape[1:] != desc1.shape[1:]:
        raise SekdError(f"cannot match {desc0.dtype} x {desc0.shape[1:]} descriptors with {desc1.dtype} x {desc1.shape[1:]}")
    binary, dev = desc0.dtype == np.uint8, resolve_device(device)
    d0, d1 = (prepare_descriptors(d, binary, rootsift).to(dev) for d in (desc0, desc1))
    n0 = torch.tensor([len(d0)], device=dev)
    m, s = match_batch(augment_rows(d0)[None], augment_cols(d1)[None], n0, binary, mode, ratio)
    return m[0].cpu().numpy().astype(np.int32), s[0].cpu().numpy().astype(np.float32)


class DescriptorCache:
    """Augmented factors (left, right) of the images of an open feature file; least recently used dropped first."""

    def __init__(self, f: h5py.File, binary: bool, rootsift: bool, device: torch.device, capacity: int = CACHE_IMAGES):
        self.f, self.binary, self.rootsift, self.device, self.capacity = f, binary, rootsift, device, capacity
        self.items: OrderedDict[str, tuple[torch.Tensor, torch.Tensor]] = OrderedDict()
        self._workspace: torch.Tensor | None = None

    def workspace(self, elements: int) -> torch.Tensor:
        """A float32 buffer of ``elements`` for the distance matrices, allocated once and reused batch after batch.

        A fresh matrix per batch (up to 128 MB) costs a mapping and the kernel's zeroing of
        every page each time, or, where the heap keeps large blocks, a heap that fragments as
        the shapes change (docs/benchmarks.md, Large scenes: peak RSS); one buffer costs neither.
        """
        if self._workspace is None or self._workspace.numel() < elements:
            self._workspace = None  # the old one goes before the new one is allocated
            self._workspace = torch.empty(elements, dtype=torch.float32, device=self.device)
        return self._workspace

    def __getitem__(self, key: str) -> tuple[torch.Tensor, torch.Tensor]:
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        d = prepare_descriptors(self.f[key]["descriptors"][()].T, self.binary, self.rootsift).to(self.device)
        self.items[key] = value = (augment_rows(d), augment_cols(d))
        if len(self.items) > self.capacity:
            self.items.popitem(last=False)
        return value


def batches(pairs: list[Pair], sizes: dict[str, int], max_elements: int, max_pairs: int = 64):
    """Split ``pairs`` into consecutive batches whose padded distance matrices fit ``max_elements``."""
    batch, n0, n1 = [], 0, 0
    for a, b in pairs:
        m0, m1 = max(n0, sizes[a]), max(n1, sizes[b])
        if batch and ((len(batch) + 1) * m0 * m1 > max_elements or len(batch) == max_pairs):
            yield batch
            batch, m0, m1 = [], sizes[a], sizes[b]
        batch.append((a, b))
        n0, n1 = m0, m1
    if batch:
        yield batch


def check_feature_file(features: Path) -> tuple[dict, dict[str, int]]:
    """Attributes and keypoint counts of a feature file whose images all have the declared descriptors.

    SekdError if some images hold descriptors of another size or type (a mixed file).
    """
    attrs = ff.read_attrs(features)
    if attrs["format"] == "hloc":
        logger.info("%s: an hloc feature file (no feature type recorded): descriptors matched as float vectors "
                    "(L2 distance, ratio %s unless --ratio)", features, FALLBACK_RATIO)
    dim, dtype = int(attrs["descriptor_dim"]), np.dtype(str(attrs["descriptor_dtype"]))
    sizes, odd = {}, []
    with h5py.File(features, "r") as f:
        for key in ff.list_keys(features):
            if "descriptors" not in f[key]:
                raise SekdError(f"{features}: image '{key}' has keypoints but no descriptors; "
                                "extract the images again with `sekd extract` (or hloc's extract_features)")
            d = f[key]["descriptors"]
            sizes[key] = int(d.shape[-1])
            # float16 (hloc's as_half) is read as float32, so only the kind of number must agree.
            same_type = d.dtype == dtype or (d.dtype == np.float16 and dtype == np.float32)
            if d.ndim != 2 or d.shape[0] != dim or not same_type:
                odd.append(f"{key} ({d.dtype} x {d.shape[0]})")
    if odd:
        raise SekdError(
            f"{features}: mixes descriptor types: the file declares {attrs['feature_type']} ({dtype} x {dim}) but "
            f"{len(odd)} image(s) differ: {_some(odd)}; re-extract them into one file per feature type"
        )
    return attrs, sizes


def _some(names: list[str], limit: int = 10) -> str:
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def check_pairs(pairs: list[Pair], sizes: dict[str, int], features: Path, pairs_path: Path) -> None:
    """SekdError listing the images named in the pairs that the feature file lacks."""
    missing = sorted({name for pair in pairs for name in pair if name not in sizes})
    if missing:
        raise SekdError(
            f"{features}: has no features for {len(missing)} image(s) named in {pairs_path}: {_some(missing)}; "
            "extract features for them first, or remove these pairs"
        )


def _file_attrs(features: Path, fattrs: dict, described: dict) -> dict:
    return {
        "format": mf.FORMAT,
        "format_version": mf.FORMAT_VERSION,
        "feature_type": str(fattrs["feature_type"]),
        "descriptor_dim": int(fattrs["descriptor_dim"]),
        "descriptor_dtype": str(fattrs["descriptor_dtype"]),
        "features_config": str(fattrs["config"]),
        "config": ff.json_attr(described),
        "features": str(features.resolve()),
        "versions": ff.json_attr(package_versions()),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _check_same_features(output: Path, attrs: dict, features: Path) -> None:
    """Refuse to add matches of one feature type to a match file of another."""
    if not output.exists():
        return
    old = ff.read_attrs(output, mf.FORMAT, role="output")
    keys = ("feature_type", "descriptor_dim", "descriptor_dtype")
    if any(str(old.get(k)) != str(attrs[k]) for k in keys):
        raise SekdError(
            f"{output}: holds matches of {old.get('feature_type')} features ({old.get('descriptor_dtype')} x "
            f"{old.get('descriptor_dim')}), but {features} has {attrs['feature_type']} ({attrs['descriptor_dtype']} x "
            f"{attrs['descriptor_dim']}); feature types cannot be mixed: choose another output or pass --overwrite"
        )


def match_features(
    features: str | Path,
    pairs: str | Path,
    output: str | Path,
    config: MatchConfig | None = None,
    *,
    overwrite: bool = False,
    num_threads: int | None = None,
    progress: bool = True,
    checkpoint_seconds: float = 10.0,
    executor: str | Executor = "local",
    ray_options: RayOptions | None = None,
) -> Path:
    """Match the image pairs listed in the file ``pairs`` using the features in ``features``; write ``output``.

    Resumable: pairs already in ``output`` (in either order) are skipped. Refuses (SekdError)
    pairs naming images the feature file lacks, and mixing feature types. Returns ``output``.

    Pairs are streamed in batches: memory holds the pair list, the descriptors of at most
    CACHE_IMAGES images and one batch of results. Finished pairs are saved to
    ``<output>.parts/`` at least every ``checkpoint_seconds`` and written into ``output`` once,
    at the end (see ``files.partstore``). Holds ``output``'s lock: a second run on the same file is refused.
    ``executor``: an open executor (a pipeline's ``run.executor``), or the name of one to open for this call
    (``"ray"`` matches on a Ray cluster with ``ray_options``, ``execution``); the same file either way.
    """
    config = config or MatchConfig()
    features, pairs_path, output = Path(features), Path(pairs), Path(output)
    with using(executor, ray_options) as runner, locking.writer_lock(output, "matches file"):
        return _match(features, pairs_path, output, config, overwrite, num_threads, progress, checkpoint_seconds,
                      runner)


def _match(features: Path, pairs_path: Path, output: Path, config: MatchConfig, overwrite: bool,
           num_threads: int | None, progress: bool, checkpoint_seconds: float, executor: Executor) -> Path:
    fattrs, sizes = check_feature_file(features)
    pair_list = read_pairs(pairs_path)
    check_pairs(pair_list, sizes, features, pairs_path)
    mf.check_hloc_keys(pair_list, pairs_path)
    binary = str(fattrs["descriptor_dtype"]) == "uint8"
    described = describe_config(config, str(fattrs["feature_type"]), binary)
    attrs = _file_attrs(features, fattrs, described)
    if not overwrite:
        _check_same_features(output, attrs, features)
    parts = partstore.PartStore(output, max_items=PART_PAIRS, max_seconds=checkpoint_seconds)
    partstore.prepare_output(output, attrs, parts, overwrite, ("features_config", "config"), "feature or match configuration")
    done = mf.stored_pairs(output, pair_list) | {frozenset(pair) for pair in _part_pairs(parts)}
    todo = [p for p in pair_list if frozenset(p) not in done]
    logger.info("%s: %d pairs, %d already matched, %d to match (%s)", output, len(pair_list),
                len(pair_list) - len(todo), len(todo), described)
    set_num_threads(num_threads)
    stage = Stage(name="match", worker=MatchWorker, args=(str(features.resolve()), binary, described, config),
                  batches=[[mf.pair_key(a, b) for a, b in group] for group in batches(todo, sizes, config.max_elements)],
                  output=output, write_group=mf.write_pair_group, unit="pair", items="pairs")

    def on_error(key: str, error: str) -> None:  # a pair fails only with its whole run (its worker raises)
        raise SekdError(error)

    # Nothing new: the file stays untouched (a rewrite would change its time for nothing).
    executor.run(stage, parts, on_error, progress=progress,
                 attrs=lambda: {"modified": time.strftime("%Y-%m-%dT%H:%M:%S%z")} if todo else None)
    return output


def _part_pairs(parts: partstore.PartStore) -> list[tuple[str, str]]:
    return [tuple(json.loads(key)) for key in sorted(parts.keys())]


class MatchWorker:
    """Matching's worker (``execution.Stage``): opens the feature file once per process (at its first batch), keeps
    the prepared descriptors of recent images (``DescriptorCache``), and matches one batch of pairs per call:
    the pairs padded into one distance matrix, so local and Ray runs compute the same numbers.
    """

    def __init__(self, features: str, binary: bool, described: dict, config: MatchConfig):
        self.features, self.binary, self.described, self.config = features, binary, described, config
        self.cache: DescriptorCache | None = None

    def _open(self) -> DescriptorCache:
        try:
            f = h5py.File(self.features, "r")
        except OSError as exc:  # e.g. a Ray node that does not see the file: nothing can be matched there
            raise SekdError(f"{self.features}: cannot read the feature file ({exc}); every node must see it at the "
                            "same path (shared storage)") from exc
        return DescriptorCache(f, self.binary, self.described.get("rootsift", False), resolve_device(self.config.device))

    def __call__(self, keys: list[str]) -> list[Result]:
        if self.cache is None:
            self.cache = self._open()
        batch = [tuple(json.loads(key)) for key in keys]
        a0, n0 = stack_rows([self.cache[a][0] for a, _ in batch])
        a1t, _ = stack_cols([self.cache[b][1] for _, b in batch])
        matches, scores = match_batch(a0, a1t, n0, self.binary, self.described["mode"], self.described["ratio"],
                                      self.config.max_elements, self.cache.workspace(self.config.max_elements))
        matches, scores = matches.cpu().numpy(), scores.cpu().numpy()
        return [(key, {"matches0": matches[i, :int(n0[i])].astype(np.int32),
                       "matching_scores0": scores[i, :int(n0[i])].astype(np.float32)}, "")
                for i, key in enumerate(keys)]
