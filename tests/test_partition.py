"""The view graph's clusters (sekd_sfm.stages.partition): cut where the links are weak, every linked photo in
a cluster, neighbours sharing photos, the same clusters every time."""
from __future__ import annotations

import numpy as np

from sekd_sfm.stages.partition import (
    ClusterOptions,
    absorb_fragments,
    leaves,
    partition,
    strongest_edges,
)


def _walk(n: int, reach: int = 4, first_id: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A walk of ``n`` photos: each linked to the next ``reach`` ones, fewer inliers the farther apart."""
    ids = np.arange(first_id, first_id + n)
    pairs = np.array([(ids[i], ids[j]) for i in range(n) for j in range(i + 1, min(n, i + reach + 1))])
    weights = np.array([400.0 / (b - a) for a, b in pairs])
    return ids, pairs, weights


def test_a_walk_is_cut_into_overlapping_stretches_the_same_way_every_time():
    ids, pairs, weights = _walk(300)
    clusters = partition(ids, pairs, weights, ClusterOptions(leaf_size=100, overlap=10))
    assert clusters == partition(ids, pairs, weights, ClusterOptions(leaf_size=100, overlap=10))
    assert len(clusters) >= 3 and set().union(*map(set, clusters)) == set(ids.tolist())
    for cluster in clusters:
        assert len(cluster) <= 110
        # A stretch of the walk: consecutive photos, the overlap included (the cut falls between photos).
        assert max(cluster) - min(cluster) + 1 == len(cluster)
    # Each cluster shares photos with another: the merge has cameras to align by.
    for k, cluster in enumerate(clusters):
        assert any(len(set(cluster) & set(other)) >= 10 for j, other in enumerate(clusters) if j != k)


def test_separate_places_are_separate_clusters_and_unlinked_photos_none():
    a, b = _walk(40), _walk(30, first_id=100)
    ids = np.r_[a[0], b[0], [500]]  # photo 500: no verified pair
    clusters = partition(ids, np.r_[a[1], b[1]], np.r_[a[2], b[2]], ClusterOptions(leaf_size=125, overlap=50))
    assert [sorted(c) for c in clusters] == [list(range(1, 41)), list(range(100, 130))]


def test_each_photo_keeps_its_strongest_links():
    _, pairs, weights = _walk(10, reach=9)
    graph = strongest_edges(10, pairs - 1, weights, k=2).toarray()
    assert np.allclose(graph, graph.T)
    # Photo 0 keeps its two nearest; photo 9 keeps 8 and 7; middle ones keep their two nearest too.
    assert set(np.flatnonzero(graph[0])) == {1, 2} and set(np.flatnonzero(graph[9])) == {7, 8}
    assert (graph > 0).sum(axis=1).max() <= 4


def test_stranded_photos_join_the_cluster_they_are_linked_to():
    _, pairs, weights = _walk(60)
    graph = strongest_edges(60, pairs - 1, weights, k=20)
    parts = [np.arange(0, 28), np.arange(28, 30), np.arange(30, 60)]
    joined = absorb_fragments(graph, parts, smallest=10)
    assert len(joined) == 2 and sorted(np.concatenate(joined).tolist()) == list(range(60))
    assert {28, 29} <= set(joined[0].tolist()) or {28, 29} <= set(joined[1].tolist())
    assert all(len(leaf) <= 40 for leaf in leaves(graph, 40))
