"""COLMAP's database and masks: pycolmap import, feature masks, verified-match and keypoint counts,
why a photo stayed unregistered, the pair lists COLMAP matches."""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from damcap.common.atomic import write_json_atomic




def pair_inliers(db_path: Path, names: list[str]) -> dict[tuple[int, int], int]:
    """Verified inliers of every matched pair, by photo index (i < j)."""
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        index = {im.image_id: names.index(im.name) for im in db.read_all_images() if im.name in names}
        out: dict[tuple[int, int], int] = {}
        ids, counts = db.read_two_view_geometry_num_inliers()
        for pid, k in zip(ids, counts):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            if a in index and b in index:
                i, j = sorted((index[a], index[b]))
                out[(i, j)] = int(k)
        return out
    finally:
        db.close()


#: what an unregistered photo's reason advises when masks were given but features came from the whole photos
WHOLE_PHOTOS_HINT = "--mask-features always matches only the features inside the masks"


def unregistered_reasons(names: list[str], registered: set[str], keypoints: dict[str, int],
                         best_inliers: dict[str, int], other_models: dict[str, int], min_num_inliers: int,
                         features_masked: bool = False, masks_given: bool = False) -> dict[str, str]:
    """Why each photo outside the kept model has no camera, as one short sentence each.

    Args:
        names: all photo names.
        registered: names in the kept model.
        keypoints: name -> features kept (after masking).
        best_inliers: name -> most verified matches with any other photo.
        other_models: name -> size of the other (smaller) model it was registered in.
        min_num_inliers: verified matches a pair needs.
        features_masked: features were restricted to the object by masks, so the matches cannot
            lie on the background.
        masks_given: the user gave masks but the features came from the whole photos: the advice
            is to match features inside them (``--mask-features always``), not to give them.
    """
    out = {}
    for n in names:
        if n in registered:
            continue
        kp, inl = keypoints.get(n, 0), best_inliers.get(n, 0)
        if kp < 50:
            out[n] = f"too few features ({kp}); blurred, textureless, or masked out"
        elif inl < min_num_inliers:
            out[n] = f"no photo shares enough verified matches with it (best {inl} < {min_num_inliers}); too little overlap"
        elif n in other_models:
            out[n] = f"registered only in a separate model of {other_models[n]} photos that does not connect to the main one"
        elif features_masked:
            out[n] = (f"its pose could not be estimated (best pair {inl} verified matches, all on the object, but too few "
                      "of them on points the model had triangulated; more overlap with the registered photos helps)")
        else:
            out[n] = (f"its pose could not be estimated (best pair {inl} verified matches, but they do not fit the registered "
                      f"cameras; if the object turned in front of the background, {WHOLE_PHOTOS_HINT if masks_given else 'give --masks'})")
    return out


def import_pycolmap():
    """pycolmap, as :func:`damcap.common.native_stderr.load_pycolmap` loads it: after OpenImageIO
    and OpenCV, with damcap's signal handlers kept and COLMAP's log lines off the terminal unless
    ``damcap --verbose``."""
    from damcap.common.native_stderr import load_pycolmap

    return load_pycolmap()


def feature_mask(mask: np.ndarray, erode_fraction: float = 0.01, threshold: float = 0.5) -> np.ndarray:
    """Where features may be kept: the object mask, eroded by ``erode_fraction`` of the longer
    image side (at least 1 pixel), so that keypoints whose descriptors straddle the silhouette
    (and see the background) are dropped.

    Args:
        mask: (H, W) float in [0, 1], 1 = object.

    Returns:
        (H, W) uint8, 255 = keep features, 0 = drop (COLMAP's mask convention).
    """
    import cv2

    r = max(1, round(erode_fraction * max(mask.shape)))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.erode(np.where(mask > threshold, 255, 0).astype(np.uint8), kernel)


def write_colmap_masks(masks: dict[str, Path], out_dir: Path, erode_fraction: float = 0.01) -> None:
    """Feature masks (:func:`feature_mask`) in COLMAP's naming (``IMG_1.JPG`` -> ``IMG_1.JPG.png``)."""
    from damcap.common.exr import write_png

    from damcap.reconstruct.photos import read_mask

    out_dir.mkdir(parents=True, exist_ok=True)
    for name, path in masks.items():
        target = out_dir / f"{name}.png"
        if not target.exists():
            write_png(target, feature_mask(read_mask(path), erode_fraction))


def database_summary(db_path: Path, names: list[str]) -> tuple[dict[str, int], dict[str, int]]:
    """Per photo: kept features, and the most verified inliers with any other photo."""
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        images = {im.name: im.image_id for im in db.read_all_images()}
        id_to_name = {v: k for k, v in images.items()}
        keypoints = {n: db.num_keypoints_for_image(images[n]) if n in images else 0 for n in names}
        best: dict[str, int] = {n: 0 for n in names}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        for pid, k in zip(pair_ids, inliers):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            for i in (a, b):
                n = id_to_name.get(i)
                if n is not None:
                    best[n] = max(best[n], int(k))
        return keypoints, best
    finally:
        db.close()


def read_descriptors(db_path: Path, names: list[str]) -> list[np.ndarray]:
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        images = {im.name: im.image_id for im in db.read_all_images()}
        out = []
        for n in names:
            d = db.read_descriptors(images[n]) if n in images else None
            data = getattr(d, "data", d)
            out.append(np.asarray(data) if data is not None else np.zeros((0, 128), np.uint8))
        return out
    finally:
        db.close()


# ---- pair lists -------------------------------------------------------------------------
# COLMAP's pair list (``ImportedPairingOptions.match_list_path``) is "name1 name2" a line: each
# line is trimmed, cut at spaces, a line starting with '#' is a comment, and a name that is not
# in the database is skipped with an error in the log. A photo named "Photo 0001.jpg" would be
# read as "Photo" and silently never matched. So photo names never go into a pair list: while
# COLMAP matches, each image in the database carries an alias made of its image id.


def pair_list_aliases(names_by_id: dict[int, str]) -> dict[int, str]:
    """An alias per image id that COLMAP's pair list reads back intact, equal to no photo's name.

    The aliases are a prefix and the image id; the prefix grows until no photo name starts with
    it, so an alias never equals a name (the database keeps names unique while they are renamed).

    >>> pair_list_aliases({1: "Photo 0001.jpg", 2: "img.jpg"})
    {1: 'pair-1', 2: 'pair-2'}
    >>> pair_list_aliases({1: "pair-2", 2: "x"})
    {1: '_pair-1', 2: '_pair-2'}
    """
    prefix = "pair-"
    while any(name.startswith(prefix) for name in names_by_id.values()):
        prefix = "_" + prefix
    return {i: f"{prefix}{i}" for i in names_by_id}


def pair_list_text(pairs: list[tuple[str, str]]) -> str:
    """COLMAP's pair list for ``pairs`` of database image names, one "name1 name2" a line.

    Raises:
        ValueError: a name COLMAP would not read back as written (empty, with whitespace, or
            starting with '#').

    >>> pair_list_text([("pair-1", "pair-2")])
    'pair-1 pair-2\\n'
    """
    for pair in pairs:
        for name in pair:
            if not name or name.startswith("#") or any(c.isspace() for c in name):
                raise ValueError(f"COLMAP's pair list cannot hold the image name {name!r}: "
                                 "expected no whitespace and no leading '#'")
    return "".join(f"{a} {b}\n" for a, b in pairs)


def _aliases_path(db_path: Path) -> Path:
    return db_path.with_name(db_path.name + ".aliases.json")


def restore_image_names(db_path: Path) -> None:
    """Give the database's images back the photo names :func:`images_named_for_pair_lists` replaced
    (also after a run killed while matching); nothing to do when no alias record exists."""
    record = _aliases_path(db_path)
    if not record.exists():
        return
    if db_path.exists():
        name_of_alias = json.loads(record.read_text(encoding="utf-8"))
        pycolmap = import_pycolmap()
        db = pycolmap.Database.open(str(db_path))
        try:
            for im in db.read_all_images():
                if im.name in name_of_alias:
                    im.name = name_of_alias[im.name]
                    db.update_image(im)
        finally:
            db.close()
    record.unlink()


@contextmanager
def images_named_for_pair_lists(db_path: Path) -> Iterator[dict[str, str]]:
    """Within the block, every image in the database is named by its :func:`pair_list_aliases`
    alias; the photo names come back on leaving it (:func:`restore_image_names`).

    Yields:
        photo name -> alias, the names to write in a pair list (:func:`pair_list_text`).
    """
    pycolmap = import_pycolmap()
    restore_image_names(db_path)
    try:
        db = pycolmap.Database.open(str(db_path))
        try:
            images = db.read_all_images()
            aliases = pair_list_aliases({im.image_id: im.name for im in images})
            # the record is written before any image is renamed: a run killed in between is restored
            write_json_atomic(_aliases_path(db_path), {aliases[im.image_id]: im.name for im in images})
            alias_of_name = {im.name: aliases[im.image_id] for im in images}
            for im in images:
                im.name = aliases[im.image_id]
                db.update_image(im)
        finally:
            db.close()
        yield alias_of_name
    finally:
        restore_image_names(db_path)


def unmatched_pairs(db_path: Path, pairs: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """The pairs of photo names that have no match record in the database (COLMAP writes one, empty
    or not, for every pair it matched)."""
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        return [(a, b) for a, b in pairs if a not in ids or b not in ids or not db.exists_matches(ids[a], ids[b])]
    finally:
        db.close()
