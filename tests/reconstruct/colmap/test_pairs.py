"""Image pairs for matching: exhaustive, ring, retrieval, VLAD similarity."""

from __future__ import annotations

import numpy as np

from damcap.reconstruct.colmap.pairs import exhaustive_pairs, retrieval_pairs, ring_pairs, vlad_similarity


def test_exhaustive_pairs_count():
    pairs = exhaustive_pairs(7)
    assert len(pairs) == 21 and len(set(pairs)) == 21 and all(i < j for i, j in pairs)


def test_ring_pairs_wrap_and_no_wrap():
    assert ring_pairs(6, 2) == [(0, 1), (0, 2), (0, 4), (0, 5), (1, 2), (1, 3), (1, 5), (2, 3), (2, 4), (3, 4), (3, 5), (4, 5)]
    assert ring_pairs(6, 2, loop=False) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4), (3, 5), (4, 5)]
    # overlap larger than the set: every pair once
    assert ring_pairs(4, 10) == exhaustive_pairs(4)


def test_retrieval_pairs_top_k():
    sim = np.array([[0, .9, .2, .1], [.9, 0, .3, .8], [.2, .3, 0, .7], [.1, .8, .7, 0]])
    assert retrieval_pairs(sim, 1) == [(0, 1), (1, 3), (2, 3)]  # row 3's best is 1
    assert retrieval_pairs(sim, 2) == [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)]


def test_vlad_similarity_finds_the_photos_that_share_features():
    rng = np.random.default_rng(0)
    scene_a = rng.integers(0, 255, (300, 128)).astype(np.float32)
    scene_b = rng.integers(0, 255, (300, 128)).astype(np.float32)

    def view(scene: np.ndarray) -> np.ndarray:  # the same features, a random subset, with noise
        pick = rng.choice(len(scene), 200, replace=False)
        return np.clip(scene[pick] + rng.normal(0, 8, (200, 128)), 0, 255)

    descs = [view(scene_a), view(scene_a), view(scene_b), view(scene_b), view(scene_a)]
    sim = vlad_similarity(descs, words=16, seed=0)
    assert sim.shape == (5, 5) and np.allclose(sim, sim.T) and np.allclose(np.diag(sim), 0)
    assert set(retrieval_pairs(sim, 1)) <= {(0, 1), (0, 4), (1, 4), (2, 3)}  # never across scenes
    assert sim[0, 1] > sim[0, 2] + 0.1 and sim[2, 3] > sim[1, 3] + 0.1
