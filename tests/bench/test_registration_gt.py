"""The ground-truth registration study's pure parts: its errors against reference cameras, the
intrinsics comparison and the report table (no registration is run)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.registration_gt import discussion_lines, gt_errors, intrinsics_vs_gt, pp_rule_refines, row_cells, scene_key, write_report
from damcap.reconstruct.normalize import similarity, transform_world_from_cam
from damcap.reconstruct.undistort import PhotoCamera

from tests.reconstruct.conftest import _cameras


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def _rot_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1.0, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def _named(mats: np.ndarray) -> dict[str, np.ndarray]:
    return {f"p{k}": m for k, m in enumerate(mats)}


def test_errors_vanish_under_any_similarity_of_the_world():
    ref = _cameras(6)
    est = transform_world_from_cam(similarity(0.37, _rot_z(40) @ _rot_x(25), np.array([3.0, -1.0, 2.0])), ref)
    e = gt_errors(_named(est), _named(ref))
    assert e["compared"] == 6
    for k in ("rot_sim_median_deg", "rot_sim_max_deg", "rot_common_median_deg", "rot_common_max_deg",
              "centre_median_rel", "centre_max_rel"):
        assert e[k] < 1e-9, k
    c = ref[:, :3, 3]
    assert e["extent"] == pytest.approx(max(np.linalg.norm(a - b) for a in c for b in c))


def test_one_camera_turned_about_its_own_axis_shows_its_angle():
    ref = _cameras(8)
    est = ref.copy()
    est[3, :3, :3] = est[3, :3, :3] @ _rot_z(2.0)  # camera 3 rolled by 2 deg; centres unchanged
    e = gt_errors(_named(est), _named(ref))
    # the centres are exact, so the similarity is the identity: the error is exactly 2 deg on one camera
    assert e["rot_sim_max_deg"] == pytest.approx(2.0, abs=1e-9) and e["rot_sim_median_deg"] < 1e-9
    assert e["centre_max_rel"] < 1e-12
    # the common rotation spreads a little of it over the others, never more than the 2 deg
    assert 1.0 < e["rot_common_max_deg"] <= 2.0 + 1e-9


def test_centre_error_is_relative_to_the_reference_extent():
    ref = _cameras(5)
    est = ref.copy()
    c = ref[:, :3, 3]
    extent = max(np.linalg.norm(a - b) for a in c for b in c)
    est[2, :3, 3] += np.array([0.0, 0.0, 0.01 * extent])  # one centre off by 1% of the extent
    e = gt_errors(_named(est), _named(ref))
    # the identity is one candidate alignment with squared residuals summing to (1%)^2, so the
    # least-squares one leaves no centre further off than 1%; it cannot absorb the move entirely
    assert 0.001 < e["centre_max_rel"] <= 0.01 + 1e-12 and e["centre_median_rel"] <= e["centre_max_rel"]
    # relative to the extent: the reference's units do not matter
    scaled = transform_world_from_cam(similarity(10.0, np.eye(3), np.zeros(3)), ref)
    e10 = gt_errors(_named(est), _named(scaled))
    assert e10["centre_max_rel"] == pytest.approx(e["centre_max_rel"]) and e10["extent"] == pytest.approx(10 * extent)


def test_fewer_than_three_common_photos_give_only_the_count():
    ref = _cameras(4)
    assert gt_errors({"p0": ref[0], "p1": ref[1], "x": ref[2]}, _named(ref)) == {"compared": 2}


def test_intrinsics_against_the_reference():
    ref = PhotoCamera(1536, 1024, 1379.74, 1382.08, 760.595, 503.655)
    shared = PhotoCamera(1536, 1024, 1385.0, 1385.0, 768.0, 512.0, (0.01,) + (0.0,) * 7)
    i = intrinsics_vs_gt([shared] * 3, ref)
    assert i["cameras"] == 1 and i["focal_spread_px"] == 0.0
    assert i["focal_err_px"] == pytest.approx(1385.0 - (1379.74 + 1382.08) / 2)
    assert i["pp_err_px"] == pytest.approx([768.0 - 760.595, 512.0 - 503.655])
    per_photo = [PhotoCamera(1536, 1024, f, f, 768.0, 512.0) for f in (1370.0, 1380.0, 1390.0)]
    i = intrinsics_vs_gt(per_photo, ref)
    assert i["cameras"] == 3 and i["focal_px"] == pytest.approx(1380.0) and i["focal_spread_px"] == pytest.approx(20.0)
    assert intrinsics_vs_gt([], ref) == {}


def _result() -> dict:
    machine = {"date_utc": "2026-01-01 00:00:00 UTC", "nproc": 2, "cpu_model": "cpu"}
    ref = {"what": "Strecha ground truth", "photos": 8, "width": 1536, "height": 1024, "focal_px": 1380.91,
           "pp_px": [760.6, 503.66], "pp_offset_px": [-7.4, -8.34], "pp_tilt_deg": 0.462, "extent": 12.5}
    rows = [{"method": "damcap", "photos": 8, "registered": 8, "wall_s": 30.04, "stage_wall_s": {"features": 20.0, "mapping": 3.26},
             "errors": {"compared": 8, "rot_sim_median_deg": 0.1234, "rot_sim_max_deg": 0.5, "rot_common_median_deg": 0.1,
                        "rot_common_max_deg": 0.4, "centre_median_rel": 0.0012, "centre_max_rel": 0.0034, "extent": 12.5},
             "intrinsics": {"cameras": 1, "focal_px": 1385.0, "focal_err_px": 4.09, "focal_spread_px": 0.0,
                            "pp_px": [768.0, 512.0], "pp_err_px": [7.4, 8.34]},
             "principal_point": {"offset_px": [-6.9, -8.1], "sd_px": [0.4, 0.5], "tilt_deg": 0.44, "used": False}},
            {"method": "pycolmap global", "photos": 8, "registered": 0, "wall_s": 12.0, "error": "no model"}]
    return {"scenes": {"herz-jesus-p8": {"command": ".venv/bin/python -m bench.registration_gt", "machine": machine,
                                         "pycolmap": "4.2.1", "reference": ref, "rows": rows}}}


def test_table_rows():
    rows = _result()["scenes"]["herz-jesus-p8"]["rows"]
    assert row_cells(rows[0]) == ["damcap", "8/8", "0.123 / 0.500", "0.100 / 0.400", "0.12 / 0.34", "1385.0 (+4.1)",
                                  "(+7.4, +8.3)", "(-6.9, -8.1) +- (0.4, 0.5)", "-", "30.0 (3.3)"]
    assert row_cells(rows[1]) == ["pycolmap global", "0/8 (no model)", "- / -", "- / -", "- / -", "-", "-", "-", "-", "12.0"]
    checked = {**rows[0], "method": "damcap reconstruct", "intrinsics": {}, "principal_point": None,
               "self_check": {"verdict": "photos flagged", "flagged": ["a.jpg"], "recall_min": 0.8531}}
    assert row_cells(checked)[5:9] == ["-", "-", "-", "photos flagged, recall min 0.853, flagged 1"]


def test_report_names_the_command_and_every_row(tmp_path):
    res = _result()
    sub = {**res["scenes"]["herz-jesus-p8"], "command": ".venv/bin/python -m bench.registration_gt --first 4", "photos": 4}
    sub["rows"] = [{**sub["rows"][0], "photos": 4, "registered": 4}]
    res["scenes"][scene_key("herz-jesus-p8", 4)] = sub
    write_report(res, tmp_path / "r.md")
    text = (tmp_path / "r.md").read_text()
    assert "## herz-jesus-p8" in text and "Command: `.venv/bin/python -m bench.registration_gt`" in text
    assert "| damcap | 8/8 | 0.123 / 0.500 |" in text and "| pycolmap global | 0/8 (no model) |" in text
    assert "(-7.40, -8.34) from the image centre (tilt 0.462 deg)" in text
    assert "## Fewer photos" in text and "| herz-jesus-p8 (first 4) | damcap | 4/4 | 0.123 / 0.500 |" in text
    assert "- `.venv/bin/python -m bench.registration_gt --first 4`" in text
    assert "- herz-jesus-p8: refined: 23.7 sigma (needs 3), 8 photos, tilt 0.44 deg (at most 1)" in text


def test_pp_rule_is_damcaps_auto_rule():
    est = {"offset_px": [-6.0, -8.0], "sd_px": [10 / 3, 10 / 3], "tilt_deg": 0.4}  # 3 sigma exactly
    assert pp_rule_refines(est, 5) == (True, "refined: 3.0 sigma (needs 3), 5 photos, tilt 0.40 deg (at most 1)")
    assert not pp_rule_refines(est, 4)[0]
    assert not pp_rule_refines({**est, "tilt_deg": 1.01}, 100)[0]
    assert pp_rule_refines(None, 100) == (False, "no estimate")


def test_discussion_compares_refined_with_centred_and_global_with_incremental():
    res = _result()
    rows = res["scenes"]["herz-jesus-p8"]["rows"]
    refined = {**rows[0], "method": "damcap refined pp",
               "errors": {**rows[0]["errors"], "rot_sim_median_deg": 0.15, "centre_median_rel": 0.0005},
               "intrinsics": {**rows[0]["intrinsics"], "pp_err_px": [0.5, -2.8]}}
    inc = {**rows[0], "method": "pycolmap incremental", "stage_wall_s": {"mapping": 12.0}}
    glo = {**rows[0], "method": "pycolmap global", "stage_wall_s": {"mapping": 25.0},
           "errors": {**rows[0]["errors"], "rot_sim_median_deg": 0.2, "rot_sim_max_deg": 0.3, "centre_max_rel": 0.002}}
    res["scenes"]["herz-jesus-p8"]["rows"] = [rows[0], refined, inc, glo]
    text = "\n".join(discussion_lines(res))
    assert ("- herz-jesus-p8: refined: 23.7 sigma (needs 3), 8 photos, tilt 0.44 deg (at most 1); measured 0.123 -> 0.150 deg, centre 0.12 -> "
            "0.05 % (median); pp (+7.4, +8.3) -> (+0.5, -2.8) px") in text
    assert ("- herz-jesus-p8: registered 8 / 8 of 8; mapping 12.0 s / 25.0 s; rotation 0.123 / 0.500 deg against "
            "0.200 / 0.300 deg; centre max 0.34 % against 0.20 %") in text


def test_known_intrinsics_row_and_floor_line(tmp_path):
    """The reference-intrinsics rerun is a row of its scene's table and a line of the discussion,
    next to damcap's refined run and the centres' spread."""
    res = _result()
    sc = res["scenes"]["herz-jesus-p8"]
    row = sc["rows"][0]
    sc["rows"].append({**row, "method": "damcap refined pp"})
    sc["known_intrinsics"] = {**row, "method": "pycolmap incremental, reference intrinsics fixed (mapping only)",
                              "errors": {**row["errors"], "rot_sim_median_deg": 0.157, "rot_common_median_deg": 0.021}}
    sc["known_intrinsics_command"] = ".venv/bin/python -m bench.registration_gt --known-intrinsics"
    sc["reference"]["centre_spread"] = [1.0, 0.138, 0.018]
    text = "\n".join(discussion_lines(res))
    assert ("- herz-jesus-p8: reference intrinsics 0.157 / 0.500 deg sim, 0.021 / 0.400 deg common; damcap refined pp "
            "0.123 / 0.500 sim, 0.100 / 0.400 common; centres 1.000 : 0.138 : 0.018") in text
    write_report(res, tmp_path / "r.md")
    report = (tmp_path / "r.md").read_text()
    assert "| pycolmap incremental, reference intrinsics fixed (mapping only) | 8/8 | 0.157 / 0.500 |" in report
    assert "`.venv/bin/python -m bench.registration_gt --known-intrinsics`" in report


def test_a_rerun_of_some_methods_keeps_the_other_rows_with_their_command(tmp_path):
    from bench.registration_gt import merged_scene

    prev = _result()["scenes"]["herz-jesus-p8"]
    new = {**prev, "command": ".venv/bin/python -m bench.registration_gt --methods 'damcap reconstruct'",
           "rows": [{**prev["rows"][0], "method": "damcap reconstruct", "command": "x"}]}
    new["rows"][0]["command"] = new["command"]
    sc = merged_scene(prev, new)
    assert [r["method"] for r in sc["rows"]] == ["damcap reconstruct", "damcap", "pycolmap global"]
    write_report({"scenes": {"herz-jesus-p8": sc}}, tmp_path / "r.md")
    text = (tmp_path / "r.md").read_text()
    assert ("Rows *damcap*, *pycolmap global* measured earlier by `.venv/bin/python -m bench.registration_gt` "
            "(2026-01-01 00:00:00 UTC).") in text
