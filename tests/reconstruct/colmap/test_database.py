"""What the COLMAP database says about photos that did not register."""

from __future__ import annotations

import numpy as np
import pytest

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


# ---- pair lists: photo names are opaque strings -------------------------------------------

#: names COLMAP's pair list cannot hold as written: spaces, a leading '#' (a comment line), a
#: leading dash, non-ASCII letters
ODD_NAMES = ["Photo 0000.jpg", "# café ß.jpg", "-dash photo.jpg", "tab\there.jpg", "plain.jpg"]


def _database_with(tmp_path, names):
    from damcap.reconstruct.colmap.database import import_pycolmap
    from damcap.synth.photos import write_jpeg

    pycolmap = import_pycolmap()
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in names:
        write_jpeg(photos / name, np.full((16, 16, 3), 128, np.uint8), None)
    db_path = tmp_path / "database.db"
    pycolmap.Database.open(str(db_path)).close()
    pycolmap.import_images(str(db_path), str(photos), image_names=names)
    return db_path


def _image_names(db_path):
    from damcap.reconstruct.colmap.database import import_pycolmap

    db = import_pycolmap().Database.open(str(db_path))
    try:
        return {im.image_id: im.name for im in db.read_all_images()}
    finally:
        db.close()


def test_colmap_reads_every_pair_of_odd_names_back_through_the_aliases(tmp_path):
    """The pair list written for COLMAP is read back by COLMAP's own parser (ImportedPairGenerator)
    as exactly the pairs asked for, whatever the photo names; written with the names themselves,
    it loses the pairs (the bug: 'Photo 0000.jpg' was read as 'Photo')."""
    from damcap.reconstruct.colmap.database import import_pycolmap, images_named_for_pair_lists, pair_list_text

    pycolmap = import_pycolmap()
    db_path = _database_with(tmp_path, ODD_NAMES)
    id_of = {name: i for i, name in _image_names(db_path).items()}
    pairs = [(a, b) for k, a in enumerate(ODD_NAMES) for b in ODD_NAMES[k + 1:]]
    lst = tmp_path / "pairs.txt"

    def read_back() -> set[tuple[int, int]]:
        db = pycolmap.Database.open(str(db_path))
        try:
            return {tuple(sorted(p)) for p in pycolmap.ImportedPairGenerator(pycolmap.ImportedPairingOptions(match_list_path=str(lst)), db).all_pairs()}
        finally:
            db.close()

    want = {tuple(sorted((id_of[a], id_of[b]))) for a, b in pairs}
    with images_named_for_pair_lists(db_path) as alias:
        assert sorted(alias) == sorted(ODD_NAMES)
        lst.write_text(pair_list_text([(alias[a], alias[b]) for a, b in pairs]), encoding="utf-8")
        assert read_back() == want
    assert _image_names(db_path) == {i: n for n, i in id_of.items()}  # the photo names are back
    lst.write_text("".join(f"{a} {b}\n" for a, b in pairs), encoding="utf-8")  # the names as they are
    # COLMAP cuts lines at spaces and skips '#' lines: of the 10 pairs, only the one whose names have
    # neither (a tab inside a name passes) is read back
    assert read_back() == {tuple(sorted((id_of["tab\there.jpg"], id_of["plain.jpg"])))}


def test_pair_list_text_refuses_names_colmap_would_misread():
    from damcap.reconstruct.colmap.database import pair_list_text

    assert pair_list_text([("pair-1", "pair-2"), ("ß.jpg", "-x.jpg")]) == "pair-1 pair-2\nß.jpg -x.jpg\n"
    for bad in ("Photo 0000.jpg", "#1.jpg", "a\tb.jpg", ""):
        with pytest.raises(ValueError, match="cannot hold the image name"):
            pair_list_text([("pair-1", bad)])


def test_aliases_never_equal_a_photo_name():
    from damcap.reconstruct.colmap.database import pair_list_aliases

    names = {1: "pair-2", 2: "_pair-1", 3: "Photo 3.jpg"}
    aliases = pair_list_aliases(names)
    assert aliases == {1: "__pair-1", 2: "__pair-2", 3: "__pair-3"}
    assert not set(aliases.values()) & set(names.values())


def test_a_run_killed_while_matching_gets_its_names_back(tmp_path):
    """The alias record is written before the images are renamed; if the process dies inside the
    block, the next run restores the photo names from it."""
    from damcap.reconstruct.colmap.database import images_named_for_pair_lists, restore_image_names

    db_path = _database_with(tmp_path, ODD_NAMES[:3])
    before = _image_names(db_path)
    block = images_named_for_pair_lists(db_path)
    block.__enter__()  # entered, never left: what a killed run leaves
    assert set(_image_names(db_path).values()) == {"pair-1", "pair-2", "pair-3"}
    restore_image_names(db_path)
    assert _image_names(db_path) == before
    assert not (tmp_path / "database.db.aliases.json").exists()


_LOADED_THEN_SIGTERM = r"""
import os, signal, sys, time
from damcap.cli.main import _signals_and_warnings
from damcap.cli.paths import Terminated
from damcap.reconstruct.colmap.database import import_pycolmap
with _signals_and_warnings():
    pycolmap = import_pycolmap()
    pycolmap.logging.error("E-from-colmap")
    sys.stderr.flush()
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
        print("not interrupted")
    except Terminated:
        print("terminated: damcap's handler")
"""


@pytest.mark.parametrize("verbose", [False, True])
def test_colmap_keeps_damcaps_sigterm_handler_and_its_log_lines_off_the_terminal(verbose):
    """Once pycolmap is loaded (glog installs its failure handler for SIGTERM when it loads), SIGTERM
    still reaches damcap's handler (not a native stack dump); COLMAP's own log lines, its errors
    too, stay off stderr unless --verbose (DAMCAP_VERBOSE)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "DAMCAP_VERBOSE"} | ({"DAMCAP_VERBOSE": "1"} if verbose else {})
    got = subprocess.run([sys.executable, "-c", _LOADED_THEN_SIGTERM], capture_output=True, text=True, timeout=120, env=env)
    assert got.returncode == 0 and got.stdout.strip() == "terminated: damcap's handler", (got.returncode, got.stdout, got.stderr[-1500:])
    assert ("E-from-colmap" in got.stderr) == verbose, got.stderr[-500:]
    assert "*** SIGTERM" not in got.stderr and "Check failure stack trace" not in got.stderr
