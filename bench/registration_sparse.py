"""Sparse subsets of a real capture: damcap's registration against plain pycolmap (issue 26).

Subsets of the cape photos (``real/mold_gold_cape``: 119 photos, 912 px, with masks and LLFF
reference poses): every 2nd of the first 60, every 4th of all. Four registrations each, in one
run, side by side:

- ``damcap (no retry)``: ``SfmOptions(retry_upsampled_below=0)``, the registration before the
  retry: SIFT's upsampled first octave skipped for photos of 800 px and more;
- ``damcap``: the default on the whole photos (the octave skipped first; registered again with
  it when fewer than 95% of the photos register);
- ``damcap reconstruct --masks``: the default command with masks (``--mask-features auto``: the
  whole photos, then features inside the masks when fewer than 95% register or the self-check
  flags a photo; the candidate with more photos passing the self-check is kept), a small capture
  (64 px) and ``--min-registered-fraction 0.1`` (the default 0.5 refuses a capture of 14 of 30
  photos); the cameras are read back from the capture;
- ``pycolmap``: plain pycolmap 4.2.1 as a new user would run it: features restricted to the
  masks, its default extraction (first octave upsampled, 8192 features), exhaustive matching,
  default incremental mapper.

Reported: registered photos, median / max rotation error against the reference poses after one
rotation common to all cameras is removed (``agreement``), and wall time. Results:
``bench/results/registration_sparse.json`` and ``bench/registration_sparse.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import CACHE, RESULTS, command_line, log, machine_info, rows_not_rerun, shared_data_dir
from bench.reconstruct import reference_registration

REPORT = Path(__file__).with_name("registration_sparse.md")
RESULT = RESULTS / "registration_sparse.json"
SUBSETS = {"every 2nd of the first 60": lambda names: names[:60][::2], "every 4th": lambda names: names[::4]}
METHODS = ("damcap (no retry)", "damcap", "damcap reconstruct --masks", "pycolmap")


def subset_folder(data: Path, names: list[str], tag: str) -> Path:
    """A folder of links to the subset's photos and masks (the shared data stays as it is)."""
    root = CACHE / "registration_sparse" / tag
    if root.exists():
        shutil.rmtree(root)
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    (root / "masks_pycolmap").mkdir()
    import cv2

    for n in names:
        (root / "images" / n).symlink_to(data / "images" / n)
        mask = data / "masks" / (Path(n).stem + ".png")
        (root / "masks" / mask.name).symlink_to(mask)
        cv2.imwrite(str(root / "masks_pycolmap" / (n + ".png")), cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE))
    return root


def _rotation_errors(est: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> dict:
    from damcap.reconstruct.normalize import rotation_aligned_errors_deg

    names = [n for n in est if n in ref]
    if len(names) < 2:
        return {"compared": len(names)}
    err = rotation_aligned_errors_deg(np.stack([est[n] for n in names]), np.stack([ref[n] for n in names]))
    return {"compared": len(names), "median_rot_aligned_deg": float(np.median(err)), "max_rot_aligned_deg": float(np.max(err))}


def run_damcap(root: Path, names: list[str], retry: bool) -> dict:
    from damcap.common.errors import DamcapError
    from damcap.reconstruct.colmap.register import SfmOptions, register_photos

    work = root / ("work-damcap" if retry else "work-damcap-noretry")
    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    try:
        reg, rep = register_photos(root / "images", names, work, replace(SfmOptions(), retry_upsampled_below=0.95 if retry else 0.0))
    except DamcapError as e:
        return {"registered": 0, "error": str(e)[:200], "wall_s": round(time.perf_counter() - t0, 1)}
    return {"registered": rep.registered, "features": rep.features, "retry": rep.retry, "wall_s": round(time.perf_counter() - t0, 1),
            "est": {p.name: p.world_from_cam for p in reg.photos}}


def run_reconstruct(root: Path) -> dict:
    from damcap.common.capture_folder import read_capture
    from damcap.common.errors import DamcapError
    from damcap.reconstruct.geometry import GeometryOptions
    from damcap.reconstruct.pipeline import ReconstructOptions, reconstruct_capture

    out = root / "capture"
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    try:
        _, report = reconstruct_capture(root / "images", out, ReconstructOptions(capture_size=64, geometry=GeometryOptions(voxels=48), supersample=1,
                                                                                  train_views=3, min_registered_fraction=0.1),
                                        masks_dir=root / "masks")
    except DamcapError as e:
        return {"registered": 0, "error": str(e)[:200], "wall_s": round(time.perf_counter() - t0, 1)}
    cap = read_capture(out)
    return {"registered": len(cap.frames), "features": report.registration["features_used"],
            "candidates": report.registration["candidates"], "self_check": (report.self_check or {}).get("summary"),
            "wall_s": round(time.perf_counter() - t0, 1), "est": {f.extra["photo"]: f.world_from_cam for f in cap.frames}}


def run_pycolmap(root: Path, names: list[str]) -> dict:
    import pycolmap

    from damcap.reconstruct.poses import world_from_cam_of_colmap

    work = root / "work-pycolmap"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    t0 = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.mask_path = str(root / "masks_pycolmap")
    pycolmap.extract_features(work / "db.db", root / "images", image_names=names, reader_options=reader,
                              camera_mode=pycolmap.CameraMode.SINGLE, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(work / "db.db", device=pycolmap.Device.cpu)
    recs = pycolmap.incremental_mapping(work / "db.db", root / "images", work / "sparse")
    wall = round(time.perf_counter() - t0, 1)
    if not recs:
        return {"registered": 0, "wall_s": wall}
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    est = {im.name: world_from_cam_of_colmap(im.cam_from_world().matrix()) for im in best.images.values()}
    return {"registered": best.num_reg_images(), "wall_s": wall, "est": est}


def write_report(res: dict, path: Path = REPORT) -> None:
    lines = ["# Registration of sparse subsets (issue 26)", "",
             f"Command: `{res['command']}` ({res['machine']['date_utc']}, {res['machine']['nproc']} cores, "
             f"{res['machine']['cpu_model']}; the machine is shared, so times are side by side in one run only).", "",
             "Cape photos (912 px). pycolmap's features are restricted to the masks; damcap's registrations are on "
             "the whole photos, except `damcap reconstruct --masks` (the default command: whole photos, then features "
             "inside the masks when needed; 'registered' counts the capture's frames). Rotation error against the LLFF reference after removing one common rotation; "
             "'-' where fewer than 2 photos registered.", "",
             "| subset | photos | method | registered | median / max rotation error (deg) | wall (s) |",
             "|---|---|---|---|---|---|"]
    for row in res["rows"]:
        err = (f"{row['median_rot_aligned_deg']:.3f} / {row['max_rot_aligned_deg']:.3f}" if "median_rot_aligned_deg" in row
               else "-")
        lines.append(f"| {row['subset']} | {row['photos']} | {row['method']} | {row['registered']} | {err} | {row['wall_s']} |")
    earlier = sorted({(r["command"], r["date_utc"]) for r in res["rows"] if r.get("command")})
    lines += [""] + [f"Rows not measured by the command above: `{c}` ({d})." for c, d in earlier]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subsets", nargs="+", default=list(SUBSETS), choices=list(SUBSETS))
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS),
                    help="rerun only these; the saved rows of the others are kept, each with the command that measured it")
    args = ap.parse_args(argv)
    data = shared_data_dir() / "real" / "mold_gold_cape"
    all_names = sorted(p.name for p in (data / "images").iterdir())
    ref_all = reference_registration("mold_gold_cape", all_names, shared_data_dir() / "real")
    ref = {p.name: p.world_from_cam for p in ref_all.photos}
    rows = []
    for tag, pick in SUBSETS.items():
        if tag not in args.subsets:
            continue
        names = pick(all_names)
        root = subset_folder(data, names, tag.replace(" ", "-"))
        for method, run in (("damcap (no retry)", lambda: run_damcap(root, names, retry=False)),
                            ("damcap", lambda: run_damcap(root, names, retry=True)),
                            ("damcap reconstruct --masks", lambda: run_reconstruct(root)),
                            ("pycolmap", lambda: run_pycolmap(root, names))):
            if method not in args.methods:
                continue
            log(f"{tag}: {method} on {len(names)} photos")
            out = run()
            est = out.pop("est", {})
            row = {"subset": tag, "photos": len(names), "method": method, **out, **_rotation_errors(est, ref)}
            log(f"  -> {json.dumps({k: v for k, v in row.items() if k not in ('retry', 'candidates')})}")
            rows.append(row)
    res = {"command": command_line("registration_sparse", argv), "machine": machine_info(),
           "rows": merged_rows(json.loads(RESULT.read_text(encoding="utf-8")) if RESULT.is_file() else None, rows)}
    RESULT.write_text(json.dumps(res, indent=1), encoding="utf-8")
    write_report(res)
    return 0


def merged_rows(prev: dict | None, new: list[dict]) -> list[dict]:
    """The new rows, and the saved rows (``prev``, a saved result) of the (subset, method) pairs
    not rerun, each saved row with the command and date that measured it; in subset, then
    :data:`METHODS` order.

    >>> prev = {"command": "a", "machine": {"date_utc": "d0"}, "rows": [{"subset": "every 4th", "method": "pycolmap"},
    ...         {"subset": "every 4th", "method": "damcap"}]}
    >>> [(r["method"], r.get("command", "b")) for r in merged_rows(prev, [{"subset": "every 4th", "method": "damcap"}])]
    [('damcap', 'b'), ('pycolmap', 'a')]
    """
    kept = rows_not_rerun(prev, new, lambda r: (r["subset"], r["method"]))
    order = list(SUBSETS)
    return sorted(new + kept, key=lambda r: (order.index(r["subset"]) if r["subset"] in order else len(order),
                                             METHODS.index(r["method"]) if r["method"] in METHODS else len(METHODS)))


def rewrite_report() -> None:
    """The markdown table again from the saved results (no registration is rerun)."""
    write_report(json.loads(RESULT.read_text(encoding="utf-8")))


if __name__ == "__main__":
    raise SystemExit(main())
