"""Retrieval pairs: a global descriptor per image from its own local descriptors, then nearest neighbours.

The global descriptor is VLAD (Jégou et al. 2010) with the refinements of "All about VLAD"
(Arandjelović & Zisserman 2013): local descriptors are L2-normalised, reduced by PCA to
``pca_dim`` dimensions, assigned to the nearest of ``vocabulary_size`` k-means centroids;
the residuals to each centroid are summed, each centroid's sum is L2-normalised
(intra-normalisation), then the whole vector gets a signed square root and an L2 norm.
Binary descriptors (ORB, AKAZE, BRISK: uint8 bytes) are unpacked to +-1 floats first, so
every feature type works the same way.

The vocabulary (PCA + centroids) is learned on the collection itself from a bounded sample
of descriptors (at most ``max_samples`` from at most ``sample_images`` images): no download,
nothing shipped per feature type, and it fits whatever the images show.

Global descriptors are stored beside the features in ``<features>.global.h5``::

    attrs: format="sekd-global", identity (JSON: feature file identity + retrieval config)
    vocabulary/mean (D), vocabulary/projection (D x d), vocabulary/centroids (k x d)   float32
    names       M strings           image keys
    descriptors M x (k * d) float16 unit L2 (cosine similarity = dot product)

The vocabulary is learned from a bounded sample (its cost does not grow with the collection): the
sample's PCA and its split into ``vocabulary_groups`` groups in the driver, each group's words as one item
of an ``execution.Stage`` (``WordsWorker``); each image's VLAD is one item of another (``VladWorker``).
Both run in this process or on Ray workers (``executor``).

Resumable: images already described are not recomputed; a different feature file or
retrieval configuration makes a new vocabulary and recomputes everything. Work in progress
is saved in ``<global>.parts/`` (the vocabulary, and each described image through the crash-safe
part store), and the file is only ever replaced whole (temporary name with the PID, fsync, rename),
so a kill at any moment loses at most a few seconds of work.
"""
from __future__ import annotations

import hashlib
import json
import logging
import shutil
import tempfile
import time
from collections.abc import Iterable
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

import h5py
import numpy as np
import torch

from ..errors import SekdError
from ..execution import Executor, Stage, using
from ..files import features as ff
from ..files.atomic import atomic_output
from ..files.locking import exclusive_lock
from ..files.pairresults import PairResults, write_pair_group
from ..runtime import exact_sqrt

logger = logging.getLogger("sekd")
FORMAT = "sekd-global"
#: The format of the per-image results of a run in progress (``<global>.parts/descriptors.h5``).
PARTS_FORMAT = "sekd-global-parts"
#: The format of the vocabulary's groups in progress (``<global>.parts/words.h5``).
WORDS_FORMAT = "sekd-vocabulary-groups"
#: Images per Ray task: an image's VLAD takes ~20 ms, so a task of 64 outweighs its ~5 ms of overhead.
IMAGES_PER_TASK = 64


@dataclass
class RetrievalConfig:
    """How global descriptors are made: VLAD with ``vocabulary_size`` centroids over ``pca_dim``-D local descriptors.

    The global descriptor has ``vocabulary_size * pca_dim`` dimensions (65,536 by default,
    128 KiB per image as float16). 1024 words: recall@20 on generated streets of 500 and
    1,000 photos 0.974 and 0.956 against 0.959 and 0.934 with 512 (docs/pairs.md).
    """

    vocabulary_size: int = 1024
    pca_dim: int = 64
    max_samples: int = 100_000
    sample_images: int = 1000
    kmeans_iterations: int = 20
    #: The words are learned in this many groups of the sample, each on its own (``learn_vocabulary``); 1: one
    #: k-means over the whole sample.
    vocabulary_groups: int = 4
    seed: int = 0


#: Fewest sampled descriptors per visual word (the vocabulary shrinks for tiny collections).
SAMPLES_PER_WORD = 32


@dataclass
class Vocabulary:
    """PCA and k-means centroids of local descriptors: ``mean`` (D), ``projection`` (D x d), ``centroids`` (k x d)."""

    mean: np.ndarray
    projection: np.ndarray
    centroids: np.ndarray


def global_path(features: str | Path) -> Path:
    """Where the global descriptors of ``features`` live: ``features.h5`` -> ``features.global.h5``."""
    features = Path(features)
    return features.with_name(features.stem + ".global.h5")


def local_to_float(descriptors: np.ndarray) -> torch.Tensor:
    """N x D local descriptors as unit-L2 float32 (binary uint8 bytes unpacked to N x 8D +-1 values)."""
    if descriptors.dtype == np.uint8:
        bits = np.unpackbits(descriptors, axis=1).astype(np.float32)
        x = torch.from_numpy(bits * 2 - 1)
    else:
        x = torch.from_numpy(np.ascontiguousarray(descriptors, dtype=np.float32))
    return torch.nn.functional.normalize(x, dim=1)


def _nearest_centroid(x: torch.Tensor, centroids: torch.Tensor, block: int = 8192) -> torch.Tensor:
    """Index of the nearest centroid (L2) of each row of ``x``, in blocks so memory stays ~block x k.

    One fused ``addmm`` (``|c|^2 - 2 x.c``) per block of 8,192 rows (32 MB of distances at k = 1,024, in cache):
    the vocabulary's 20 Lloyd assignments of 100,000 descriptors took 27.6 s in blocks of 65,536 with a separate
    subtraction, 17.5 s so, the same assignments (one thread, AVX2)."""
    norms = (centroids * centroids).sum(1)
    return torch.cat([torch.addmm(norms, x[i:i + block], centroids.T, alpha=-2).argmin(1)
                      for i in range(0, len(x), block)])


def kmeans(x: torch.Tensor, k: int, iterations: int = 20, seed: int = 0) -> torch.Tensor:
    """k x D centroids of the N x D points ``x`` (k-means++ seeding, Lloyd iterations; k <= N).

    Torch is enough here: at N = 100,000, D = 64, k = 1,024 an iteration is ~13 GFLOP (~0.9 s on one AVX2 core).
    """
    gen = torch.Generator().manual_seed(seed)
    sq = (x * x).sum(1)

    def dist_to(i: int) -> torch.Tensor:  # squared L2 to x[i] as one matrix-vector product
        return (sq - 2 * (x @ x[i]) + sq[i]).clamp(min=0)

    first = int(torch.randint(len(x), (1,), generator=gen))
    centroids, dist = [x[first]], dist_to(first)
    for _ in range(1, k):
        total = float(dist.sum())
        pick = int(torch.multinomial(dist / total, 1, generator=gen)) if total > 0 else int(
            torch.randint(len(x), (1,), generator=gen))
        centroids.append(x[pick])
        dist = torch.minimum(dist, dist_to(pick))
    c = torch.stack(centroids)
    for _ in range(iterations):
        assign = _nearest_centroid(x, c)
        sums = torch.zeros_like(c).index_add_(0, assign, x)
        counts = torch.bincount(assign, minlength=k).to(x.dtype)
        new = torch.where(counts[:, None] > 0, sums / counts.clamp(min=1)[:, None], c)  # empty cluster: keep
        if torch.allclose(new, c, atol=1e-6):
            break
        c = new
    return c


def sample_descriptors(features: Path, names: list[str], config: RetrievalConfig) -> torch.Tensor:
    """N x D unit-L2 float32 local descriptors of ``names`` (at most ``max_samples`` from at most ``sample_images``
    images evenly spread over the collection, the same number from each)."""
    rng = np.random.default_rng(config.seed)
    chosen = [names[i] for i in np.unique(np.linspace(0, len(names) - 1, min(len(names), config.sample_images)).round()
                                          .astype(int))] if names else []
    per_image = max(1, -(-config.max_samples // max(1, len(chosen))))
    sample = []
    for name in chosen:
        desc = ff.read_features(features, name)["descriptors"]
        if len(desc) > per_image:
            desc = desc[np.sort(rng.choice(len(desc), per_image, replace=False))]
        sample.append(local_to_float(desc))
    return torch.cat(sample) if sample else torch.zeros(0, 0)


def share_words(counts: list[int], words: int) -> list[int]:
    """``words`` shared among groups of ``counts`` points in proportion (largest remainders first), no group more
    words than points."""
    total = sum(counts)
    exact = [words * c / total for c in counts]
    shares = [min(int(e), c) for e, c in zip(exact, counts)]
    for g in sorted(range(len(counts)), key=lambda g: shares[g] - exact[g]):
        if sum(shares) == words:
            break
        shares[g] += shares[g] < counts[g]
    return shares


class WordsWorker:
    """The vocabulary's per-group work (an ``execution.Stage`` worker): the k-means words (``kmeans``) of one
    group of the sample. ``sample``: an .npy file of the N x d reduced sample; ``groups``: one of its N group
    indices; ``words``: each group's number of words."""

    def __init__(self, sample: str, groups: str, words: list[int], iterations: int, seed: int):
        self.sample, self.groups, self.words, self.iterations, self.seed = sample, groups, words, iterations, seed

    def __call__(self, keys: list[str]):
        sample, groups = np.load(self.sample, mmap_mode="r"), np.load(self.groups)
        for key in keys:
            group = int(key.removeprefix("group-"))
            x = torch.from_numpy(np.ascontiguousarray(sample[np.flatnonzero(groups == group)]))
            centroids = kmeans(x, self.words[group], self.iterations, self.seed) if self.words[group] else x[:0]
            yield key, {"centroids": centroids.numpy()}, ""


def learn_vocabulary(features: Path, names: list[str], config: RetrievalConfig, executor: str | Executor = "local",
                     scratch: Path | None = None, identity: str = "") -> Vocabulary:
    """PCA + k-means on a sample of the local descriptors of ``names`` (``sample_descriptors``).

    The k-means runs in ``vocabulary_groups`` groups (``grouped_kmeans``, on ``executor``): a group of N/g points
    with k/g words costs 1/g^2 of one k-means over the whole sample, all g together 1/g, and the groups run in
    parallel. With 4 groups the 1,024 words of 100,000 descriptors take 2.9 s instead of 11.1 s (one thread), and
    retrieval recall@20 on generated walks of 100 to 2,000 photos stays within 0.004 of one k-means (another seed
    moves it by up to 0.008; docs/experiments.md, section 45). ``scratch``, ``identity``: ``grouped_kmeans``'s
    folder and signature (the global file's parts and identity: an interrupted run keeps its finished groups)."""
    x = sample_descriptors(features, names, config)
    if len(x) < 2:
        raise SekdError(f"{features}: fewer than 2 keypoints in the whole collection; retrieval pairs need "
                        "descriptors (use --pairs exhaustive, or extract with a lower --threshold)")
    mean = (x.sum(0, dtype=torch.float64) / len(x)).float()
    x -= mean  # in place: the sample is the largest array here (<= max_samples x D floats)
    eigvals, eigvecs = torch.linalg.eigh((x.T @ x).double() / len(x))
    dim = min(config.pca_dim, x.shape[1])
    projection = eigvecs[:, eigvals.argsort(descending=True)[:dim]].float()  # D x d, top principal axes
    reduced = torch.nn.functional.normalize(x @ projection, dim=1)
    del x
    # At least SAMPLES_PER_WORD descriptors per word: with fewer, words sit on single descriptors,
    # residuals vanish and the VLADs of a small collection carry nothing (tens of photos).
    words = min(config.vocabulary_size, max(1, len(reduced) // SAMPLES_PER_WORD))
    groups = max(1, min(config.vocabulary_groups, words))
    if groups == 1:
        centroids = kmeans(reduced, words, config.kmeans_iterations, config.seed)
    else:
        centroids = grouped_kmeans(reduced, words, groups, config.kmeans_iterations, config.seed, executor, scratch,
                                   identity)
    return Vocabulary(mean.numpy(), projection.numpy(), centroids.numpy())


def grouped_kmeans(x: torch.Tensor, k: int, groups: int, iterations: int = 20, seed: int = 0,
                   executor: str | Executor = "local", scratch: Path | None = None,
                   signature: str = "") -> torch.Tensor:
    """k x D centroids of the N x D points ``x`` learned in ``groups`` groups: ``x`` split by a k-means of ``groups``
    centroids, each group given its share of the ``k`` (``share_words``) and its own ``kmeans``, the groups' k-means
    run on ``executor`` (``WordsWorker``; in group order in the result).

    ``scratch``: a folder for the files the workers read (the points, their groups) and the finished groups, which
    a call with the same ``signature`` reuses (an interrupted run); on a Ray cluster every node must see it at the
    same path (as the features: docs/cluster.md). Default: a temporary folder (a local executor), signature: a
    digest of the points and settings."""
    top = kmeans(x, groups, iterations, seed)
    assign = _nearest_centroid(x, top)
    shares = share_words(torch.bincount(assign, minlength=groups).tolist(), k)
    with nullcontext(scratch) if scratch else tempfile.TemporaryDirectory(prefix="sekd-vocabulary-") as folder:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        points, grouping = folder / "sample.npy", folder / "groups.npy"
        for path, array in ((points, x.numpy()), (grouping, assign.numpy().astype(np.int32))):
            with atomic_output(path) as tmp, open(tmp, "wb") as f:
                np.save(f, array)
        results = PairResults(folder / "words.h5", WORDS_FORMAT,
                              signature or _digest(x, [k, groups, iterations, seed, shares]))
        keys = [f"group-{g}" for g in range(groups)]
        stage = Stage(name="vocabulary", worker=WordsWorker,
                      args=(str(points.resolve()), str(grouping.resolve()), shares, iterations, seed),
                      batches=results.missing(keys), output=results.path, write_group=write_pair_group,
                      unit="group", items="groups", verb="learned")
        with using(executor) as runner:
            found = results.compute(stage, runner, progress=False)
        results.remove()
        points.unlink()
        grouping.unlink()
    return torch.cat([torch.from_numpy(found[key]["centroids"]) for key in keys])


def _digest(x: torch.Tensor, settings: list) -> str:
    """What ``grouped_kmeans``'s groups depend on when the caller names nothing: the points and the settings."""
    return hashlib.sha1(x.numpy().tobytes() + json.dumps(settings).encode()).hexdigest()


def vlad(descriptors: np.ndarray, vocab: Vocabulary) -> np.ndarray:
    """Global descriptor (k * d float32, unit L2; zeros for an image without keypoints) of N x D local descriptors."""
    centroids = torch.from_numpy(vocab.centroids)
    out = torch.zeros_like(centroids)
    if len(descriptors):
        x = local_to_float(descriptors)
        x = torch.nn.functional.normalize((x - torch.from_numpy(vocab.mean)) @ torch.from_numpy(vocab.projection), dim=1)
        assign = _nearest_centroid(x, centroids)
        out.index_add_(0, assign, x - centroids[assign])
    out = torch.nn.functional.normalize(out, dim=1).flatten()  # intra-normalisation: no cluster dominates
    out = out.sign() * exact_sqrt(out.abs())  # power law: damps bursts of repeated structure
    return torch.nn.functional.normalize(out, dim=0).numpy()


def _identity(features: Path, config: RetrievalConfig) -> str:
    attrs = ff.read_attrs(features)
    keep = {k: str(attrs.get(k)) for k in ("feature_type", "descriptor_dim", "descriptor_dtype", "config", "created")}
    return json.dumps({"features": keep, "retrieval": asdict(config)}, sort_keys=True)


def _write_atomic(path: Path, write) -> None:
    """Call ``write(h5file)`` on a temporary file (unique per process), fsync it, rename it onto ``path``."""
    try:
        with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
            write(f)
    except OSError as exc:
        raise SekdError(f"{path}: cannot write global descriptors ({exc}); free space or choose another folder, "
                        "then rerun (described images are kept)") from exc


def _read_existing(path: Path, identity: str) -> tuple[Vocabulary | None, list[str]]:
    """The stored vocabulary and described names when ``path`` was made the same way, else (None, [])."""
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT or f.attrs.get("identity") != identity:
                return None, []
            vocab = Vocabulary(*(f["vocabulary"][k][()] for k in ("mean", "projection", "centroids")))
            return vocab, [n.decode() if isinstance(n, bytes) else n for n in f["names"][()]]
    except (OSError, KeyError):
        return None, []


def _vocab_id(vocab: Vocabulary) -> str:
    return hashlib.sha1(b"".join(a.tobytes() for a in (vocab.mean, vocab.projection, vocab.centroids))).hexdigest()


def _vocabulary_in_progress(parts: Path, identity: str) -> Vocabulary | None:
    """The vocabulary of an interrupted first run (so its chunks stay valid), if made the same way."""
    try:
        with np.load(parts / "vocabulary.npz") as data:
            same = str(data["identity"]) == identity
            return Vocabulary(data["mean"], data["projection"], data["centroids"]) if same else None
    except Exception:  # noqa: BLE001 - missing or torn: learn it again
        return None


def _save_vocabulary(parts: Path, identity: str, vocab: Vocabulary) -> None:
    _savez_durable(parts / "vocabulary.npz", identity=np.array(identity), **asdict(vocab))


def _savez_durable(target: Path, **arrays: np.ndarray) -> None:
    """``np.savez`` onto ``target`` atomically (temporary name, fsync, rename)."""
    with atomic_output(target) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def compute_global_descriptors(features: str | Path, config: RetrievalConfig | None = None, output: str | Path | None = None,
                               progress: bool = True, executor: str | Executor = "local") -> Path:
    """Describe every image of ``features`` by one global descriptor; write ``output`` (default ``global_path``).

    Returns ``output``. Images already in ``output`` (same feature file, same config) are kept. ``executor``: where
    the images' VLADs are computed (a name or an open ``execution.Executor``); the vocabulary is learned here.
    """
    config = config or RetrievalConfig()
    features = Path(features)
    output = Path(output) if output else global_path(features)
    identity, names = _identity(features, config), ff.list_keys(features)
    with exclusive_lock(output, what="global descriptors file"):
        try:
            _describe_all(features, output, config, identity, names, progress, executor)
        except OSError as exc:
            raise SekdError(f"{output}: global descriptors failed ({exc}); fix the cause (disk space, permissions) "
                            "and rerun: images already described are kept") from exc
    return output


class VladWorker:
    """Global descriptors' per-image work (an ``execution.Stage`` worker): each image's VLAD (``vlad``, stored as
    float16) from its local descriptors in ``features``."""

    def __init__(self, features: str, vocabulary: Vocabulary):
        self.features, self.vocabulary = features, vocabulary

    def __call__(self, keys: list[str]):
        for name in keys:
            row = vlad(ff.read_features(self.features, name)["descriptors"], self.vocabulary)
            yield name, {"vlad": row.astype(np.float16)}, ""


def _describe_all(features: Path, output: Path, config: RetrievalConfig, identity: str, names: list[str],
                  progress: bool, executor: str | Executor) -> None:
    vocab, stored = _read_existing(output, identity)
    parts = output.with_name(output.name + ".parts")
    done = set(stored)
    todo = [n for n in names if n not in done]
    if todo or done != set(names) or not output.is_file():
        # One executor for the vocabulary and the VLADs (a Ray cluster joined once), opened only for work: an
        # up-to-date file needs no cluster.
        with using(executor) as runner:
            if vocab is None:
                vocab = _vocabulary_in_progress(parts, identity)
            if vocab is None:
                vocab = _learned_vocabulary(features, output, parts, config, identity, names, runner)
            parts.mkdir(parents=True, exist_ok=True)
            results = PairResults(parts / "descriptors.h5", PARTS_FORMAT, _vocab_id(vocab), max_items=256)
            stage = Stage(name="global descriptors", worker=VladWorker, args=(str(features.resolve()), vocab),
                          batches=results.missing(todo), output=results.path, write_group=write_pair_group,
                          unit="img", items="images", verb="described", joinable=True, per_task=IMAGES_PER_TASK)
            results.run(stage, runner, progress)
        _merge(output, identity, vocab, stored, results.items(), set(names))
    shutil.rmtree(parts, ignore_errors=True)  # everything in it is now in the output
    logger.info("%s: %d global descriptors (%d new)", output, len(names), len(todo))


def _learned_vocabulary(features: Path, output: Path, parts: Path, config: RetrievalConfig, identity: str,
                        names: list[str], executor: Executor) -> Vocabulary:
    """``learn_vocabulary`` on ``executor``, logged and saved in ``parts`` (an interrupted run's images stay valid)."""
    started = time.perf_counter()
    vocab = learn_vocabulary(features, names, config, executor, parts, identity)
    groups = min(config.vocabulary_groups, len(vocab.centroids))  # as learn_vocabulary splits the words
    groups = f" in {groups} groups" if groups > 1 else ""
    logger.info("%s: vocabulary of %d words learned%s in %.1f s", output, len(vocab.centroids), groups,
                time.perf_counter() - started)
    _save_vocabulary(parts, identity, vocab)
    return vocab


def _merge(output: Path, identity: str, vocab: Vocabulary, stored: list[str],
           described: Iterable[tuple[str, dict[str, np.ndarray]]], keep: set[str]) -> None:
    """Write the global file: rows of the old file still wanted, then the images ``described`` (the stage's results,
    ``PairResults.items``); block by block, bounded memory."""
    old_rows = [i for i, n in enumerate(stored) if n in keep]

    def write(f: h5py.File) -> None:
        f.attrs["format"], f.attrs["identity"] = FORMAT, identity
        for key, value in asdict(vocab).items():
            f.create_dataset(f"vocabulary/{key}", data=value)
        dim = vocab.centroids.size
        rows = f.create_dataset("descriptors", (0, dim), np.float16, maxshape=(None, dim), chunks=(64, dim))
        all_names = [stored[i] for i in old_rows]
        if old_rows:
            with h5py.File(output, "r") as old:
                rows.resize(len(old_rows), axis=0)
                rows[:] = old["descriptors"][old_rows]
        seen, block = set(all_names), []

        def flush() -> None:
            rows.resize(rows.shape[0] + len(block), axis=0)
            rows[rows.shape[0] - len(block):] = np.stack(block)
            block.clear()

        for name, arrays in described:
            if name in keep and name not in seen:
                block.append(arrays["vlad"])
                all_names.append(name)
                seen.add(name)
                if len(block) == 256:
                    flush()
        if block:
            flush()
        f.create_dataset("names", data=np.array(all_names, dtype=h5py.string_dtype()))

    _write_atomic(output, write)


def _read_rows(data: h5py.Dataset, rows: np.ndarray) -> torch.Tensor:
    """Rows (increasing indices) of a 2-D dataset as float32; one slice read when they are dense."""
    if rows[-1] - rows[0] + 1 <= 2 * len(rows):  # h5py point selections are slow: read the span, index in memory
        return torch.from_numpy(data[rows[0]:rows[-1] + 1][rows - rows[0]].astype(np.float32))
    return torch.from_numpy(data[rows].astype(np.float32))


def nearest_neighbors(path: str | Path, names: list[str], k: int, block: int = 512) -> dict[str, list[str]]:
    """The ``k`` most similar images (cosine, best first) of each of ``names`` among ``names``, from the global file.

    Blocked over queries and database (``block`` rows each), so memory is ~block x block
    similarities plus 2 x block descriptors, whatever the number of images.
    """
    with h5py.File(path, "r") as f:
        stored = [n.decode() if isinstance(n, bytes) else n for n in f["names"][()]]
        index = {n: i for i, n in enumerate(stored)}
        missing = [n for n in names if n not in index]
        if missing:
            raise SekdError(f"{path}: no global descriptor for {missing[0]!r}; delete the file and rerun")
        rows = np.array(sorted(index[n] for n in names), dtype=np.int64)  # h5py reads increasing indices
        data = f["descriptors"]
        k = min(k, len(rows) - 1)
        result: dict[str, list[str]] = {}
        if k < 1:
            return {n: [] for n in names}
        for q0 in range(0, len(rows), block):
            queries = _read_rows(data, rows[q0:q0 + block])
            best_sim = torch.full((len(queries), k), -float("inf"))
            best_idx = torch.zeros((len(queries), k), dtype=torch.long)
            for d0 in range(0, len(rows), block):
                sim = queries @ _read_rows(data, rows[d0:d0 + block]).T
                if q0 == d0:
                    sim.fill_diagonal_(-float("inf"))  # an image is not its own neighbour
                sim, idx = torch.cat([best_sim, sim], 1), torch.cat([best_idx, torch.arange(d0, d0 + sim.shape[1])
                                                                   .expand(len(queries), -1)], 1)
                best_sim, top = sim.topk(k, dim=1)
                best_idx = idx.gather(1, top)
            for i, neighbours in enumerate(best_idx.tolist()):
                result[stored[rows[q0 + i]]] = [stored[rows[j]] for j in neighbours]
    return result


def neighbour_recall(retrieved: dict[str, list[str]], truth: dict[str, set[str]], k: int) -> float:
    """Recall@k: found true neighbours / possible ones, summed over queries with at least one true neighbour.

    For a query with T true neighbours, at most ``min(T, k)`` can be among its first ``k``
    retrieved, so that is its denominator (a perfect retrieval scores 1.0 at every k).
    """
    found = possible = 0
    for name, true in truth.items():
        if true:
            found += len(set(retrieved.get(name, [])[:k]) & true)
            possible += min(len(true), k)
    if possible == 0:
        raise ValueError("the ground truth has no neighbour pairs")
    return found / possible


def pair_recall(pairs, truth: dict[str, set[str]]) -> float:
    """Fraction of the true neighbour pairs ``{a, b}`` (a in truth[b]) present in ``pairs`` in either order."""
    true_pairs = {frozenset((a, b)) for a, others in truth.items() for b in others if a != b}
    if not true_pairs:
        raise ValueError("the ground truth has no neighbour pairs")
    return len(true_pairs & {frozenset(p) for p in pairs}) / len(true_pairs)


def query_neighbors(path: str | Path, queries: dict[str, np.ndarray], k: int, among: list[str] | None = None,
                    block: int = 512) -> dict[str, list[str]]:
    """The ``k`` images of the global file ``path`` most similar to each query (cosine, best first); read only.

    ``queries``: name -> N x D local descriptors of photos that are not in the file (new photos to
    localize), described with the file's own vocabulary; ``among``: only these stored images are
    candidates (None: all). Nothing is written: the file and its vocabulary stay as they are.
    """
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != FORMAT:
            raise SekdError(f"{path}: not a sekd global descriptors file; delete it (it is made again) or rerun")
        vocab = Vocabulary(*(f["vocabulary"][key][()] for key in ("mean", "projection", "centroids")))
        stored = [n.decode() if isinstance(n, bytes) else n for n in f["names"][()]]
        wanted = set(stored) if among is None else set(among)
        rows = np.array([i for i, n in enumerate(stored) if n in wanted], dtype=np.int64)
        names = list(queries)
        if not len(rows) or not names:
            return {n: [] for n in names}
        q = torch.from_numpy(np.stack([vlad(queries[n], vocab) for n in names]))  # Q x (k*d), unit L2
        sims = torch.cat([q @ _read_rows(f["descriptors"], rows[i:i + block]).T for i in range(0, len(rows), block)], 1)
    best = sims.topk(min(k, len(rows)), dim=1).indices.tolist()
    return {n: [stored[rows[j]] for j in best[i]] for i, n in enumerate(names)}
