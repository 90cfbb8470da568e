"""Loss terms of the training steps (docs/method.md "Training"), each on plain tensors.

Shapes: B = batch, h x w = crop; descriptors are unit vectors unless stated.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

#: Logs of probabilities get this added (the authors' constant), so log(0) never occurs.
LOG_EPS = 1e-8
#: Squared distances are clamped to at least this before the square root, so the gradient at
#: a zero distance stays finite (changes distances below 1e-6 only).
MIN_SQUARED_DISTANCE = 1e-12


def pairwise_distances(a: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """``d_ij = sqrt(max(|a_i|^2 + |p_j|^2 - 2 a_i.p_j, 0))`` for ``N x C`` and ``M x C`` -> ``N x M``."""
    squared = (a * a).sum(1)[:, None] + (p * p).sum(1)[None, :] - 2 * a @ p.t()
    return squared.clamp_min(MIN_SQUARED_DISTANCE).sqrt()


def hardest_negatives(d: torch.Tensor, min_distance: float = 0.008, penalty: float = 10.0,
                      exclude: torch.Tensor | None = None) -> torch.Tensor:
    """Per i: the smallest non-matching distance in row i *or* column i of ``d`` (anchor swap).

    The diagonal, entries closer than ``min_distance`` (practically the same point) and the
    ``exclude`` entries (``N x N`` bool, symmetric) get ``penalty`` added so they are never
    picked. ``N x N`` -> ``N``.
    """
    eye = torch.eye(d.shape[0], dtype=torch.bool, device=d.device)
    never = eye | (d < min_distance)
    if exclude is not None:
        never |= exclude
    masked = d + penalty * never.to(d.dtype)
    return torch.minimum(masked.min(dim=1).values, masked.min(dim=0).values)


def triplet_loss(a: torch.Tensor, p: torch.Tensor, form: str = "ratio", ratio_threshold: float = 0.85,
                 margin: float = 0.8, normalise: str = "count", min_distance: float = 0.008,
                 penalty: float = 10.0, exclude: torch.Tensor | None = None) -> torch.Tensor:
    """Descriptor loss of one sample: matched unit descriptors ``a_i <-> p_i`` (``N x C`` each), scalar.

    ``ratio`` ([code]): mean of ``pos - neg`` over the pairs with ``pos / neg > ratio_threshold``.
    ``margin`` ([paper]): ``sum max(0, pos - neg + margin)`` over n (``count``) or over the
    non-zero terms (``nonzero``, the code's variant). ``exclude``: pairs never used as negatives.
    """
    d = pairwise_distances(a, p)
    pos, neg = d.diagonal(), hardest_negatives(d, min_distance, penalty, exclude)
    if form == "ratio":
        active = ((pos / neg) > ratio_threshold).detach().to(d.dtype)
        return ((pos - neg) * active).sum() / (active.sum() + 1e-8)
    terms = F.relu(pos - neg + margin)
    count = (terms > 0).sum().clamp_min(1) if normalise == "nonzero" else terms.numel()
    return terms.sum() / count


def spread_out(a: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Global orthogonal regularisation (Zhang et al. 2017, "Learning spread-out local feature descriptors").

    Over the non-matching pairs ``a_i . p_j`` (i != j) of ``N x C`` unit descriptors:
    ``mean^2 + max(0, mean of squares - 1 / C)``, zero when they are spread like random unit
    vectors (mean 0, second moment 1 / C). The triplet losses are unchanged by a common
    component added to every descriptor except that it shrinks all their distances alike,
    which lowers a positive loss: this term pushes back. Scalar; 0 for fewer than 2 rows.
    """
    n = a.shape[0]
    if n < 2:
        return a.new_zeros(())
    dots = (a @ p.t())[~torch.eye(n, dtype=torch.bool, device=a.device)]
    return dots.mean() ** 2 + F.relu(dots.pow(2).mean() - 1.0 / a.shape[1])


def preservation_mse(new: tuple[torch.Tensor, ...], old: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """``mean_v MSE(new_v, old_v)`` over the views: ``0.5 (MSE(X0, X0') + MSE(X1, X1'))`` for two."""
    return sum(F.mse_loss(n, o) for n, o in zip(new, old)) / len(new)


def focal_loss(logits: torch.Tensor, labels: torch.Tensor, bg_weight: float, gamma: float = 1.0) -> torch.Tensor:
    """``(1 / 2N) sum_p w_y (1 - q)^gamma (-log q)``, ``q = softmax(L)[y]`` clamped to [1e-7, 1 - 1e-7].

    ``logits`` B x 2 x h x w, ``labels`` B x h x w in {0, 1}; N = B h w (the 1/2: the mean over
    the two class columns of the authors' implementation). Weights: background ``bg_weight``, keypoint 1.
    """
    y = labels.long()
    q = F.softmax(logits, dim=1).gather(1, y[:, None])[:, 0].clamp(1e-7, 1 - 1e-7)
    w = torch.where(y == 1, torch.ones_like(q), torch.full_like(q, bg_weight))
    return (w * (1 - q).pow(gamma) * -q.log()).sum() / (2 * q.numel())


def _kl_terms(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Element-wise ``x (log x - log(y + eps))`` (0 where x = 0)."""
    return torch.xlogy(x, x) - x * torch.log(y + LOG_EPS)


def repeatability_weighted(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """[code] Dense symmetric KL of one sample, weighted by the mean keypoint probability.

    ``u, v``: ``N x 2`` probabilities at corresponding pixels of view 0 and view 1.
    ``0.5 * mean_{p,c} w_p [KL terms both ways]`` with ``w_p = 0.5 (u_p1 + v_p1)`` detached.
    """
    w = (0.5 * (u[:, 1] + v[:, 1])).detach()[:, None]
    return 0.5 * (w * (_kl_terms(v, u) + _kl_terms(u, v))).mean()


def repeatability_paper(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """[paper] ``0.5 sum_i (KL(u_i || v_i) + KL(v_i || u_i))`` over corresponding keypoints (``N x 2``)."""
    return 0.5 * (_kl_terms(u, v) + _kl_terms(v, u)).sum()


def spatial_neighbours(points: torch.Tensor, radius: float) -> torch.Tensor:
    """``N x N`` bool: keypoints (``N x 2`` pixels) closer than ``radius`` px to each other (not self).

    All False for ``radius`` <= 0.
    """
    if radius <= 0:
        return torch.zeros(len(points), len(points), dtype=torch.bool, device=points.device)
    xy = points.to(torch.float32)
    close = torch.cdist(xy, xy) < radius
    return close & ~torch.eye(len(points), dtype=torch.bool, device=points.device)
