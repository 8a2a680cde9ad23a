"""Scoring a segmentation: Hungarian matching of materials, per-material DSSIM against the k-means baseline."""

from __future__ import annotations

import numpy as np

from damcap.appearance.segment.kmeans_baseline import kmeans_baseline
from damcap.appearance.segment.score import match_materials, segmentation_scores


def test_each_dam_reproduces_its_material(two_materials, segmented):
    _, train, test = two_materials
    same = segmentation_scores(segmented, train, train, same_view=True)
    novel = segmentation_scores(segmented, train, test, same_view=False)
    assert np.mean(list(same["estimated weights"].values())) < 0.03
    assert np.mean(list(novel["true weights"].values())) < 0.12
    # and better than the paper's k-means baseline on novel views
    km = kmeans_baseline(train, 2, steps=300)
    km_novel = segmentation_scores(km, train, test, same_view=False)
    assert np.mean(list(novel["true weights"].values())) < 0.9 * np.mean(list(km_novel["true weights"].values()))


def test_match_materials_hungarian():
    t = np.eye(3)[[0, 0, 1, 1, 2, 2]]
    p = np.eye(3)[[2, 2, 0, 0, 1, 1]]
    perm, iou = match_materials(p, t)
    assert perm.tolist() == [2, 0, 1] and iou == 1.0
