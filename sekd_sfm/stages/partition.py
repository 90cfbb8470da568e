"""The view graph cut into overlapping clusters of photos, for the hierarchical mapper (``stages.hierarchical``).

The graph: one node per photo, one edge per verified pair, weighted by its inlier matches, each photo keeping
its ``neighbours`` strongest edges (a pair stays when either photo keeps it). Each connected part is cut in two
by a normalized cut (the sign split of the Fiedler vector of the normalized Laplacian, swept for the cut of least
normalized cost among balanced ones) until every part holds at most ``leaf_size`` photos; then each leaf takes
up to ``overlap`` photos of the others, those most strongly linked to it, so that neighbouring clusters share
cameras to be aligned by. The same graph gives the same clusters: no randomness, ties broken by image id.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import eigsh

from .colmap import open_database, require_pycolmap

#: A cut leaves at least this share of the photos on each side: clusters of similar sizes map in similar times.
MIN_SIDE = 0.3
#: A leaf of fewer photos (or of fewer than MIN_SIDE of the leaf size) joins its most strongly linked neighbour
#: (COLMAP's models keep 10 photos at least).
MIN_CLUSTER = 10
#: Above this many photos the Fiedler vector comes from a sparse eigensolver (below, a dense one is faster).
DENSE_UP_TO = 600


@dataclass(frozen=True)
class ClusterOptions:
    """How the view graph is cut: ``leaf_size`` photos at most per cluster before the overlap, ``overlap`` photos
    added from the other clusters, ``neighbours`` strongest edges per photo (COLMAP's ``image_overlap`` 50 and
    ``num_image_matches`` 20)."""

    leaf_size: int = 125
    overlap: int = 50
    neighbours: int = 20


def view_graph(database, min_num_matches: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The verified pairs of ``database`` with at least ``min_num_matches`` inliers: image ids ``(N,)`` int64 of
    every photo, and the edges as ``pairs (E, 2)`` image ids and ``weights (E,)`` inlier counts (a pair that did
    not verify has none)."""
    pycolmap = require_pycolmap()
    with open_database(database) as db:
        ids = np.array(sorted(image.image_id for image in db.read_all_images()), np.int64)
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
    found = [(pycolmap.pair_id_to_image_pair(pair_id), n) for pair_id, n in zip(pair_ids, counts)
             if n >= max(1, int(min_num_matches))]
    pairs = np.array([pair for pair, _ in found], np.int64).reshape(-1, 2)
    return ids, pairs, np.array([n for _, n in found], np.float64)


def strongest_edges(n: int, edges: np.ndarray, weights: np.ndarray, k: int) -> sparse.csr_matrix:
    """The ``n x n`` symmetric weight matrix of ``edges`` (node indices), each node keeping its ``k`` heaviest."""
    keep = np.zeros(len(edges), bool)
    for side in (0, 1):
        order = np.lexsort((-weights, edges[:, side]))  # by node, heaviest first
        node = edges[order, side]
        rank = np.arange(len(order)) - np.searchsorted(node, node)  # position within the node's edges
        keep[order[rank < k]] = True
    a, b, w = edges[keep, 0], edges[keep, 1], weights[keep]
    return sparse.coo_matrix((np.r_[w, w], (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()


def bisect(weights: sparse.csr_matrix) -> np.ndarray:
    """The normalized cut of a connected graph: a boolean ``(n,)`` side per node, each side >= MIN_SIDE of them."""
    n = weights.shape[0]
    degree = np.asarray(weights.sum(axis=1)).ravel()
    scale = sparse.diags(1.0 / np.sqrt(np.maximum(degree, 1e-12)))
    normalized = scale @ weights @ scale
    if n <= DENSE_UP_TO:
        _, vectors = np.linalg.eigh(normalized.toarray())
        fiedler = vectors[:, -2]
    else:  # the two largest of the normalized adjacency: the smallest of the normalized Laplacian
        start = np.sqrt(degree) + np.linspace(0.0, 1.0, n)  # fixed start vector: the same cut every run
        values, vectors = eigsh(normalized, k=2, which="LA", v0=start)
        fiedler = vectors[:, np.argsort(values)[0]]
    embedding = fiedler / np.sqrt(np.maximum(degree, 1e-12))
    order = np.lexsort((np.arange(n), embedding))
    return _best_sweep(weights, degree, order)


def _best_sweep(weights: sparse.csr_matrix, degree: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The split of ``order`` (nodes along the Fiedler vector) of least normalized cut among balanced ones."""
    n = len(order)
    position = np.empty(n, np.int64)
    position[order] = np.arange(n)
    coo = weights.tocoo()
    # An edge is cut by every split between its two nodes' positions: a difference array over split points.
    low, high = np.minimum(position[coo.row], position[coo.col]), np.maximum(position[coo.row], position[coo.col])
    change = np.zeros(n + 1)
    np.add.at(change, low + 1, coo.data / 2)  # each edge is stored twice
    np.add.at(change, high + 1, -coo.data / 2)
    cut = np.cumsum(change)[1:n]  # cut[s - 1]: the weight across the split after s nodes
    volume = np.cumsum(degree[order])[:-1]
    total = degree.sum()
    cost = cut / np.maximum(volume, 1e-12) + cut / np.maximum(total - volume, 1e-12)
    sizes = np.arange(1, n)
    lowest = max(1, int(np.ceil(MIN_SIDE * n)))
    cost[(sizes < lowest) | (sizes > n - lowest)] = np.inf
    split = int(np.argmin(cost)) + 1
    side = np.zeros(n, bool)
    side[order[split:]] = True
    return side


def _largest_first(parts) -> list[np.ndarray]:
    """Node sets, largest first, ties by their smallest node (the same order every run)."""
    return sorted(parts, key=lambda nodes: (-len(nodes), int(nodes.min())))


def leaves(weights: sparse.csr_matrix, leaf_size: int) -> list[np.ndarray]:
    """Node index sets of at most ``leaf_size`` nodes: connected parts, cut in two until small enough."""
    count, labels = connected_components(weights, directed=False)
    todo = [np.flatnonzero(labels == k) for k in range(count)]
    done: list[np.ndarray] = []
    while todo:
        nodes = todo.pop()
        if len(nodes) <= leaf_size:
            done.append(nodes)
            continue
        sub = weights[nodes][:, nodes]
        parts, labels = connected_components(sub, directed=False)
        if parts > 1:  # the kept edges can split what the full graph joined
            todo.extend(nodes[labels == k] for k in range(parts))
            continue
        side = bisect(sub)
        todo.extend([nodes[~side], nodes[side]])
    return _largest_first(done)


def absorb_fragments(weights: sparse.csr_matrix, parts: list[np.ndarray], smallest: int) -> list[np.ndarray]:
    """``parts`` with each one of fewer than ``smallest`` nodes joined to the part it has most edge weight into
    (a cut can strand a few photos whose links all crossed it; alone they would map to nothing)."""
    parts = _largest_first(parts)
    owner = np.full(weights.shape[0], -1)
    for k, nodes in enumerate(parts):
        owner[nodes] = k
    for k in range(len(parts) - 1, -1, -1):  # smallest first
        nodes = parts[k]
        if len(nodes) >= smallest:
            continue
        strength = np.bincount(owner[weights[nodes].indices], weights[nodes].data, minlength=len(parts))
        strength[k] = 0.0  # a part already joined to another owns no node any more: no strength either
        if strength.max() <= 0:
            continue  # a small connected part of its own: it stays a cluster
        target = int(np.argmax(strength))
        parts[target] = np.sort(np.r_[parts[target], nodes])
        owner[nodes] = target
        parts[k] = nodes[:0]
    return _largest_first(p for p in parts if len(p))


def with_overlap(weights: sparse.csr_matrix, leaf: np.ndarray, overlap: int) -> np.ndarray:
    """``leaf`` and up to ``overlap`` other nodes, grown ring by ring: the neighbours of most edge weight into the
    set so far first, then theirs (a walk's clusters touch through a few photos only). Sorted node indices."""
    inside = np.zeros(weights.shape[0], bool)
    inside[leaf] = True
    added = 0
    while added < overlap:
        strength = np.asarray(weights[np.flatnonzero(inside)].sum(axis=0)).ravel()
        strength[inside] = 0.0
        ring = np.flatnonzero(strength > 0)
        if len(ring) == 0:
            break
        ring = ring[np.lexsort((ring, -strength[ring]))][:overlap - added]
        inside[ring] = True
        added += len(ring)
    return np.flatnonzero(inside)


def partition(ids: np.ndarray, pairs: np.ndarray, weights: np.ndarray,
              options: ClusterOptions = ClusterOptions()) -> list[list[int]]:
    """The clusters of the view graph (``view_graph``): lists of image ids, largest leaf first, each with its
    overlap. Photos of no verified pair are in no cluster."""
    index = {int(image_id): k for k, image_id in enumerate(ids)}
    edges = np.array([[index[int(a)], index[int(b)]] for a, b in pairs], np.int64).reshape(-1, 2)
    graph = strongest_edges(len(ids), edges, weights, options.neighbours)
    linked = np.flatnonzero(np.asarray(graph.sum(axis=1)).ravel() > 0)
    sub = graph[linked][:, linked]
    # A cut leaves >= MIN_SIDE of a part on each side: smaller leaves are fragments it stranded.
    fragment = min(MIN_CLUSTER, int(np.ceil(MIN_SIDE * options.leaf_size)))
    parts = absorb_fragments(sub, leaves(sub, options.leaf_size), fragment)
    clusters = [with_overlap(sub, leaf, options.overlap) for leaf in parts]
    return [[int(ids[linked[k]]) for k in cluster] for cluster in clusters]
