"""Keypoint refinement (between matching and the database): move keypoints to where their matches agree.

A learned detector puts a keypoint where its probability map peaks, and that peak does not
follow the surface exactly: under a known homography SEKD's matched keypoints land a median
0.27 px from where the other photo's keypoint is (OpenCV SIFT: 0.12 px). Along a long walk
these errors add up to drift. This stage is the keypoint adjustment of Pixel-Perfect SfM
(Lindenberger et al., ICCV 2021) computed on image intensities instead of dense CNN features:

1. per matched pair, a RANSAC fundamental matrix keeps the geometrically consistent matches;
2. per kept match (a, b), the local affine map between the two photos (least squares over the
   pair's ``neighbours`` nearest matches) and a Lucas-Kanade alignment of a Gaussian-weighted
   patch around a's keypoint into photo b (contrast gain and offset free, for lighting) give
   ``t``: where a's keypoint lies in b, relative to b's keypoint;
3. one sparse linear least-squares problem over all keypoints, ``d_b - A d_a = t`` per match
   plus a weak prior ``prior * d = 0`` (it fixes each track's free shift at the mean of its
   detections), reweighted twice (Huber) against the odd wrong match.

Matches whose patches do not align (normalised cross-correlation under ``min_ncc``, or a
shift over ``max_shift``) are left out. Keypoints of no kept match stay where they are.
Work happens at the extraction's resolution (the feature file's ``resize_max``), where the
patches have the size the detector saw; shifts are applied in original pixels.

Output: an hloc-layout keypoints file (``<image>/keypoints``, ``<image>/image_size``) that
``create_database`` (and hloc's triangulation) reads in place of the feature file's keypoints.

Steps 1-2 are per pair and run as an ``execution.Stage`` (``RefineWorker``) on the caller's executor
(worker processes on this machine, or a Ray cluster), saved pair by pair to ``<output stem>-pairs.h5`` (a killed run
resumes from the pairs it finished; the file goes once the output is written); step 3 runs here.
"""
from __future__ import annotations

import json
import logging
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import SekdError
from ..execution import Executor, Stage, using
from ..files import features as ff
from ..files import matches as mf
from ..files.atomic import atomic_output
from ..files.images import ImageReadError, load_scaled, to_resized_pixels
from ..files.pairresults import PairResults, write_pair_group
from ..files.signature import input_signature
from ..runtime import package_versions

logger = logging.getLogger("sekd")

FORMAT = "sekd-keypoints"
#: The per-pair alignments of a refinement in progress (``RefineWorker``'s output).
PAIRS_FORMAT = "sekd-refine-pairs-2"  # 2: two arrays per pair (edges, info)
#: Pairs per worker call on a Ray cluster or in a local worker process (a single process makes one call for all):
#: ~1 s of work, so the last tasks leave few cores idle; a Ray cluster grows it with its size.
PAIRS_PER_TASK = 8
#: Long side (px) the photos are aligned at when the feature file does not say (an hloc file):
#: the resolution ``sekd reconstruct`` extracts at.
DEFAULT_ALIGN_MAX = 1600
#: Images kept decoded (with their gradients) while pairs are processed.
IMAGE_CACHE_BYTES = 512 * 1024 * 1024


@dataclass
class RefineConfig:
    """Settings of the keypoint refinement; lengths in pixels at the extraction's resolution."""

    enabled: bool = True
    patch_radius: int = 4       # the patch is (2r+1)^2 px
    sigma: float = 2.5          # Gaussian weight of the patch
    iterations: int = 8         # Lucas-Kanade steps
    min_ncc: float = 0.7        # a match whose aligned patches correlate less is left out
    max_shift: float = 1.5      # ... and one whose alignment moves further
    neighbours: int = 12        # matches that fix the local affine map of a match
    ransac_px: float = 1.5      # epipolar threshold of the pair's RANSAC
    prior: float = 0.1          # weight pulling each keypoint towards its detection

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class AlignImage:
    """A photo at the extraction's resolution: intensities, gradients, and original pixels per pixel."""

    image: np.ndarray   # H x W float32, 0..255
    gx: np.ndarray      # H x W float32, d image / dx
    gy: np.ndarray
    sx: float
    sy: float

    def __post_init__(self):
        # H x W x 3 (intensity, gx, gy): the alignment samples all three at the same points, so one gather serves
        # them (a third of the indexing work of three lookups). The three fields become views of it: one copy of
        # the pixels is held, not two.
        self.stacked = np.stack([self.image, self.gx, self.gy], -1)
        self.image, self.gx, self.gy = self.stacked[..., 0], self.stacked[..., 1], self.stacked[..., 2]

    @property
    def nbytes(self) -> int:
        return self.stacked.nbytes


def load_align_image(path: Path, resize_max: int | None) -> AlignImage:
    """Grayscale photo reduced as extraction reduces it, with Sobel gradients (per pixel)."""
    import cv2

    _, small, sx, sy = load_scaled(path, resize_max)
    image = small.astype(np.float32)
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    return AlignImage(image, gx, gy, sx, sy)


def bilinear(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Values of ``image`` (H x W, or H x W x C) at ``points`` (... x 2, x y in pixels, centres at integers), clamped
    to the image: ``...`` (or ``... x C``).

    Exact bilinear interpolation (OpenCV's remap rounds positions to 1/32 px).
    """
    h, w = image.shape[:2]
    flat = image.reshape(h * w, -1)
    x = np.clip(points[..., 0], 0, w - 1.001)
    y = np.clip(points[..., 1], 0, h - 1.001)
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]  # the points' dtype (float32 for the alignment)
    i = y0.astype(np.int64) * w + x0.astype(np.int64)
    # np.take over rows gathers all channels of a pixel at once (fancy indexing is ~3x slower there).
    top = np.take(flat, i, axis=0)
    top += (np.take(flat, i + 1, axis=0) - top) * fx
    bottom = np.take(flat, i + w, axis=0)
    bottom += (np.take(flat, i + w + 1, axis=0) - bottom) * fx
    top += (bottom - top) * fy
    return top if image.ndim == 3 else top[..., 0]


def patch_grid(radius: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Offsets ``P x 2`` of a (2r+1)^2 patch and their Gaussian weights ``P`` (P = (2r+1)^2)."""
    axis = np.arange(-radius, radius + 1, dtype=np.float32)
    offsets = np.stack(np.meshgrid(axis, axis), -1).reshape(-1, 2)
    return offsets, np.exp(-(offsets ** 2).sum(1) / (2 * sigma ** 2)).astype(np.float32)


def local_affines(xa: np.ndarray, xb: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """Per match, the affine ``x_b ~ A x_a + c`` fitted to its ``neighbours`` nearest matches (in photo a).

    ``xa``, ``xb``: ``M x 2``. Returns ``A`` (``M x 2 x 2``) and the fit's error at the match itself (px).
    """
    from scipy.spatial import cKDTree

    k = min(neighbours, len(xa))
    _, nearest = cKDTree(xa).query(xa, k=k)
    nearest = nearest.reshape(len(xa), k)
    X = np.concatenate([xa[nearest], np.ones((len(xa), k, 1))], -1)      # M x k x 3
    Xt = X.transpose(0, 2, 1)
    solution = np.linalg.solve(Xt @ X + 1e-6 * np.eye(3), Xt @ xb[nearest])  # M x 3 x 2
    A = solution[:, :2, :].transpose(0, 2, 1)
    predicted = np.einsum("mij,mj->mi", A, xa) + solution[:, 2, :]
    return A, np.linalg.norm(predicted - xb, axis=1)


def _centred(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    return values - (values * weights).sum(1, keepdims=True) / weights.sum()


#: A patch alignment step smaller than this (px, both axes) ends that match's iterations: a tenth of the
#: keypoints' remaining error after refinement (~0.1 px).
CONVERGED_PX = 1e-2


def _gauss_newton_step(b: AlignImage, xb: np.ndarray, t: np.ndarray, warped: np.ndarray, patch_a: np.ndarray,
                       aa: np.ndarray, w: np.ndarray) -> np.ndarray:
    """One Gauss-Newton step of ``align_patches`` for ``M`` matches: the change of ``t`` (``M x 2``, px) to subtract.

    ``xb``, ``t``: ``M x 2``; ``warped``: ``M x P x 2`` (a's patch offsets mapped into b); ``patch_a``: ``M x P``
    (centred); ``aa``: ``M x 1`` (its weighted energy); ``w``: ``1 x P``. The step is clipped to 1 px per axis.
    """
    sampled = _centred(bilinear(b.stacked, xb[:, None] + t[:, None] + warped), w[..., None])  # M x P x 3
    patch_b, gx, gy = sampled[..., 0], sampled[..., 1], sampled[..., 2]
    gain = (patch_a * patch_b * w).sum(1, keepdims=True) / aa
    residual = patch_b - gain * patch_a
    gxw, gyw = gx * w, gy * w
    hessian = np.stack([np.stack([(gx * gxw).sum(1), (gy * gxw).sum(1)], -1),
                        np.stack([(gy * gxw).sum(1), (gy * gyw).sum(1)], -1)], -2) + 1e-3 * np.eye(2)
    gradient = np.stack([(gxw * residual).sum(1), (gyw * residual).sum(1)], -1)
    return np.clip(np.linalg.solve(hessian, gradient[..., None])[..., 0], -1, 1).astype(np.float32)


def align_patches(a: AlignImage, b: AlignImage, xa: np.ndarray, xb: np.ndarray, A: np.ndarray,
                  config: RefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Where a's patch around each ``xa`` lies in photo b, relative to ``xb``: shifts ``t`` (``M x 2``) and NCC (``M``).

    Minimises sum_o w(o) (I_b(x_b + t + A o) - g I_a(x_a + o) - h)^2 over t, g and h by
    Gauss-Newton (g, h in closed form each step). Points in pixels at the processed resolution.
    """
    offsets, weights = patch_grid(config.patch_radius, config.sigma)
    w = weights[None]
    patch_a = _centred(bilinear(a.stacked, xa[:, None] + offsets[None])[..., 0], w)
    warped = np.einsum("mij,pj->mpi", A, offsets).astype(np.float32)           # M x P x 2
    t = np.zeros((len(xa), 2), np.float32)
    aa = np.maximum((patch_a * patch_a * w).sum(1, keepdims=True), 1e-6)
    active = np.arange(len(xa))
    for _ in range(config.iterations):
        step = _gauss_newton_step(b, xb[active], t[active], warped[active], patch_a[active], aa[active], w)
        t[active] -= step
        # A match stops once its step is under CONVERGED_PX (on a generated 40-photo block: 4.0 steps of the 8 on
        # average; the refined keypoints differ from 8 steps' by 0.0005 px on average, at most 0.02 px).
        active = active[np.abs(step).max(1) > CONVERGED_PX]
        if not len(active):
            break
    patch_b = _centred(bilinear(b.stacked, xb[:, None] + t[:, None] + warped)[..., 0], w)
    ncc = (patch_a * patch_b * w).sum(1) / np.sqrt(np.maximum((patch_a ** 2 * w).sum(1) * (patch_b ** 2 * w).sum(1), 1e-9))
    return t, ncc


def solve_offsets(num_points: int, ia: np.ndarray, ib: np.ndarray, A: np.ndarray, t: np.ndarray,
                  prior: float, reweightings: int = 2, fixed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Keypoint shifts ``d`` (``num_points x 2``) with ``d[ib] - A d[ia] ~ t`` per match, and the final residuals.

    ``ia``, ``ib``: ``E`` point indices; ``A``: ``E x 2 x 2``; ``t``: ``E x 2``. Linear least
    squares plus ``prior * d = 0``, then Huber reweighting (scale 0.25 px) ``reweightings`` times.
    ``fixed`` (``num_points`` bools): points that do not move (their columns leave the system, so ``d`` = 0 there).

    Solved exactly, through the normal equations, track by track (``TrackSystem``): the system falls apart into
    one small block per track. Points of no match keep ``d = 0``, the prior's minimum, and leave the system.
    """
    E = len(ia)
    if E == 0:
        return np.zeros((num_points, 2)), np.zeros(0)
    matched = np.zeros(num_points, bool)
    matched[ia] = matched[ib] = True
    moving = np.flatnonzero(matched if fixed is None else matched & ~fixed)
    column = np.full(num_points, -1, np.int64)
    column[moving] = np.arange(len(moving))
    system = TrackSystem(len(moving), column[ia], column[ib])  # -1: a fixed point, whose shift (zero) leaves it
    d = np.zeros((num_points, 2))
    weight = np.ones(E)
    for _ in range(reweightings + 1):
        d[moving] = system.solve(A, t, weight ** 2, prior)
        da, db = d[ia], d[ib]
        residual = np.hypot(db[:, 0] - A[:, 0, 0] * da[:, 0] - A[:, 0, 1] * da[:, 1] - t[:, 0],
                            db[:, 1] - A[:, 1, 0] * da[:, 0] - A[:, 1, 1] * da[:, 1] - t[:, 1])
        weight = 1 / np.maximum(1, residual / 0.25)
    return d, residual


#: Tracks (connected points) of at most this many points are solved as dense blocks, many at once; larger ones
#: (wrong matches can chain tracks together) as one sparse system.
MAX_DENSE_TRACK = 64
#: Matches per pass of the dense blocks' assembly, which holds 14 numbers per match: bounds its memory (~56 MB).
ASSEMBLY_MATCHES = 250_000
#: Entries of the dense blocks assembled at once (32 MB).
ASSEMBLY_ENTRIES = 4_000_000


class TrackSystem:
    """The normal equations of ``solve_offsets`` for fixed matches, one dense block per track.

    Each match ``e`` ties the shift of point ``b[e]`` to that of ``a[e]``: the equations of different tracks
    share no unknown, so the ``2k x 2k`` block of a track of ``k`` points is solved on its own, and tracks of
    one size all at once (a batched LAPACK solve). A sparse factorisation of the whole (SuperLU) cost 1.6 s
    for the 270,000 matches of 100 photos and 59 s (6.5 GB) for 6.3 million, where the blocks take a
    fraction of that (docs/experiments.md, section 49).

    ``columns``: unknown points; ``a``, ``b``: each match's columns (``E``; -1: a fixed point, left out).
    """

    def __init__(self, columns: int, a: np.ndarray, b: np.ndarray):
        from scipy import sparse
        from scipy.sparse.csgraph import connected_components

        linked = (a >= 0) & (b >= 0)
        graph = sparse.coo_matrix((np.ones(int(linked.sum())), (a[linked], b[linked])), shape=(columns, columns))
        _, track = connected_components(graph, directed=False)
        size = np.bincount(track)
        # Columns in order of track size, then track: each size's tracks are one contiguous run of columns.
        order = np.lexsort((track, size[track]))
        self.rank = np.empty(columns, np.int64)  # column -> its place in that order
        self.rank[order] = np.arange(columns)
        sizes = size[track[order]]
        self.groups = [(int(k), int(lo), int(hi)) for k, lo, hi in _runs(sizes)]  # (size, first, end) ranks
        self.columns = columns
        self.a = np.where(a >= 0, self.rank[np.maximum(a, 0)], -1)
        self.b = np.where(b >= 0, self.rank[np.maximum(b, 0)], -1)
        # Matches in column order of their track (a match's points share one), so a run of tracks has a run of them.
        key = np.where(self.b >= 0, self.b, self.a)
        self.matches = np.argsort(key, kind="stable")
        self.first = np.searchsorted(key[self.matches], np.arange(columns + 1))

    def solve(self, A: np.ndarray, t: np.ndarray, w2: np.ndarray, prior: float) -> np.ndarray:
        """The shifts (``columns x 2``) minimising ``sum w2 |d_b - A d_a - t|^2 + prior^2 |d|^2``."""
        shifts = np.zeros((self.columns, 2))
        for k, lo, hi in self.groups:
            if k > MAX_DENSE_TRACK:
                shifts[lo:] = self._solve_sparse(lo, A, t, w2, prior)
                break
            per_track = (self.first[hi] - self.first[lo]) * k / (hi - lo)  # matches
            step = k * max(1, min(int(ASSEMBLY_MATCHES / max(per_track, 1)), ASSEMBLY_ENTRIES // (2 * k) ** 2))
            for start in range(lo, hi, step):
                shifts[start:min(start + step, hi)] = self._solve_dense(k, start, min(start + step, hi), A, t, w2,
                                                                        prior)
        return shifts[self.rank]

    def _solve_dense(self, k: int, lo: int, hi: int, A, t, w2, prior: float) -> np.ndarray:
        """The shifts of columns ``lo:hi``: whole tracks of ``k`` points each."""
        e = self.matches[self.first[lo]:self.first[hi]]
        n, tracks = 2 * k, (hi - lo) // k
        a, b, w = self.a[e] - lo, self.b[e] - lo, w2[e]
        (a00, a01), (a10, a11), (t0, t1) = A[e, 0].T, A[e, 1].T, t[e].T
        # A fixed end (-1) takes no equation: its entries get weight 0, placed at its partner's.
        wa, wb = np.where(a >= 0, w, 0.0), np.where(b >= 0, w, 0.0)
        a, b = np.where(a >= 0, a, b), np.where(b >= 0, b, a)
        wc = np.minimum(wa, wb)
        # A match adds w [[I, -A], [-A^T, A^T A]] over (d_b, d_a) to its track's block, w [t, -A^T t] to its right side.
        ra, rb = 2 * (a % k), 2 * (b % k)  # the first row of d_a and d_b within the block
        block = b // k * n
        ra_n, rb_n = (block + ra) * n, (block + rb) * n  # rows d_a[0] and d_b[0] of the flattened blocks
        flat = np.concatenate([rb_n + rb, rb_n + n + rb + 1,
                               rb_n + ra, rb_n + ra + 1, rb_n + n + ra, rb_n + n + ra + 1,
                               ra_n + rb, ra_n + n + rb, ra_n + rb + 1, ra_n + n + rb + 1,
                               ra_n + ra, ra_n + ra + 1, ra_n + n + ra, ra_n + n + ra + 1])
        c00, c01, c10, c11 = -wc * a00, -wc * a01, -wc * a10, -wc * a11
        q01 = wa * (a00 * a01 + a10 * a11)
        value = np.concatenate([wb, wb, c00, c01, c10, c11, c00, c01, c10, c11,
                                wa * (a00 * a00 + a10 * a10), q01, q01, wa * (a01 * a01 + a11 * a11)])
        normal = np.bincount(flat, value, minlength=tracks * n * n).reshape(tracks, n, n)
        normal[:, np.arange(n), np.arange(n)] += prior ** 2
        rhs = np.bincount(np.concatenate([block + rb, block + rb + 1, block + ra, block + ra + 1]),
                          np.concatenate([wb * t0, wb * t1, -wa * (a00 * t0 + a10 * t1), -wa * (a01 * t0 + a11 * t1)]),
                          minlength=tracks * n)
        return np.linalg.solve(normal, rhs.reshape(tracks, n, 1)).reshape(hi - lo, 2)

    def _solve_sparse(self, lo: int, A, t, w2, prior: float) -> np.ndarray:
        """The shifts of columns ``lo:`` (the tracks over MAX_DENSE_TRACK points) from one sparse system (SuperLU)."""
        from scipy import sparse
        from scipy.sparse.linalg import spsolve

        e = self.matches[self.first[lo]:]
        cols, E = self.columns - lo, len(e)
        ca, cb = np.where(self.a[e] >= 0, self.a[e] - lo, -1), np.where(self.b[e] >= 0, self.b[e] - lo, -1)
        rows = np.arange(E)
        r = np.concatenate([2 * rows, 2 * rows + 1, 2 * rows, 2 * rows, 2 * rows + 1, 2 * rows + 1])
        c = np.concatenate([2 * cb, 2 * cb + 1, 2 * ca, 2 * ca + 1, 2 * ca, 2 * ca + 1])
        v = np.concatenate([np.ones(E), np.ones(E), -A[e, 0, 0], -A[e, 0, 1], -A[e, 1, 0], -A[e, 1, 1]])
        known = c >= 0
        system = sparse.csr_matrix((v[known], (r[known], c[known])), shape=(2 * E, 2 * cols))
        weights = np.repeat(w2[e], 2)
        normal = (system.T @ sparse.diags(weights) @ system).tocsc()
        normal += sparse.identity(2 * cols, format="csc") * prior ** 2
        return spsolve(normal, system.T @ (weights * t[e].ravel()), permc_spec="COLAMD").reshape(-1, 2)


def _runs(values: np.ndarray):
    """``(value, start, end)`` of each run of equal values in ``values`` (sorted)."""
    if len(values) == 0:
        return
    edges = np.flatnonzero(np.diff(values)) + 1
    starts, ends = np.concatenate([[0], edges]), np.concatenate([edges, [len(values)]])
    yield from zip(values[starts], starts, ends)


class _ImageCache:
    """Decoded photos, least recently used dropped first once over ``budget`` bytes."""

    def __init__(self, image_dir: Path, resize_max: int | None, budget: int = IMAGE_CACHE_BYTES):
        self.image_dir, self.resize_max, self.budget = image_dir, resize_max, budget
        self.items: OrderedDict[str, AlignImage] = OrderedDict()

    def __getitem__(self, name: str) -> AlignImage:
        if name in self.items:
            self.items.move_to_end(name)
            return self.items[name]
        try:
            item = load_align_image(self.image_dir / name, self.resize_max)
        except ImageReadError as exc:
            raise SekdError(f"keypoint refinement: {exc}") from None
        self.items[name] = item
        while sum(i.nbytes for i in self.items.values()) > self.budget and len(self.items) > 2:
            self.items.popitem(last=False)
        return item


def _may_share_surface(xa: np.ndarray, xb: np.ndarray, config: RefineConfig) -> bool:
    """Whether a fundamental matrix explains at least ``neighbours`` of the matches (``M x 2`` each, px), by
    OpenCV's USAC (8-point samples, SPRT): a pair of no common surface is rejected within a few hypotheses, 11x
    faster than FM_RANSAC's 1,000 iterations on such pairs (70 % of a retrieval run's pairs). Only a gate:
    USAC's inliers differ from FM_RANSAC's (more of them, and the refined poses are worse: fountain-P11 pose
    AUC@1 0.935 against 0.943), so FM_RANSAC still picks the matches of the pairs that pass."""
    import cv2

    _, inliers = cv2.findFundamentalMat(xa, xb, cv2.USAC_FM_8PTS, config.ransac_px, 0.999)
    return inliers is not None and inliers.sum() >= config.neighbours


def _pair_edges(a: AlignImage, b: AlignImage, ka: np.ndarray, kb: np.ndarray, idx: np.ndarray,
                config: RefineConfig):
    """The kept matches of one pair (``idx``: ``M x 2`` keypoint indices): a's and b's indices, A, t (processed px)."""
    import cv2

    ia, ib = idx[:, 0].astype(np.int64), idx[:, 1].astype(np.int64)
    if len(ia) < max(8, config.neighbours):
        return None
    xa, xb = to_resized_pixels(ka[ia], a.sx, a.sy), to_resized_pixels(kb[ib], b.sx, b.sy)
    if not _may_share_surface(xa, xb, config):
        return None
    _, inliers = cv2.findFundamentalMat(xa, xb, cv2.FM_RANSAC, config.ransac_px, 0.999)
    if inliers is None or inliers.sum() < config.neighbours:
        return None
    keep = inliers[:, 0].astype(bool)
    ia, ib, xa, xb = ia[keep], ib[keep], xa[keep], xb[keep]
    A, fit_error = local_affines(xa, xb, config.neighbours)
    t, ncc = align_patches(a, b, xa.astype(np.float32), xb.astype(np.float32), A.astype(np.float32), config)
    ok = (fit_error < 3) & (ncc > config.min_ncc) & (np.abs(t).max(1) < config.max_shift)
    return ia[ok], ib[ok], A[ok], t[ok].astype(np.float64)


def _edges_arrays(kept, considered: int, a: AlignImage, b: AlignImage) -> dict[str, np.ndarray]:
    """What a pair contributes to the solve, as two arrays (HDF5's cost is per dataset, ~1 ms, not per byte):
    ``edges`` (``M x 8``: a's and b's keypoint indices, the local affine map row by row, the alignment; float64
    holds the indices exactly) and ``info`` (the matches considered, then both photos' original pixels per
    processed pixel: sx, sy of a, then of b)."""
    if kept is None:
        kept = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2, 2)), np.zeros((0, 2)))
    ia, ib, A, t = kept
    edges = np.concatenate([ia[:, None], ib[:, None], A.reshape(-1, 4), t], 1).astype(np.float64)
    return {"edges": edges, "info": np.array([considered, a.sx, a.sy, b.sx, b.sy], np.float64)}


def _unpack_edges(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``ia``, ``ib`` (``M``), ``A`` (``M x 2 x 2``), ``t`` (``M x 2``) of a pair's ``edges`` (``_edges_arrays``)."""
    edges = arrays["edges"]
    return (edges[:, 0].astype(np.int64), edges[:, 1].astype(np.int64), edges[:, 2:6].reshape(-1, 2, 2),
            edges[:, 6:8])


class RefineWorker:
    """Refinement's per-pair work (an ``execution.Stage`` worker): for each pair key (``matches.pair_key``), the
    geometrically kept matches and their patch alignments (``_pair_edges``). Built once per process; decoded
    photos are cached across calls (``_ImageCache``)."""

    def __init__(self, image_dir: str, features: str, matches: str, anchor: str | None, config: dict,
                 resize_max: int | None):
        self.features, self.matches = Path(features), Path(matches)
        self.anchor = Path(anchor) if anchor else None
        self.config = RefineConfig(**config)
        self.images = _ImageCache(Path(image_dir), resize_max)

    def _keypoints(self, names: set[str]) -> dict[str, np.ndarray]:
        """Keypoints (float64, original pixels) of ``names``: the anchor's where it has the image, else the features'."""
        found: dict[str, np.ndarray] = {}
        if self.anchor is not None:
            with h5py.File(self.anchor, "r") as f:
                found = {n: f[n]["keypoints"][()].astype(np.float64) for n in names if n in f}
        with h5py.File(self.features, "r") as f:
            found.update({n: f[n]["keypoints"][()].astype(np.float64) for n in names if n not in found})
        return found

    def __call__(self, keys: list[str]):
        pairs = [tuple(json.loads(key)) for key in keys]
        keypoints = self._keypoints({name for pair in pairs for name in pair})
        for key, (name0, name1, idx, _) in zip(keys, mf.iter_matches(self.matches, pairs)):
            a, b = self.images[name0], self.images[name1]
            kept = _pair_edges(a, b, keypoints[name0], keypoints[name1], idx, self.config)
            yield key, _edges_arrays(kept, len(idx), a, b), ""


def _pairs_file(output: Path) -> Path:
    return output.with_name(f"{output.stem}-pairs.h5")


def _align_pairs(features: Path, matches: Path, pairs: list[tuple[str, str]], image_dir: Path, output: Path,
                 config: RefineConfig, signature: str, anchor: Path | None,
                 executor: Executor, progress: bool) -> tuple[dict[str, dict[str, np.ndarray]], PairResults]:
    """Every pair's arrays (``RefineWorker``), by pair key: computed on ``executor`` into the pairs file beside
    ``output``, those a killed run with the same inputs finished reused; and that file, to remove once used."""
    results = PairResults(_pairs_file(output), PAIRS_FORMAT, signature)
    stage = Stage(name="refine keypoints", worker=RefineWorker,
                  args=(str(image_dir.resolve()), str(features.resolve()), str(matches.resolve()),
                        str(anchor.resolve()) if anchor else None, config.as_dict(), _alignment_resolution(features)),
                  batches=results.missing([mf.pair_key(a, b) for a, b in pairs]), output=results.path,
                  write_group=write_pair_group, unit="pair", items="pairs", verb="aligned", joinable=True,
                  per_task=PAIRS_PER_TASK, local_processes=True)
    return results.compute(stage, executor, progress), results


def _signature(features: Path, matches: Path, pairs: list[tuple[str, str]], config: RefineConfig,
               anchor: Path | None = None) -> str:
    """What the refined keypoints depend on: the files (size, modification time), the pairs, the settings."""
    return input_signature((features, matches, anchor), pairs, config.as_dict())


def is_current(output: Path, signature: str) -> bool:
    """Whether ``output`` holds refined keypoints made from exactly these inputs."""
    try:
        with h5py.File(output, "r") as f:
            return f.attrs.get("format") == FORMAT and f.attrs.get("signature") == signature
    except OSError:
        return False


def _alignment_resolution(features: Path) -> int | None:
    """The extraction's ``resize_max`` recorded in a sekd feature file; DEFAULT_ALIGN_MAX for a foreign file."""
    try:
        config = json.loads(ff.read_attrs(features).get("config", "{}"))
    except (SekdError, ValueError):
        return DEFAULT_ALIGN_MAX
    return config.get("resize_max", DEFAULT_ALIGN_MAX)


def refine_keypoints(features: str | Path, matches: str | Path, pairs: list[tuple[str, str]], image_dir: str | Path,
                     output: str | Path, config: RefineConfig | None = None, progress: bool = True,
                     anchor: str | Path | None = None, executor: str | Executor = "local") -> Path:
    """Refined keypoints of every image of ``features`` (hloc layout, original pixels) written to ``output``.

    ``pairs`` are the matched pairs to use (read from ``matches``). Reused when ``output`` was
    made from the same files, pairs and settings; written atomically (a killed run leaves no
    partial file). Returns ``output``.

    ``anchor``: an earlier refined file (``sekd reconstruct --extend``): its images keep its keypoints
    exactly and are the fixed ends of their matches, so only the other images' keypoints move.
    ``executor``: where the per-pair alignments run (an open executor, e.g. a pipeline's ``run.executor``, or the
    name of one; the same file either way). Call it holding the output folder's lock (the pipelines do).
    """
    config = config or RefineConfig()
    features, matches, image_dir, output = Path(features), Path(matches), Path(image_dir), Path(output)
    anchor = Path(anchor) if anchor is not None else None
    signature = _signature(features, matches, pairs, config, anchor)
    if is_current(output, signature):
        logger.info("%s: refined keypoints up to date, reused", output)
        return output
    start = time.perf_counter()
    names = ff.list_keys(features)
    with h5py.File(features, "r") as f:
        keypoints = {n: f[n]["keypoints"][()].astype(np.float64) for n in names}
        sizes = {n: f[n]["image_size"][()] for n in names if "image_size" in f[n]}
        # hloc's triangulation scales its thresholds by the keypoints' "uncertainty" (px): kept as extraction set it.
        uncertainty = {n: f[n]["keypoints"].attrs["uncertainty"] for n in names if "uncertainty" in f[n]["keypoints"].attrs}
    anchored = _anchored_keypoints(anchor, {n: len(k) for n, k in keypoints.items()}) if anchor is not None else {}
    keypoints.update({n: k.astype(np.float64) for n, k in anchored.items()})
    first = np.cumsum([0] + [len(keypoints[n]) for n in names])
    base = dict(zip(names, first[:-1].tolist()))
    wanted = [p for p in pairs if p[0] in base and p[1] in base]
    with using(executor) as runner:
        aligned, pair_results = _align_pairs(features, matches, wanted, image_dir, output, config, signature,
                                             anchor, runner, progress)
    scales: dict[str, tuple[float, float]] = {}
    edges, considered = [], 0
    for name0, name1 in wanted:  # in the pairs' order, whatever order they were computed in
        pair = aligned[mf.pair_key(name0, name1)]
        count, sx0, sy0, sx1, sy1 = pair["info"].tolist()
        scales[name0], scales[name1] = (sx0, sy0), (sx1, sy1)
        considered += int(count)
        ia, ib, A, t = _unpack_edges(pair)
        edges.append((base[name0] + ia, base[name1] + ib, A, t))
    if edges:
        ia, ib, A, t = (np.concatenate(part) for part in zip(*edges))
    else:
        ia, ib, A, t = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2, 2)), np.zeros((0, 2))
    fixed = np.zeros(first[-1].item(), bool)
    for name in anchored:
        fixed[base[name]: base[name] + len(keypoints[name])] = True
    shifts, residual = solve_offsets(first[-1].item(), ia.astype(np.int64), ib.astype(np.int64), A, t, config.prior,
                                     fixed=fixed)
    shifts = np.clip(shifts, -config.max_shift, config.max_shift)
    moved = np.linalg.norm(shifts, axis=1)
    summary = {"matches": considered, "aligned": len(ia),
               "median_shift_px": round(float(np.median(moved[moved > 0])), 4) if (moved > 0).any() else 0.0,
               "median_residual_px": round(float(np.median(residual)), 4) if len(residual) else None,
               "seconds": round(time.perf_counter() - start, 2)}
    with atomic_output(output) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update({"format": FORMAT, "signature": signature, "config": json.dumps(config.as_dict()),
                        "features": str(features), "matches": str(matches), "summary": json.dumps(summary),
                        "versions": json.dumps(package_versions()), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
        for name in names:
            sx, sy = scales.get(name, (1.0, 1.0))
            refined = keypoints[name] + shifts[base[name]: base[name] + len(keypoints[name])] * (sx, sy)
            group = f.create_group(name)
            group.create_dataset("keypoints", data=anchored[name] if name in anchored else refined.astype(np.float32))
            if name in uncertainty:
                group["keypoints"].attrs["uncertainty"] = uncertainty[name]
            if name in sizes:
                group.create_dataset("image_size", data=sizes[name])
    pair_results.remove()
    logger.info("%s: %d of %d matches aligned, median shift %.3f px", output, summary["aligned"], considered,
                summary["median_shift_px"])
    return output


def _anchored_keypoints(anchor: Path, counts: dict[str, int]) -> dict[str, np.ndarray]:
    """The keypoints (as stored, float32 N x 2) of ``anchor``'s images among those of ``counts`` (keypoints per
    image in the feature file); SekdError when a count differs (the files come from different extractions)."""
    with h5py.File(anchor, "r") as f:
        kept = {n: f[n]["keypoints"][()] for n in counts if n in f}
    wrong = [n for n, k in kept.items() if len(k) != counts[n]]
    if wrong:
        raise SekdError(f"{anchor}: {wrong[0]} has {len(kept[wrong[0]])} keypoints, the feature file "
                        f"{counts[wrong[0]]}; the files come from different extractions")
    return kept


def refine_summary(path: Path) -> dict:
    """The summary a refinement recorded (matches, aligned, median shift and residual, seconds)."""
    with h5py.File(path, "r") as f:
        return json.loads(f.attrs["summary"])
