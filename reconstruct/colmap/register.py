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
  on a copy unless it is used (``principal_point``), and its 1-sigma from COLMAP's covariance), so a
  user sees how far the centred default is from what the photos support.

Resumable: each stage records a fingerprint of its inputs and options in ``work_dir/state.json``;
a finished stage with the same fingerprint is not redone (an interrupted extraction or matching
continues where COLMAP's database stops), and a finished registration is loaded from
``work_dir/model``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from damcap.common.atomic import write_json_atomic
from damcap.common.errors import DamcapError
from damcap.common.validate import COUNT, MAX_IMAGE_SIDE, SEED, in_range

from damcap.reconstruct.poses import Registration
from damcap.reconstruct.colmap.model import image_observations, registration_of_reconstruction
from damcap.reconstruct.undistort import colmap_camera
from damcap.reconstruct.colmap.database import (database_summary, images_named_for_pair_lists, import_pycolmap, pair_inliers,
                                                pair_list_text, read_descriptors, restore_image_names, unmatched_pairs,
                                                unregistered_reasons, write_colmap_masks)
from damcap.reconstruct.colmap.pairs import exhaustive_pairs, retrieval_pairs, ring_pairs, transitive_pairs, vlad_similarity
from damcap.reconstruct.colmap.principal_point import adjust_principal_point, photos_support_offset


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
    """Options of camera registration (``damcap reconstruct``'s "Registration" options; the
    fields marked ``cli_exclude`` are the library's and the bench's)."""

    max_image_size: int = field(default=1024, metadata=in_range(1, MAX_IMAGE_SIDE))
    """longest image side for feature extraction, pixels (photos are not modified; keypoints are
    rescaled to the photos' resolution)"""
    max_num_features: int = field(default=4096, metadata=COUNT)
    """SIFT feature budget per photo (before masking)"""
    upsample_below: int = field(default=800, metadata=in_range(0, MAX_IMAGE_SIDE, cli_panel="advanced"))
    """SIFT starts one octave up (doubles the image) only when the longer side, after
    ``max_image_size``, is below this; large photos skip that costly octave"""
    retry_upsampled_below: float = field(default=0.95, metadata=in_range(0, 1, cli_panel="advanced"))
    """when the octave was skipped and no more than this fraction of the photos register, features
    are extracted again with it and the registration with more photos is kept (0 = never). The
    octave costs 2.7x the time on the 119 cape photos (296 s against 111 s, all registered either
    way) but decides sparse sets: every 2nd of the first 60 cape photos register 2 of 30 without
    it, 15 of 30 with it (plain pycolmap: 16)"""
    pairing: Pairing = "auto"
    """which photo pairs are matched: 'exhaustive' (all pairs), 'sequential' (file order as a
    ring), 'retrieval' (ring + most similar photos by a vocabulary learned from the set), 'auto'
    (exhaustive up to
    ``exhaustive_max_images`` photos, else retrieval)"""
    exhaustive_max_images: int = field(default=40, metadata={"cli_exclude": True})
    """'auto' matches all pairs up to this many photos"""
    sequential_overlap: int = field(default=5, metadata={**COUNT, "cli_panel": "advanced"})
    """ring pairing: neighbours on each side in file-name order"""
    loop_closure: bool = field(default=True, metadata={"cli_exclude": True})
    """ring pairing wraps around (the last photos of an orbit meet the first ones)"""
    retrieval_neighbours: int = field(default=8, metadata={**COUNT, "cli_panel": "advanced"})
    """retrieval pairing: most similar photos matched per photo, besides the ring"""
    transitive_neighbours: int = field(default=5, metadata={"cli_exclude": True})
    """after the first matching round, each photo is also matched with this many of its
    neighbours' neighbours (strongest two-hop links in the verified match graph; 0 = off;
    not used with exhaustive pairing)"""
    vocabulary_words: int = field(default=64, metadata={"cli_exclude": True})
    """retrieval pairing: VLAD vocabulary size, learned from the set's own descriptors"""
    camera_model: CameraModelName = "SIMPLE_RADIAL"
    """COLMAP camera model fitted to the photos"""
    principal_point: Literal["auto", "refine", "centre"] = "auto"
    """where the principal point comes from. After mapping, one more global bundle adjustment
    with the principal point free tells where the photos put it; 'refine' uses it (instant-ngp's colmap2nerf does), 'centre' keeps the image
    centre (COLMAP's and LLFF's convention), 'auto' uses it where the photos support it
    (:func:`~damcap.reconstruct.colmap.principal_point.photos_support_offset`). It turns every
    camera by about atan(offset / focal): Strecha's ground truth sits (-7.4, -8.35) px off
    (0.46 deg); see docs/registration.md"""
    single_camera: bool = field(default=True, metadata={"cli_flag": "--single-camera/--camera-per-photo"})
    """photos of the same size share one camera (one lens, one zoom); False = one per photo"""
    min_num_inliers: int = field(default=15, metadata={"cli_exclude": True})
    """verified matches a pair needs to count"""
    filter_stationary_matches: bool = field(default=True, metadata={"cli_exclude": True})
    """drop matches that do not move between two photos (a static background on a turntable)"""
    sift_peak_threshold: float = field(default=0.02 / 3, metadata={"cli_exclude": True})
    """SIFT's contrast threshold on the difference of Gaussians (COLMAP's default 0.02 / 3)"""
    low_contrast_peak_threshold: float | None = field(default=None, metadata={"cli_exclude": True})
    """when set, a few photos are probed first (:func:`peak_threshold_for`): where the subject
    offers few features, the set is extracted at this lower threshold instead (features inside
    masks: :data:`MASKED_PEAK_THRESHOLD`)"""
    mask_erode: float = field(default=0.01, metadata={"cli_exclude": True})
    """masks are eroded by this fraction of the longer image side before they restrict features
    (descriptors at the silhouette see the background)"""
    num_threads: int = field(default=-1, metadata={"cli_panel": "advanced", "cli_flag": "--threads", **in_range(-1, 4096)})
    """CPU threads for COLMAP (-1 = all)"""
    seed: int = field(default=0, metadata=SEED)
    """COLMAP's random seed (RANSAC, mapping): same seed, same result"""


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
    features: str = "first octave as set"
    """'skipped first octave', 'upsampled first octave' or 'upsampled first octave (retry)'"""
    retry: dict[str, Any] | None = None
    """the other pass when registration was retried with upsampled features: its registered count
    (or its error) and which pass was kept"""
    sift_peak_threshold: float | None = None
    """SIFT's contrast threshold the features were extracted at (None: from before it was recorded)"""


def fingerprint(obj: Any) -> str:
    """Short stable hash of a JSON-able object (which inputs and options made a stage)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


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


def _fingerprints(photo_dir: Path, names: list[str], opts: SfmOptions, masks: dict[str, Path] | None,
                  content: dict[str, str] | None = None) -> tuple[str, str, str]:
    """(features, matches, pairing) fingerprints: which inputs and options made each stage.

    ``content`` identifies each image (e.g. a digest of a registration proxy); without it, the
    file sizes do."""
    files = {nm: content[nm] for nm in names} if content is not None else {nm: (photo_dir / nm).stat().st_size for nm in names}
    mask_files = {nm: str(p.resolve()) for nm, p in (masks or {}).items()}
    fp_features = fingerprint({"files": files, "masks": mask_files, "max_image_size": opts.max_image_size,
                               "max_num_features": opts.max_num_features, "camera_model": opts.camera_model,
                               "upsample_below": opts.upsample_below, "mask_erode": opts.mask_erode if masks else None,
                               "single_camera": opts.single_camera, "sift_peak_threshold": opts.sift_peak_threshold,
                               "low_contrast_peak_threshold": opts.low_contrast_peak_threshold})
    pairing = opts.pairing
    if pairing == "auto":
        pairing = "exhaustive" if len(names) <= opts.exhaustive_max_images else "retrieval"
    pair_opts = {k: getattr(opts, k) for k in ("sequential_overlap", "loop_closure", "retrieval_neighbours",
                                               "vocabulary_words", "min_num_inliers", "seed", "transitive_neighbours",
                                               "filter_stationary_matches")}
    return fp_features, fingerprint([fp_features, pairing, pair_opts]), pairing


def _features_and_matches(photo_dir: Path, names: list[str], work_dir: Path, opts: SfmOptions, masks: dict[str, Path] | None,
                          progress: StageProgress, stages: "_Stages", seconds: dict[str, float], resumed: list[str],
                          wipe: tuple[Path, ...] = (), content: dict[str, str] | None = None) -> tuple[Path, int, str]:
    """COLMAP features and verified matches in ``work_dir/database.db`` (stages resumed by fingerprint).

    Returns:
        database path, number of matched pairs, the pairing used.
    """
    from damcap.reconstruct.photos import image_size

    pycolmap = import_pycolmap()
    n = len(names)
    db_path = work_dir / "database.db"
    fp_features, fp_matches, pairing = _fingerprints(photo_dir, names, opts, masks, content)
    restore_image_names(db_path)  # a run killed while matching left the images under their pair-list aliases
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
        ext.sift.first_octave = 0 if octave_skipped(sizes, opts) else -1
        ext.sift.peak_threshold = opts.sift_peak_threshold
        probed: dict[str, tuple[Any, Any]] = {}
        if opts.low_contrast_peak_threshold is not None:
            ext.sift.peak_threshold, probed = _probed_peak_threshold(photo_dir, names, work_dir / "probe.db", mode, reader, ext, opts)
        stages.state["sift_peak_threshold"] = float(ext.sift.peak_threshold)
        _write_features(db_path, probed)  # the probe's photos, extracted as the set would extract them
        todo = [nm for nm in names if nm not in probed]
        for k in range(0, len(todo), EXTRACT_CHUNK):
            progress("features", len(probed) + k, n)
            pycolmap.extract_features(str(db_path), str(photo_dir), image_names=todo[k:k + EXTRACT_CHUNK], camera_mode=mode,
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
                sim = vlad_similarity(read_descriptors(db_path, names), opts.vocabulary_words, seed=opts.seed)
                pairs = sorted(set(pairs) | set(retrieval_pairs(sim, opts.retrieval_neighbours)))
                progress("vocabulary", 1, 1)
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = opts.num_threads
        verify = pycolmap.TwoViewGeometryOptions()
        verify.min_num_inliers = opts.min_num_inliers
        verify.filter_stationary_matches = opts.filter_stationary_matches
        verify.ransac.random_seed = opts.seed

        def match_pairs(stage: str, todo: list[tuple[int, int]]) -> None:
            with images_named_for_pair_lists(db_path) as alias:  # photo names may hold spaces; aliases do not
                for k in range(0, len(todo), MATCH_CHUNK):
                    progress(stage, k, len(todo))
                    lst = work_dir / "pairs.txt"
                    chunk = [(alias[names[i]], alias[names[j]]) for i, j in todo[k:k + MATCH_CHUNK]]
                    lst.write_text(pair_list_text(chunk), encoding="utf-8")
                    po = pycolmap.ImportedPairingOptions()
                    po.match_list_path = str(lst)
                    pycolmap.match_image_pairs(str(db_path), matching_options=match, pairing_options=po,
                                               verification_options=verify, device=pycolmap.Device.cpu)
            missed = unmatched_pairs(db_path, [(names[i], names[j]) for i, j in todo])
            if missed:
                raise DamcapError(f"{db_path}: COLMAP matched {len(todo) - len(missed)} of the {len(todo)} photo pairs it was given; "
                                  f"not e.g. {missed[0][0]!r} with {missed[0][1]!r} (see COLMAP's log above)")
            progress(stage, len(todo), len(todo))

        match_pairs("matching", pairs)
        if pairing != "exhaustive" and opts.transitive_neighbours > 0:
            extra = transitive_pairs(n, pair_inliers(db_path, names), opts.transitive_neighbours, opts.min_num_inliers)
            match_pairs("matching (two-hop)", extra)
            pairs = sorted(set(pairs) | set(extra))
        seconds["matching"] = time.perf_counter() - t0
        write_json_atomic(work_dir / "matched_pairs.json", {"pairs": len(pairs)})
        stages.mark("matches", fp_matches, done=True)
        n_pairs = len(pairs)
    else:
        resumed.append("matches")
        saved = _load_state(work_dir / "matched_pairs.json").get("pairs")  # absent in older work folders
        n_pairs = int(saved) if saved is not None else len(pair_inliers(db_path, names))

    return db_path, n_pairs, pairing


#: :func:`peak_threshold_for`: the lower threshold is used when the probed photos keep fewer than
#: this fraction of their feature budget at the default one
LOW_CONTRAST_BUDGET_FRACTION = 0.5


#: photos (spread over the set) whose features decide the contrast threshold
PEAK_PROBE_PHOTOS = 4


def peak_threshold_for(median_features: float, budget: int, default: float, low: float) -> float:
    """SIFT's contrast threshold for a photo set, from the median feature count of a few photos
    extracted at ``default``: ``low`` when that is under :data:`LOW_CONTRAST_BUDGET_FRACTION` of
    the budget (the subject offers few features; weaker ones add points), else ``default``. Where
    the budget binds, weaker features would only replace finer ones: COLMAP fills the budget from
    the coarsest scales down. Measured (bench/registration_gt.md, docs/registration.md): the
    rendered turntable's object keeps 650 of 9614 at the default, and 0.003 takes its median
    rotation error from 0.104 to 0.075 deg; every 2nd of the first 60 cape photos keep about 8800
    of 9780 inside the masks (4 probed), and 0.003 took theirs from 0.195 to 0.415 deg.

    >>> peak_threshold_for(650, 9614, 0.0067, 0.003), peak_threshold_for(8097, 8670, 0.0067, 0.003)
    (0.003, 0.0067)
    """
    return low if median_features < LOW_CONTRAST_BUDGET_FRACTION * budget else default


def _probed_peak_threshold(photo_dir: Path, names: list[str], probe_db: Path, mode: Any, reader: Any, ext: Any,
                           opts: SfmOptions) -> tuple[float, dict[str, tuple[Any, Any]]]:
    """:func:`peak_threshold_for` on :data:`PEAK_PROBE_PHOTOS` photos spread over ``names``,
    extracted as the set will be (``reader``, ``ext``) into a scratch database.

    Returns:
        the threshold, and when it is the one the probe used, the probed photos' (keypoints,
        descriptors) by name, so that the set's extraction need not repeat them (else empty).
    """
    pycolmap = import_pycolmap()
    probe = [names[round(i)] for i in np.linspace(0, len(names) - 1, min(PEAK_PROBE_PHOTOS, len(names)))]
    probe_db.unlink(missing_ok=True)
    pycolmap.Database.open(str(probe_db)).close()
    pycolmap.import_images(str(probe_db), str(photo_dir), camera_mode=mode, image_names=probe, options=reader)
    pycolmap.extract_features(str(probe_db), str(photo_dir), image_names=probe, camera_mode=mode, reader_options=reader,
                              extraction_options=ext, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(str(probe_db))
    try:
        images = db.read_all_images()
        counts = [db.num_keypoints_for_image(im.image_id) for im in images]
        low = opts.low_contrast_peak_threshold
        assert low is not None
        threshold = peak_threshold_for(float(np.median(counts)) if counts else 0.0, opts.max_num_features, ext.sift.peak_threshold, low)
        features = ({im.name: (db.read_keypoints(im.image_id), db.read_descriptors(im.image_id)) for im in images}
                    if threshold == ext.sift.peak_threshold else {})
    finally:
        db.close()
    probe_db.unlink(missing_ok=True)
    return threshold, features


def _write_features(db_path: Path, features: dict[str, tuple[Any, Any]]) -> None:
    """Store (keypoints, descriptors) of images already imported into ``db_path``, by name, where
    the database has none yet (a resumed extraction may have stored them)."""
    if not features:
        return
    db = import_pycolmap().Database.open(str(db_path))
    try:
        for name, (keypoints, descriptors) in features.items():
            image_id = db.read_image_with_name(name).image_id
            if not db.exists_keypoints(image_id):
                db.write_keypoints(image_id, keypoints)
            if not db.exists_descriptors(image_id):
                db.write_descriptors(image_id, descriptors)
    finally:
        db.close()


def octave_skipped(sizes: set[tuple[int, int]], opts: SfmOptions) -> bool:
    """Whether feature extraction skips SIFT's upsampled first octave for photos of ``sizes``
    ((width, height) pairs): their longer side, capped at ``max_image_size``, reaches ``upsample_below``.

    >>> octave_skipped({(912, 912)}, SfmOptions()), octave_skipped({(640, 480)}, SfmOptions())
    (True, False)
    """
    longest = min(max(max(s) for s in sizes), opts.max_image_size)
    return not longest < opts.upsample_below


def wants_upsampled_retry(registered: int, photos: int, skipped: bool, retry_below: float) -> bool:
    """Whether to register again with the upsampled first octave: it was skipped and no more than
    ``retry_below`` of the photos registered (38 of 40 is 95 %: retried at 0.95).

    >>> wants_upsampled_retry(2, 30, True, 0.95), wants_upsampled_retry(38, 40, True, 0.95), wants_upsampled_retry(119, 119, True, 0.95)
    (True, True, False)
    """
    return skipped and retry_below > 0 and registered <= retry_below * photos + 1e-9


#: masked features: the SIFT budget grows by at most this factor (see :func:`masked_options`)
MASKED_BUDGET_MAX_FACTOR = 4


#: masked features: SIFT's contrast threshold where the object offers few features
#: (:func:`peak_threshold_for`; COLMAP's default 0.0067): weaker ones make more points. The rendered turntable
#: (36 photos of 800 px, bench/registration_gt.md), median rotation error against the true cameras
#: (seeds 0, 1, 2 where measured): 0.0067 -> 0.104 / 0.105 / 0.105 deg (2335 points); 0.0045 ->
#: 0.091; 0.004 -> 0.093; 0.003 -> 0.075 / 0.076 / 0.079 (3095 points); 0.002 -> 0.076 (3369 points)
MASKED_PEAK_THRESHOLD = 0.003


def masked_options(opts: SfmOptions, object_fraction: float) -> SfmOptions:
    """Options for features restricted to the object by masks.

    COLMAP finds up to ``max_num_features`` features on the whole image and then drops those
    outside the mask, so an object filling a fraction ``object_fraction`` of the photo keeps
    about that fraction of the budget: the budget is divided by it (at most
    ``MASKED_BUDGET_MAX_FACTOR`` x). The object is a small part of the photo, so SIFT's upsampled
    first octave is always used (no skip-then-retry), and an object that offers few features
    gives weaker ones too (:data:`MASKED_PEAK_THRESHOLD`, :func:`peak_threshold_for`).

    Args:
        opts: the options for whole photos.
        object_fraction: mean fraction of a photo's pixels inside its mask, (0, 1].

    >>> o = masked_options(SfmOptions(), 0.25)
    >>> o.max_num_features, o.upsample_below > o.max_image_size, o.retry_upsampled_below, o.low_contrast_peak_threshold
    (16384, True, 0.0, 0.003)
    """
    factor = min(float(MASKED_BUDGET_MAX_FACTOR), 1.0 / max(float(object_fraction), 1e-6))
    return replace(opts, max_num_features=int(round(opts.max_num_features * max(factor, 1.0))),
                   upsample_below=opts.max_image_size + 1, retry_upsampled_below=0.0,
                   low_contrast_peak_threshold=MASKED_PEAK_THRESHOLD)


def register_photos(photo_dir: str | Path, names: list[str], work_dir: str | Path, opts: SfmOptions = SfmOptions(),
                    masks: dict[str, Path] | None = None, progress: StageProgress | None = None,
                    content: dict[str, str] | None = None, masks_given: bool = False) -> tuple[Registration, SfmReport]:
    """Register a photo set with COLMAP; resume what a previous run in ``work_dir`` finished.

    Large photos first skip SIFT's upsampled octave (fast); when too few of them register
    (:func:`wants_upsampled_retry`), features are extracted again with it, in
    ``work_dir/upsampled``, and the registration with more photos is kept. The report says
    which (``features``, ``retry``). ``masks_given``: the user has masks that ``masks`` does not
    apply to the features (the advice for unregistered photos says how to use them).

    Raises:
        DamcapError: fewer than 2 photos, or no pass registered any.
    """
    from damcap.reconstruct.photos import image_size

    photo_dir, work_dir = Path(photo_dir), Path(work_dir)
    skipped = len(names) >= 2 and octave_skipped({image_size(photo_dir / nm) for nm in names}, opts)
    first_error: DamcapError | None = None
    try:
        reg, rep = _register_once(photo_dir, names, work_dir, opts, masks, progress, content, masks_given)
        rep.features = reg.stats["features"] = "skipped first octave" if skipped else "upsampled first octave"
    except DamcapError as e:
        if not skipped or opts.retry_upsampled_below <= 0 or len(names) < 2:
            raise
        first_error, reg, rep = e, None, None  # type: ignore[assignment]
    if rep is not None and not wants_upsampled_retry(rep.registered, rep.photos, skipped, opts.retry_upsampled_below):
        return reg, rep
    upsampled = replace(opts, upsample_below=opts.max_image_size + 1)
    try:
        reg2, rep2 = _register_once(photo_dir, names, work_dir / "upsampled", upsampled, masks, progress, content, masks_given)
    except DamcapError as e:
        if rep is None:
            raise first_error from None  # type: ignore[misc]
        rep.retry = {"upsampled_first_octave": str(e), "kept": "skipped first octave"}
        reg.stats = asdict(rep)
        return reg, rep
    first = {"registered": rep.registered} if rep is not None else {"error": str(first_error)}
    if rep is not None and rep.registered >= rep2.registered:
        rep.retry = {"upsampled_first_octave": {"registered": rep2.registered}, "kept": "skipped first octave"}
        reg.stats = asdict(rep)
        return reg, rep
    rep2.features = "upsampled first octave (retry)"
    rep2.retry = {"skipped_first_octave": first, "kept": "upsampled first octave"}
    rep2.seconds = {k: round(v + (rep.seconds.get(k, 0.0) if rep is not None else 0.0), 2) for k, v in rep2.seconds.items()}
    reg2.stats = asdict(rep2)
    return reg2, rep2


def _register_once(photo_dir: Path, names: list[str], work_dir: Path, opts: SfmOptions, masks: dict[str, Path] | None,
                   progress: StageProgress | None, content: dict[str, str] | None,
                   masks_given: bool = False) -> tuple[Registration, SfmReport]:
    """One registration pass with ``opts`` (resumed from what ``work_dir`` holds).

    Args:
        photo_dir: folder of the photos (read only).
        names: photo file names to register, sorted (their order is the ring order).
        work_dir: folder for the database, masks, model and state (created).
        opts: registration options.
        masks: photo name -> mask file (white = object) to restrict features to the object, or None.
        progress: called as (stage, done, total).
        content: image name -> what identifies its content for the resumable stages (e.g. a
            digest of a registration proxy); None: the file sizes.

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

    _, fp_matches, _ = _fingerprints(photo_dir, names, opts, masks, content)
    # refining the principal point is a later step of mapping (older mapping states stay valid)
    fp_mapping = fingerprint([fp_matches, opts.seed] + {"refine": ["refine_principal_point"], "centre": [],
                                                        "auto": ["principal_point auto"]}[opts.principal_point])

    if stages.status("mapping", fp_mapping) == "done" and model_dir.is_dir() and report_path.is_file():
        rec = pycolmap.Reconstruction(str(model_dir))
        rep = SfmReport(**json.loads(report_path.read_text(encoding="utf-8")))
        rep.resumed = ["features", "matches", "mapping"]
        if rep.principal_point is None and rec.num_cameras() == 1:  # a registration from before the estimate
            principal = adjust_principal_point(rec, pycolmap, apply=False)[0]  # on a copy: the model stays as it was
            if principal is not None:
                rep.principal_point = asdict(replace(principal, used=opts.principal_point == "refine"))
                write_json_atomic(report_path, asdict(rep))
        reg = registration_of_reconstruction(rec, names, "sfm", str(model_dir))
        reg.unregistered = dict(rep.unregistered)
        reg.stats = asdict(rep)
        progress("registration (reused)", 1, 1)
        return reg, rep

    db_path, n_pairs, pairing = _features_and_matches(photo_dir, names, work_dir, opts, masks, progress, stages, seconds,
                                                      resumed, wipe=(model_dir, work_dir / "models", report_path), content=content)

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
    keypoints, best_inliers = database_summary(db_path, names)
    if not recs:
        reasons = unregistered_reasons(names, set(), keypoints, best_inliers, {}, opts.min_num_inliers, bool(masks),
                                       masks_given and not masks)
        worst = sorted(reasons.items())[:3]
        raise DamcapError(
            f"{photo_dir}: COLMAP could not register the photos (no initial pair among {n} photos; e.g. "
            + "; ".join(f"{k}: {v}" for k, v in worst)
            + "). Photos need overlap and texture; try "
            + ("more photos or --poses" if masks else "--mask-features always, more photos, or --poses" if masks_given
               else "--masks, more photos, or --poses")
        )
    ranked = sorted(recs.values(), key=lambda r: r.num_reg_images(), reverse=True)
    rec = ranked[0]
    progress("principal point", 0, 1)
    t0 = time.perf_counter()
    principal, adjusted = adjust_principal_point(rec, pycolmap, apply=opts.principal_point == "refine")
    if principal is not None and opts.principal_point == "auto":
        use, why = photos_support_offset(principal, int(rec.num_reg_images()))
        if use:  # the copy the estimate was made on is the registration with the point refined
            rec, principal = adjusted, replace(principal, used=True)
        principal = replace(principal, decision=f"auto: {why}")
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
    reg.unregistered = unregistered_reasons(names, registered, keypoints, best_inliers, others, opts.min_num_inliers,
                                           bool(masks), masks_given and not masks)
    rep = SfmReport(photos=n, registered=len(registered), points=int(rec.num_points3D()),
                    mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()), pairs=n_pairs,
                    pairing=pairing, seconds={k: round(v, 2) for k, v in seconds.items()},
                    unregistered=reg.unregistered, resumed=resumed,
                    principal_point=asdict(principal) if principal is not None else None,
                    sift_peak_threshold=stages.state.get("sift_peak_threshold"))
    write_json_atomic(report_path, asdict(rep))
    stages.mark("mapping", fp_mapping, done=True)
    reg.stats = asdict(rep)
    progress("mapping", n, n)
    return reg, rep


def triangulate_known(photo_dir: str | Path, registration: Registration, work_dir: str | Path, opts: SfmOptions = SfmOptions(),
                      masks: dict[str, Path] | None = None, progress: StageProgress | None = None,
                      content: dict[str, str] | None = None) -> Registration:
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
        content: see :func:`register_photos`.

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
    db_path, _, _ = _features_and_matches(photo_dir, names, work_dir, opts, masks, progress, _Stages(work_dir), seconds, [],
                                          content=content)
    progress("triangulation", 0, 1)
    rec = pycolmap.Reconstruction()
    db = pycolmap.Database.open(str(db_path))
    try:
        images = {im.name: im for im in db.read_all_images()}
        for p in registration.photos:
            c, im = p.camera, images[p.name]
            cam = colmap_camera(c)
            cam.camera_id = im.camera_id
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
    for image_id, obs in image_observations(rec).items():
        k = index[rec.image(image_id).name]
        registration.photos[k] = replace(registration.photos[k], observations_px=obs)
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
