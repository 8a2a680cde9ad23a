"""Camera registration with COLMAP (pycolmap, CPU): features, pairing, matching, incremental mapping.

Choices that make a 2-core CPU run practical (bench/reconstruct.md measures them):

- SIFT on images downscaled to ``max_image_size`` with a feature budget ``max_num_features``;
  keypoints come back in full-resolution coordinates, so cameras are those of the photos.
- The turntable trap (the background stands still in the image while the object turns) is
  handled without masks: matches that do not move between two photos are dropped
  (``filter_stationary_matches``). Masks may also restrict features to the object (``masks``
  argument; eroded so descriptors do not straddle the silhouette), which a turntable with a
  textured, moving background needs; when the camera moves around a fixed object the static
  background helps: on mold_gold_cape masked features register 95/119 photos, unmasked 119/119.
- Pairing: exhaustive for small sets; for longer ones the photos' file order as a ring
  (``sequential_overlap`` neighbours each side; the ring closes the loop of an orbit) plus, per
  photo, the ``retrieval_neighbours`` most similar photos by VLAD descriptors whose vocabulary
  is learned from the set's own features (no pretrained vocabulary tree to download), plus
  two-hop neighbours in the verified match graph (``transitive_neighbours``).
- Incremental mapping; the largest model is kept and every other photo is listed with a reason.
- The report says where the photos put the principal point (a bundle adjustment with it free,
  on a copy unless ``refine_principal_point``, and its 1-sigma from COLMAP's covariance), so a
  user sees how far the centred default is from what the photos support.

Resumable: each stage records a fingerprint of its inputs and options in ``work_dir/state.json``;
a finished stage with the same fingerprint is not redone (an interrupted extraction or matching
continues where COLMAP's database stops), and a finished registration is loaded from
``work_dir/model``.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Literal, Sequence

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.errors import DamcapError

from damcap.reconstruct.poses import Registration, registration_of_reconstruction

#: progress callback: (stage, done, total)
StageProgress = Callable[[str, int, int], None]
Pairing = Literal["auto", "exhaustive", "sequential", "retrieval"]
CameraModelName = Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]

#: photos per feature-extraction call (progress granularity)
EXTRACT_CHUNK = 8
#: image pairs per matching call (progress granularity)
MATCH_CHUNK = 150


@dataclass(frozen=True)
class SfmOptions:
    """Options of camera registration (``damcap reconstruct`` mirrors them)."""

    max_image_size: int = 1024
    """longest image side for feature extraction, pixels (photos are not modified; keypoints are
    rescaled to the photos' resolution)"""
    max_num_features: int = 4096
    """SIFT feature budget per photo (before masking)"""
    upsample_below: int = 800
    """SIFT starts one octave up (doubles the image) only when the longer side, after
    ``max_image_size``, is below this; large photos skip that costly octave"""
    pairing: Pairing = "auto"
    """'exhaustive' (all pairs), 'sequential' (file order as a ring), 'retrieval' (ring + most
    similar photos by a vocabulary learned from the set), 'auto' (exhaustive up to
    ``exhaustive_max_images`` photos, else retrieval)"""
    exhaustive_max_images: int = 40
    """'auto' matches all pairs up to this many photos"""
    sequential_overlap: int = 5
    """ring pairing: neighbours on each side in file-name order"""
    loop_closure: bool = True
    """ring pairing wraps around (the last photos of an orbit meet the first ones)"""
    retrieval_neighbours: int = 8
    """retrieval pairing: most similar photos matched per photo, besides the ring"""
    transitive_neighbours: int = 5
    """after the first matching round, each photo is also matched with this many of its
    neighbours' neighbours (strongest two-hop links in the verified match graph; 0 = off;
    not used with exhaustive pairing)"""
    vocabulary_words: int = 64
    """retrieval pairing: VLAD vocabulary size, learned from the set's own descriptors"""
    camera_model: CameraModelName = "SIMPLE_RADIAL"
    """COLMAP camera model fitted to the photos"""
    refine_principal_point: bool = False
    """after mapping, one more global bundle adjustment that also refines the principal point
    (instant-ngp's colmap2nerf does this; COLMAP and LLFF keep it at the image centre). It moves
    every rotation by about atan(offset / focal): on the fox photos the principal point sits
    ~15 px off centre (0.6 deg), on the cape ~8 px (0.24 deg); see bench/reconstruct.md"""
    single_camera: bool = True
    """photos of the same size share one camera (one lens, one zoom); False = one per photo"""
    min_num_inliers: int = 15
    """verified matches a pair needs to count"""
    filter_stationary_matches: bool = True
    """drop matches that do not move between two photos (a static background on a turntable)"""
    mask_erode: float = 0.01
    """masks are eroded by this fraction of the longer image side before they restrict features
    (descriptors at the silhouette see the background)"""
    num_threads: int = -1
    """CPU threads for COLMAP (-1 = all)"""
    seed: int = 0
    """COLMAP's random seed (RANSAC, mapping): same seed, same result"""


@dataclass
class PrincipalPointEstimate:
    """Where the photos put the principal point of their one shared camera.

    From a bundle adjustment with the principal point free (on a copy of the reconstruction when
    the registration keeps it at the centre) and that adjustment's covariance (COLMAP's
    ``BACovariance``) scaled by the residual variance. The standard deviation measures noise
    only: a camera model that does not fit the lens can move the point by more.
    """

    offset_px: list[float]
    """(dx, dy): principal point minus the image centre, photo pixels"""
    sd_px: list[float]
    """1-sigma of (dx, dy), photo pixels"""
    tilt_deg: float
    """atan(|offset| / focal): how far every camera turns when this point replaces the centre"""
    used: bool
    """the registration's cameras use this point (``refine_principal_point``); else the centre"""


@dataclass
class SfmReport:
    """What registration did, for the user and the bench."""

    photos: int
    registered: int
    points: int
    mean_reprojection_error_px: float
    pairs: int
    pairing: str
    seconds: dict[str, float]
    unregistered: dict[str, str]
    resumed: list[str]
    principal_point: dict[str, Any] | None = None
    """:class:`PrincipalPointEstimate` as a dict; None with several cameras or no covariance"""


# --------------------------------------------------------------------------------------------
# Pure helpers: pairs, vocabulary, reasons
# --------------------------------------------------------------------------------------------

def exhaustive_pairs(n: int) -> list[tuple[int, int]]:
    """All (i, j), i < j, of n photos.

    >>> exhaustive_pairs(3)
    [(0, 1), (0, 2), (1, 2)]
    """
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def ring_pairs(n: int, overlap: int, loop: bool = True) -> list[tuple[int, int]]:
    """Each photo with its ``overlap`` successors in file order (wrapping around when ``loop``).

    >>> ring_pairs(4, 1)
    [(0, 1), (0, 3), (1, 2), (2, 3)]
    """
    pairs = set()
    for i in range(n):
        for k in range(1, min(overlap, n - 1) + 1):
            if i + k >= n and not loop:
                break
            j = (i + k) % n
            pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def vlad_similarity(descriptors: list[np.ndarray], words: int = 64, sample_per_image: int = 150, seed: int = 0) -> np.ndarray:
    """Image similarity from VLAD global descriptors with a vocabulary learned from the set itself.

    RootSIFT descriptors (Arandjelovic & Zisserman 2012) are assigned to ``words`` k-means
    centres; the residuals summed per centre (VLAD, Jegou et al. 2010) are power-normalised,
    intra-normalised per centre (Arandjelovic & Zisserman 2013) and L2-normalised; similarity is
    the cosine. No pretrained vocabulary is needed. On the 119 mold_gold_cape photos the 8 most
    similar photos per photo contain 75% of each photo's 8 nearest views (bag of words: 36%).

    Args:
        descriptors: per photo (K_i, 128) SIFT descriptors (uint8 or float), K_i may be 0.
        words: vocabulary size.
        sample_per_image: descriptors per photo used to learn the vocabulary.
        seed: k-means seed.

    Returns:
        (N, N) float64 similarity in [-1, 1], 0 on the diagonal.
    """
    from scipy.cluster.vq import kmeans2

    rng = np.random.default_rng(seed)
    feats = []
    for d in descriptors:
        f = np.asarray(d, dtype=np.float32)
        feats.append(np.sqrt(f / np.maximum(f.sum(1, keepdims=True), 1e-12)))  # RootSIFT
    sample = np.concatenate([f[rng.choice(len(f), min(len(f), sample_per_image), replace=False)] for f in feats if len(f)])
    k = int(min(words, max(2, len(sample) // 8)))
    centres, _ = kmeans2(sample, k, iter=10, minit="points", seed=seed)
    vecs = np.zeros((len(feats), k * sample.shape[1]))
    for i, f in enumerate(feats):
        if not len(f):
            continue
        d2 = (f * f).sum(1, keepdims=True) - 2 * f @ centres.T + (centres * centres).sum(1)[None]
        a = np.argmin(d2, axis=1)
        v = np.zeros((k, f.shape[1]))
        np.add.at(v, a, f - centres[a])
        v = np.sign(v) * np.sqrt(np.abs(v))
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        vecs[i] = v.ravel() / max(np.linalg.norm(v), 1e-12)
    sim = vecs @ vecs.T
    np.fill_diagonal(sim, 0.0)
    return sim


def retrieval_pairs(similarity: np.ndarray, k: int) -> list[tuple[int, int]]:
    """For every photo, the ``k`` most similar others.

    >>> retrieval_pairs(np.array([[0, .9, .1], [.9, 0, .5], [.1, .5, 0]]), 1)
    [(0, 1), (1, 2)]
    """
    n = len(similarity)
    pairs = set()
    for i in range(n):
        order = [j for j in np.argsort(-similarity[i], kind="stable") if j != i][:k]
        pairs.update((min(i, int(j)), max(i, int(j))) for j in order)
    return sorted(pairs)


def transitive_pairs(n: int, inliers: dict[tuple[int, int], int], per_image: int, min_inliers: int = 15) -> list[tuple[int, int]]:
    """New pairs closing triangles in the verified match graph (vocabulary-free densification).

    For every photo i, the unmatched photos k reached through a verified neighbour j, ranked by
    the bottleneck min(inliers(i, j), inliers(j, k)); the best ``per_image`` are kept.

    Args:
        n: photos.
        inliers: (i, j) with i < j -> verified matches of every pair matched so far (0 if failed).
        per_image: new pairs per photo.
        min_inliers: links weaker than this are not followed.

    >>> transitive_pairs(4, {(0, 1): 100, (1, 2): 80, (2, 3): 50, (0, 3): 0}, 1)
    [(0, 2), (1, 3)]
    """
    adj: list[dict[int, int]] = [dict() for _ in range(n)]
    for (i, j), w in inliers.items():
        if w >= min_inliers:
            adj[i][j] = w
            adj[j][i] = w
    pairs = set()
    for i in range(n):
        best: dict[int, int] = {}
        for j, w_ij in adj[i].items():
            for k, w_jk in adj[j].items():
                if k == i or (min(i, k), max(i, k)) in inliers:
                    continue
                best[k] = max(best.get(k, 0), min(w_ij, w_jk))
        for k, _ in sorted(best.items(), key=lambda kv: (-kv[1], kv[0]))[:per_image]:
            pairs.add((min(i, k), max(i, k)))
    return sorted(pairs)


def _pair_inliers(db_path: Path, names: list[str]) -> dict[tuple[int, int], int]:
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


def unregistered_reasons(names: list[str], registered: set[str], keypoints: dict[str, int],
                         best_inliers: dict[str, int], other_models: dict[str, int], min_num_inliers: int) -> dict[str, str]:
    """Why each photo outside the kept model has no camera, as one short sentence each.

    Args:
        names: all photo names.
        registered: names in the kept model.
        keypoints: name -> features kept (after masking).
        best_inliers: name -> most verified matches with any other photo.
        other_models: name -> size of the other (smaller) model it was registered in.
        min_num_inliers: verified matches a pair needs.
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
        else:
            out[n] = f"its pose could not be estimated (best pair {inl} verified matches; the matches may be on moving background)"
    return out


def fingerprint(obj: Any) -> str:
    """Short stable hash of a JSON-able object (which inputs and options made a stage)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------------
# pycolmap glue
# --------------------------------------------------------------------------------------------

def import_pycolmap():
    """pycolmap, imported after OpenImageIO and OpenCV.

    pycolmap's wheel bundles its own libpng/zlib; when it is loaded first, OpenImageIO's and
    OpenCV's PNG writers crash later in the same process (``free(): invalid pointer``).
    """
    import cv2  # noqa: F401
    import OpenImageIO  # noqa: F401
    import pycolmap

    pycolmap.logging.minloglevel = 2  # warnings and below stay quiet; damcap reports progress itself
    return pycolmap


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


def _database_summary(db_path: Path, names: list[str]) -> tuple[dict[str, int], dict[str, int]]:
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


def _read_descriptors(db_path: Path, names: list[str]) -> list[np.ndarray]:
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


def _load_state(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return {}


class _Stages:
    """Fingerprints of finished stages in ``work_dir/state.json`` (what makes a run resumable)."""

    order = ("features", "matches", "mapping")

    def __init__(self, work_dir: Path) -> None:
        self.path = work_dir / "state.json"
        self.state = _load_state(self.path)

    def status(self, stage: str, fp: str) -> str:
        """'done', 'started' (same inputs, unfinished) or 'new'."""
        s = self.state.get(stage, {})
        if s.get("fingerprint") != fp:
            return "new"
        return "done" if s.get("done") else "started"

    def mark(self, stage: str, fp: str, done: bool) -> None:
        self.state[stage] = {"fingerprint": fp, "done": done}
        if not done:  # a stage that restarts invalidates everything after it
            for later in self.order[self.order.index(stage) + 1:]:
                self.state.pop(later, None)
        write_json_atomic(self.path, self.state)


def _fingerprints(photo_dir: Path, names: list[str], opts: SfmOptions, masks: dict[str, Path] | None) -> tuple[str, str, str]:
    """(features, matches, pairing) fingerprints: which inputs and options made each stage."""
    files = {nm: (photo_dir / nm).stat().st_size for nm in names}
    mask_files = {nm: str(p.resolve()) for nm, p in (masks or {}).items()}
    fp_features = fingerprint({"files": files, "masks": mask_files, "max_image_size": opts.max_image_size,
                               "max_num_features": opts.max_num_features, "camera_model": opts.camera_model,
                               "upsample_below": opts.upsample_below, "mask_erode": opts.mask_erode if masks else None,
                               "single_camera": opts.single_camera})
    pairing = opts.pairing
    if pairing == "auto":
        pairing = "exhaustive" if len(names) <= opts.exhaustive_max_images else "retrieval"
    pair_opts = {k: getattr(opts, k) for k in ("sequential_overlap", "loop_closure", "retrieval_neighbours",
                                               "vocabulary_words", "min_num_inliers", "seed", "transitive_neighbours",
                                               "filter_stationary_matches")}
    return fp_features, fingerprint([fp_features, pairing, pair_opts]), pairing


def _features_and_matches(photo_dir: Path, names: list[str], work_dir: Path, opts: SfmOptions, masks: dict[str, Path] | None,
                          progress: StageProgress, stages: "_Stages", seconds: dict[str, float], resumed: list[str],
                          wipe: tuple[Path, ...] = ()) -> tuple[Path, int, str]:
    """COLMAP features and verified matches in ``work_dir/database.db`` (stages resumed by fingerprint).

    Returns:
        database path, number of matched pairs, the pairing used.
    """
    from damcap.reconstruct.photos import image_size

    pycolmap = import_pycolmap()
    n = len(names)
    db_path = work_dir / "database.db"
    fp_features, fp_matches, pairing = _fingerprints(photo_dir, names, opts, masks)
    # ---- features ----------------------------------------------------------------------
    st = stages.status("features", fp_features)
    if st == "new":
        for p in (db_path, work_dir / "masks") + wipe:
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    if st != "done":
        stages.mark("features", fp_features, done=False)
        t0 = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = opts.camera_model
        if masks:
            write_colmap_masks(masks, work_dir / "masks", opts.mask_erode)
            reader.mask_path = str(work_dir / "masks")
        sizes = {image_size(photo_dir / nm) for nm in names}
        mode = pycolmap.CameraMode.SINGLE if opts.single_camera and len(sizes) == 1 else (
            pycolmap.CameraMode.AUTO if opts.single_camera else pycolmap.CameraMode.PER_IMAGE)
        pycolmap.Database.open(str(db_path)).close()  # import_images needs an existing database
        pycolmap.import_images(str(db_path), str(photo_dir), camera_mode=mode, image_names=names, options=reader)
        ext = pycolmap.FeatureExtractionOptions()
        ext.max_image_size = opts.max_image_size
        ext.num_threads = opts.num_threads
        ext.sift.max_num_features = opts.max_num_features
        longest = min(max(max(s) for s in sizes), opts.max_image_size)
        ext.sift.first_octave = -1 if longest < opts.upsample_below else 0
        for k in range(0, n, EXTRACT_CHUNK):
            progress("features", k, n)
            pycolmap.extract_features(str(db_path), str(photo_dir), image_names=names[k:k + EXTRACT_CHUNK], camera_mode=mode,
                                      reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        progress("features", n, n)
        seconds["features"] = time.perf_counter() - t0
        stages.mark("features", fp_features, done=True)
    else:
        resumed.append("features")

    # ---- pairs + matches ---------------------------------------------------------------
    st = stages.status("matches", fp_matches)
    if st == "new":
        db = pycolmap.Database.open(str(db_path))
        try:
            db.clear_matches()
            db.clear_two_view_geometries()
        finally:
            db.close()
    if st != "done":
        t0 = time.perf_counter()
        stages.mark("matches", fp_matches, done=False)
        if pairing == "exhaustive":
            pairs = exhaustive_pairs(n)
        else:
            pairs = ring_pairs(n, opts.sequential_overlap, opts.loop_closure)
            if pairing == "retrieval":
                progress("vocabulary", 0, 1)
                sim = vlad_similarity(_read_descriptors(db_path, names), opts.vocabulary_words, seed=opts.seed)
                pairs = sorted(set(pairs) | set(retrieval_pairs(sim, opts.retrieval_neighbours)))
                progress("vocabulary", 1, 1)
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = opts.num_threads
        verify = pycolmap.TwoViewGeometryOptions()
        verify.min_num_inliers = opts.min_num_inliers
        verify.filter_stationary_matches = opts.filter_stationary_matches
        verify.ransac.random_seed = opts.seed

        def match_pairs(stage: str, todo: list[tuple[int, int]]) -> None:
            for k in range(0, len(todo), MATCH_CHUNK):
                progress(stage, k, len(todo))
                lst = work_dir / "pairs.txt"
                lst.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in todo[k:k + MATCH_CHUNK]), encoding="utf-8")
                po = pycolmap.ImportedPairingOptions()
                po.match_list_path = str(lst)
                pycolmap.match_image_pairs(str(db_path), matching_options=match, pairing_options=po,
                                           verification_options=verify, device=pycolmap.Device.cpu)
            progress(stage, len(todo), len(todo))

        match_pairs("matching", pairs)
        if pairing != "exhaustive" and opts.transitive_neighbours > 0:
            extra = transitive_pairs(n, _pair_inliers(db_path, names), opts.transitive_neighbours, opts.min_num_inliers)
            match_pairs("matching (two-hop)", extra)
            pairs = sorted(set(pairs) | set(extra))
        seconds["matching"] = time.perf_counter() - t0
        write_json_atomic(work_dir / "matched_pairs.json", {"pairs": len(pairs)})
        stages.mark("matches", fp_matches, done=True)
        n_pairs = len(pairs)
    else:
        resumed.append("matches")
        saved = _load_state(work_dir / "matched_pairs.json").get("pairs")  # absent in older work folders
        n_pairs = int(saved) if saved is not None else len(_pair_inliers(db_path, names))

    return db_path, n_pairs, pairing


def register_photos(photo_dir: str | Path, names: list[str], work_dir: str | Path, opts: SfmOptions = SfmOptions(),
                    masks: dict[str, Path] | None = None, progress: StageProgress | None = None) -> tuple[Registration, SfmReport]:
    """Register a photo set with COLMAP; resume what a previous run in ``work_dir`` finished.

    Args:
        photo_dir: folder of the photos (read only).
        names: photo file names to register, sorted (their order is the ring order).
        work_dir: folder for the database, masks, model and state (created).
        opts: registration options.
        masks: photo name -> mask file (white = object) to restrict features to the object, or None.
        progress: called as (stage, done, total).

    Returns:
        registration: cameras (OpenGL axes) and sparse points of the largest model.
        report: counts, timings and the reason for every unregistered photo.

    Raises:
        DamcapError: fewer than 2 photos, or COLMAP registered none.
    """
    pycolmap = import_pycolmap()
    photo_dir, work_dir = Path(photo_dir), Path(work_dir)
    if len(names) < 2:
        raise DamcapError(f"{photo_dir}: registration needs at least 2 photos, got {len(names)}")
    work_dir.mkdir(parents=True, exist_ok=True)
    stages = _Stages(work_dir)
    report_path = work_dir / "registration.json"
    model_dir = work_dir / "model"
    progress = progress or (lambda stage, done, total: None)
    n = len(names)
    seconds: dict[str, float] = {}
    resumed: list[str] = []

    _, fp_matches, _ = _fingerprints(photo_dir, names, opts, masks)
    # refining the principal point is a later step of mapping (older mapping states stay valid)
    fp_mapping = fingerprint([fp_matches, opts.seed] + (["refine_principal_point"] if opts.refine_principal_point else []))

    if stages.status("mapping", fp_mapping) == "done" and model_dir.is_dir() and report_path.is_file():
        rec = pycolmap.Reconstruction(str(model_dir))
        rep = SfmReport(**json.loads(report_path.read_text(encoding="utf-8")))
        rep.resumed = ["features", "matches", "mapping"]
        if rep.principal_point is None and rec.num_cameras() == 1:  # a registration from before the estimate
            principal = adjust_principal_point(rec, pycolmap, apply=False)  # on a copy: the model stays as it was
            if principal is not None:
                rep.principal_point = asdict(replace(principal, used=opts.refine_principal_point))
                write_json_atomic(report_path, asdict(rep))
        reg = registration_of_reconstruction(rec, names, "sfm", str(model_dir))
        reg.unregistered = dict(rep.unregistered)
        reg.stats = asdict(rep)
        progress("registration (reused)", 1, 1)
        return reg, rep

    db_path, n_pairs, pairing = _features_and_matches(photo_dir, names, work_dir, opts, masks, progress, stages, seconds,
                                                      resumed, wipe=(model_dir, work_dir / "models", report_path))

    # ---- mapping -----------------------------------------------------------------------
    stages.mark("mapping", fp_mapping, done=False)
    t0 = time.perf_counter()
    pycolmap.set_random_seed(opts.seed)
    mopts = pycolmap.IncrementalPipelineOptions()
    mopts.num_threads = opts.num_threads
    mopts.random_seed = opts.seed
    mopts.min_num_matches = opts.min_num_inliers
    mopts.min_model_size = 3
    counter = {"k": 0}

    def next_image() -> None:
        counter["k"] += 1
        progress("mapping", min(counter["k"], n), n)

    models_dir = work_dir / "models"
    if models_dir.exists():
        shutil.rmtree(models_dir)
    models_dir.mkdir()
    progress("mapping", 0, n)
    recs = pycolmap.incremental_mapping(str(db_path), str(photo_dir), str(models_dir), options=mopts,
                                        next_image_callback=next_image)
    seconds["mapping"] = time.perf_counter() - t0
    keypoints, best_inliers = _database_summary(db_path, names)
    if not recs:
        reasons = unregistered_reasons(names, set(), keypoints, best_inliers, {}, opts.min_num_inliers)
        worst = sorted(reasons.items())[:3]
        raise DamcapError(
            f"{photo_dir}: COLMAP could not register the photos (no initial pair among {n} photos; e.g. "
            + "; ".join(f"{k}: {v}" for k, v in worst)
            + "). Photos need overlap and texture; try --masks, more photos, or --poses"
        )
    ranked = sorted(recs.values(), key=lambda r: r.num_reg_images(), reverse=True)
    rec = ranked[0]
    progress("principal point", 0, 1)
    t0 = time.perf_counter()
    principal = adjust_principal_point(rec, pycolmap, apply=opts.refine_principal_point)
    seconds["principal_point"] = time.perf_counter() - t0
    progress("principal point", 1, 1)
    others: dict[str, int] = {}
    for r in ranked[1:]:
        for iid in r.reg_image_ids():
            others.setdefault(r.image(iid).name, r.num_reg_images())
    if model_dir.exists():
        shutil.rmtree(model_dir)
    model_dir.mkdir()
    rec.write_binary(str(model_dir))
    reg = registration_of_reconstruction(rec, names, "sfm", str(model_dir))
    registered = {p.name for p in reg.photos}
    reg.unregistered = unregistered_reasons(names, registered, keypoints, best_inliers, others, opts.min_num_inliers)
    rep = SfmReport(photos=n, registered=len(registered), points=int(rec.num_points3D()),
                    mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()), pairs=n_pairs,
                    pairing=pairing, seconds={k: round(v, 2) for k, v in seconds.items()},
                    unregistered=reg.unregistered, resumed=resumed,
                    principal_point=asdict(principal) if principal is not None else None)
    write_json_atomic(report_path, asdict(rep))
    stages.mark("mapping", fp_mapping, done=True)
    reg.stats = asdict(rep)
    progress("mapping", n, n)
    return reg, rep


def residual_variance(final_cost: float, residuals: int, parameters: int) -> float:
    """Variance of one residual after a least-squares fit: ``2 cost / (residuals - parameters)``.

    Args:
        final_cost: Ceres' cost, half the sum of squared residuals (px^2).
        residuals: number of scalar residuals.
        parameters: number of free parameters (effective, after the gauge is fixed).

    Returns:
        sigma^2 in px^2 (the cost's own mean when there are no spare residuals).

    >>> residual_variance(50.0, 110, 10)
    1.0
    """
    return 2.0 * final_cost / max(residuals - parameters, 1)


def principal_point_tilt_deg(offset_px: Sequence[float], focal_px: float) -> float:
    """How far a camera turns when its principal point moves by ``offset_px``: atan(|offset| / f).

    >>> round(principal_point_tilt_deg([3.0, 4.0], 5.0 / math.tan(math.radians(1.0))), 6)
    1.0
    """
    return math.degrees(math.atan2(math.hypot(*offset_px), focal_px))


def offset_in_sigmas(offset_px: Sequence[float], sd_px: Sequence[float]) -> float:
    """How many standard deviations a principal point lies from the image centre:
    hypot(dx / sx, dy / sy).

    >>> offset_in_sigmas([3.0, -4.0], [1.0, 1.0])
    5.0
    """
    return math.hypot(*(d / max(sd, 1e-9) for d, sd in zip(offset_px, sd_px)))


def adjust_principal_point(rec: Any, pycolmap: Any, apply: bool) -> PrincipalPointEstimate | None:
    """One global bundle adjustment with the principal point free (colmap2nerf's last step),
    and where it puts the point.

    Args:
        rec: a ``pycolmap.Reconstruction``.
        pycolmap: the module.
        apply: adjust ``rec`` itself (its cameras then use the point); else a copy, and ``rec``
            is unchanged.

    Returns:
        The estimate, or None when the photos use several cameras or COLMAP cannot estimate the
        covariance (the adjustment is made all the same).
    """
    if rec.num_cameras() != 1 and not apply:
        return None
    work = rec if apply else pycolmap.Reconstruction(rec)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_principal_point = True
    ba.print_summary = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in work.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba, config, work)
    summary = adjuster.solve().ceres_summary
    if work.num_cameras() != 1:
        return None
    camera = work.cameras[next(iter(work.cameras))]
    cov = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), work, adjuster)
    block = cov.get_other_params_cov(camera.params) if cov is not None else None
    if block is None or block.shape != (len(camera.params), len(camera.params)):
        return None
    var = residual_variance(summary.final_cost, summary.num_residuals_reduced, summary.num_effective_parameters_reduced)
    sd = np.sqrt(np.maximum(np.diag(block)[list(camera.principal_point_idxs())], 0.0) * var)
    offset = [camera.principal_point_x - camera.width / 2, camera.principal_point_y - camera.height / 2]
    return PrincipalPointEstimate(offset_px=[round(float(v), 2) for v in offset], sd_px=[round(float(v), 3) for v in sd],
                                  tilt_deg=round(principal_point_tilt_deg(offset, camera.mean_focal_length()), 3), used=apply)


def triangulate_known(photo_dir: str | Path, registration: Registration, work_dir: str | Path, opts: SfmOptions = SfmOptions(),
                      masks: dict[str, Path] | None = None, progress: StageProgress | None = None) -> Registration:
    """Sparse points for known cameras (COLMAP's point triangulator; cameras held fixed).

    Features and matches are made as for registration (same options, same resumable stages),
    then every track is triangulated with the given poses and intrinsics.

    Args:
        photo_dir: folder of the photos.
        registration: known cameras (OpenGL axes, any distortion of :class:`PhotoCamera`).
        work_dir: work folder (database, triangulated model).
        opts: feature and matching options.
        masks: photo name -> mask to restrict features, or None.
        progress: called as (stage, done, total).

    Returns:
        the same registration with ``points_world`` / ``points_seen_from`` filled in.
    """
    from damcap.reconstruct.poses import colmap_of_world_from_cam

    pycolmap = import_pycolmap()
    photo_dir, work_dir = Path(photo_dir), Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    progress = progress or (lambda stage, done, total: None)
    names = [p.name for p in registration.photos]
    seconds: dict[str, float] = {}
    opts = replace(opts, single_camera=False)  # one database camera per photo, set to its known intrinsics below
    db_path, _, _ = _features_and_matches(photo_dir, names, work_dir, opts, masks, progress, _Stages(work_dir), seconds, [])
    progress("triangulation", 0, 1)
    rec = pycolmap.Reconstruction()
    db = pycolmap.Database.open(str(db_path))
    try:
        images = {im.name: im for im in db.read_all_images()}
        for p in registration.photos:
            c, im = p.camera, images[p.name]
            cam = pycolmap.Camera.create_from_model_name(im.camera_id, "FULL_OPENCV", c.fx, c.width, c.height)
            cam.params = [c.fx, c.fy, c.cx, c.cy, *c.distortion]
            db.update_camera(cam)
            rec.add_camera_with_trivial_rig(cam)
            img = pycolmap.Image(name=p.name, camera_id=im.camera_id, image_id=im.image_id)
            rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(colmap_of_world_from_cam(p.world_from_cam)))
    finally:
        db.close()
    out_dir = work_dir / "triangulated"
    out_dir.mkdir(exist_ok=True)
    mopts = pycolmap.IncrementalPipelineOptions()
    mopts.num_threads = opts.num_threads
    mopts.random_seed = opts.seed
    rec = pycolmap.triangulate_points(rec, str(db_path), str(photo_dir), str(out_dir), clear_points=True, options=mopts,
                                      refine_intrinsics=False)
    index = {p.name: k for k, p in enumerate(registration.photos)}
    pts, seen = [], []
    for _, p3d in rec.points3D.items():
        el = p3d.track.elements[0]
        pts.append(p3d.xyz)
        seen.append(index[rec.image(el.image_id).name])
    progress("triangulation", 1, 1)
    registration.points_world = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    registration.points_seen_from = np.asarray(seen, dtype=np.int64)
    registration.stats = {**registration.stats, "triangulated_points": len(pts), **{f"{k}_s": round(v, 2) for k, v in seconds.items()}}
    return registration
