"""What the COLMAP database says about photos that did not register."""

from __future__ import annotations

from damcap.reconstruct.colmap.database import WHOLE_PHOTOS_HINT, unregistered_reasons


def test_unregistered_reasons_each_branch():
    names = ["a.jpg", "b.jpg", "c.jpg", "d.jpg", "e.jpg"]
    reasons = unregistered_reasons(names, {"a.jpg"}, keypoints={"a.jpg": 900, "b.jpg": 10, "c.jpg": 900, "d.jpg": 900, "e.jpg": 900},
                                   best_inliers={"a.jpg": 200, "b.jpg": 0, "c.jpg": 3, "d.jpg": 100, "e.jpg": 100},
                                   other_models={"d.jpg": 4}, min_num_inliers=15)
    assert set(reasons) == {"b.jpg", "c.jpg", "d.jpg", "e.jpg"}
    assert "too few features (10)" in reasons["b.jpg"]
    assert "best 3 < 15" in reasons["c.jpg"]
    assert "separate model of 4 photos" in reasons["d.jpg"]
    assert "could not be estimated" in reasons["e.jpg"] and "--masks" in reasons["e.jpg"]
    masked = unregistered_reasons(names, {"a.jpg"}, keypoints={n: 900 for n in names}, best_inliers={n: 100 for n in names},
                                  other_models={}, min_num_inliers=15, features_masked=True)
    assert "all on the object" in masked["e.jpg"] and "--masks" not in masked["e.jpg"]  # no background to blame


def test_the_advice_for_an_unregistered_photo_follows_the_masks_given():
    """Without masks: give --masks. With masks whose features came from the whole photos: not
    'give --masks' (they were given) but matching features inside them."""
    names = ["a.jpg", "e.jpg"]
    args = dict(keypoints={n: 900 for n in names}, best_inliers={n: 100 for n in names}, other_models={}, min_num_inliers=15)
    assert "give --masks" in unregistered_reasons(names, {"a.jpg"}, **args)["e.jpg"]
    given = unregistered_reasons(names, {"a.jpg"}, **args, masks_given=True)["e.jpg"]
    assert "--masks" not in given.replace("--mask-features", "") and WHOLE_PHOTOS_HINT in given
