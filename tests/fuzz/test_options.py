"""Every numeric option of every command with NaN, inf, -1, 0, a huge value and a non-number.

Only values outside an option's documented range are cases (``--seed 0`` is valid); each is
refused in one line naming the option and the value, before any work, with no output left.
The base arguments make a run cheap, so a missing check shows up as "accepted", not as a hang.
"""

from __future__ import annotations

import pytest

from damcap.common.data_dir import shared_data_dir
from tests.fuzz.conftest import refused

NAN, INF, NEG, ZERO, HUGE_I, HUGE_F, WORD = "nan", "inf", "-1", "0", "100000000000000000000", "1e300", "abc"
INT_POS = [NEG, ZERO, HUGE_I, WORD, "2.5"]        # counts that must be >= 1
INT_NONNEG = [NEG, HUGE_I, WORD]                   # counts where 0 means none
FLOAT_POS = [NAN, INF, NEG, ZERO, HUGE_F, WORD]    # scales, rates, distances
FLOAT_NONNEG = [NAN, INF, NEG, HUGE_F, WORD]       # weights where 0 is off
FRACTION = [NAN, INF, NEG, ZERO, "1.5", WORD]      # in (0, 1]
ANGLE = [NAN, INF, "1e300", WORD]                  # any finite angle
ELEV = [NAN, INF, "90", "-90", "1e300", WORD]       # strictly inside (-90, 90)
SEED = [NEG, HUGE_I, WORD]

W = "{W}"
BASE = {
    "closed-form": ["closed-form", f"{W}/out", "--views", "4", "--train-views", "2", "--res", "8", "--env-grid", "4", "--supersample", "1"],
    "fit": ["fit", f"{W}/cap", "-o", f"{W}/out", "--steps", "2", "--batch-size", "32", "--holdout-views", "0"],
    "render": None,
    "evaluate": ["evaluate", f"{W}/cap", "--json", f"{W}/out", "--kmeans-steps", "2"],
    "hdr": ["hdr", f"{W}/photos/images/IMG_0000.jpg", f"{W}/photos/images/IMG_0001.jpg", "-o", f"{W}/out", "--response-samples", "50"],
    "linearize": ["linearize", f"{W}/photos/images", "-o", f"{W}/out"],
    "synth-photos": ["synth-photos", f"{W}/out", "--views", "2", "--size", "16"],
    "reconstruct": ["reconstruct", f"{W}/photos/images", "-o", f"{W}/out", "--poses", f"{W}/photos/transforms.json", "--geometry", "sphere",
                    "--capture-size", "16", "--train-views", "2"],
    "export": ["export", f"{W}/m.dam", "--mesh", f"{W}/mesh.obj", "-o", f"{W}/out", "--views", "1", "--resolution", "8"],
    "view": ["view", f"{W}/m.dam", "-o", f"{W}/out"],
    "segment": ["segment", f"{W}/cap", "-o", f"{W}/out", "--materials", "2", "--steps", "1", "--init-steps", "1", "--batch-pixels", "32",
                "--psi-resolution", "8", "--restarts", "1"],
    "train-hyper": ["train-hyper", f"{W}/corpus", "-o", f"{W}/out", "--steps", "1", "--batch-size", "1", "--input-size", "16", "--pixels", "16",
                    "--eval-every", "1", "--checkpoint-every", "0", "--pixels-per-capture", "64", "--channels", "4,4"],
    "predict": ["predict", f"{W}/cap", "-o", f"{W}/out"],
    "synth": ["synth", f"{W}/out", "--views", "3", "--train-views", "2", "--res", "8", "--spp", "1"],
    "synth-set": ["synth-set", f"{W}/out", "--dry-run", "--data-dir", f"{W}"],
    "synth-studio": ["synth-studio", f"{W}/out", "--object", f"{W}/mesh.obj", "--env", str(shared_data_dir() / "envmaps" / "studio.hdr"),
                     "--views", "3", "--size", "16", "--spp", "1"],
}

OPTIONS = {
    "closed-form": {"--materials": [NEG, ZERO, "3", HUGE_I, WORD], "--views": INT_POS, "--res": INT_POS, "--elevation": ELEV,
                    "--train-views": INT_POS + ["5"], "--seed": SEED, "--env-grid": INT_POS, "--supersample": INT_POS},
    "fit": {"--target-dssim": [NAN, INF, NEG, ZERO, "1.5", WORD], "--steps": INT_POS, "--batch-size": INT_POS, "--learning-rate": FLOAT_POS,
            "--width": INT_POS, "--depth": INT_POS, "--adversarial-alpha": FLOAT_NONNEG, "--holdout-views": INT_NONNEG + ["2"],
            "--eval-every": INT_POS, "--seed": SEED, "--checkpoint-every": INT_NONNEG, "--weight-decay": FLOAT_NONNEG,
            "--quantile": FRACTION + ["1"], "--normal-refine-steps": INT_POS, "--normal-refine-voxel-px": FLOAT_POS,
            "--normal-refine-prior": FLOAT_NONNEG, "--normal-refine-min-gain": [NAN, INF, NEG, "1", WORD],
            "--normal-refine-min-gain-abs": [NAN, INF, NEG, "1", WORD]},
    "evaluate": {"--kmeans": INT_POS, "--kmeans-steps": INT_POS},
    "hdr": {"--reference-exposure": FLOAT_POS, "--saturation-fraction": FRACTION, "--response-samples": INT_POS, "--smoothness": FLOAT_NONNEG,
            "--flat-fraction": FRACTION, "--sample-phase": [NAN, INF, NEG, "1", WORD], "--iterations": INT_NONNEG},
    "linearize": {"--reference-exposure": FLOAT_POS, "--clip-level": FRACTION},
    "synth-photos": {"--views": INT_POS, "--size": INT_POS, "--elevation": ELEV, "--jitter": FLOAT_NONNEG, "--distance": FLOAT_POS + ["0.5"],
                     "--seed": SEED, "--principal-dx": [NAN, INF, HUGE_F, WORD, "9"], "--principal-dy": [NAN, INF, HUGE_F, WORD, "-9"]},
    "reconstruct": {"--voxels": INT_POS, "--hull-tolerance": INT_NONNEG, "--poisson-depth": INT_POS + ["40"], "--smooth-iterations": INT_NONNEG,
                    "--sphere-max-rms": FLOAT_POS, "--max-image-size": INT_POS, "--max-num-features": INT_POS, "--upsample-below": INT_NONNEG,
                    "--sequential-overlap": INT_POS, "--retrieval-neighbours": INT_POS, "--capture-size": INT_POS, "--train-views": INT_POS + ["5"],
                    "--split-start": INT_NONNEG + ["4"], "--min-registered": INT_POS, "--min-registered-fraction": FRACTION,
                    "--supersample": INT_POS, "--threads": ["-2", ZERO, HUGE_I, WORD], "--seed": SEED,
                    "--min-silhouette-recall": FRACTION, "--min-silhouette-precision": FRACTION, "--max-reprojection-px": FLOAT_POS,
                    "--mask-features": [WORD, "yes"], "--self-check": [WORD, "strict"], "--principal-point": [WORD, "centred"],
                    "--dense-size": INT_POS + ["8"], "--dense-planes": INT_POS + ["2"], "--dense-views": INT_POS + ["1"]},
    "export": {"--fps": INT_POS, "--views": INT_POS, "--elevation": ELEV, "--azimuth0-deg": ANGLE, "--resolution": INT_POS,
               "--distance": FLOAT_POS + ["0.5"], "--fov": FLOAT_POS + ["180"], "--supersample": INT_POS},
    "view": {"--port": [NEG, "65536", HUGE_I, WORD], "--azimuth": ANGLE, "--elevation": ELEV, "--distance": FLOAT_POS, "--fov": FLOAT_POS + ["180"]},
    "segment": {"--steps": INT_NONNEG, "--init-steps": INT_NONNEG, "--batch-pixels": INT_POS, "--frames-per-step": INT_POS + ["3"],
                "--learning-rate": FLOAT_POS, "--sparsity-beta": FLOAT_NONNEG, "--prior-weight": FLOAT_NONNEG,
                "--illumination-degree": [NEG, "3", HUGE_I, WORD], "--colour-floor": [NAN, INF, NEG, "1.5", WORD],
                "--psi-resolution": INT_POS, "--psi-channels": INT_POS, "--width": INT_POS, "--depth": INT_POS, "--seed": SEED,
                "--materials": [NEG, ZERO, HUGE_I, WORD, NAN], "--max-materials": INT_POS, "--margin": FLOAT_NONNEG,
                "--min-gain": FLOAT_NONNEG, "--restarts": INT_POS, "--min-share": FRACTION, "--target-dssim": [NAN, INF, NEG, ZERO, WORD]},
    "train-hyper": {"--steps": INT_POS, "--batch-size": INT_POS, "--pixels": INT_POS, "--learning-rate": FLOAT_POS, "--input-size": INT_POS,
                    "--channels": ["0,4", "-1", "abc", "", "100000000000000000000"], "--max-captures": INT_NONNEG, "--val-fraction": [NAN, INF, NEG, "1", WORD],
                    "--eval-every": INT_POS, "--pixels-per-capture": INT_POS, "--seed": SEED, "--checkpoint-every": INT_NONNEG,
                    "--grad-clip": FLOAT_NONNEG},
    "predict": {"--refine-steps": INT_NONNEG},
    "synth": {"--materials": [ZERO, "9", WORD], "--views": INT_POS, "--res": INT_POS, "--spp": INT_POS, "--elevation": ELEV, "--max-depth": INT_POS},
    "synth-set": {"--jobs": INT_POS},
    "synth-studio": {"--views": INT_POS + ["2"], "--size": INT_POS, "--spp": INT_POS, "--elevation": ELEV, "--jitter": FLOAT_NONNEG,
                     "--distance": FLOAT_POS + ["0.5"], "--board-size": FLOAT_POS + ["1"], "--board-saturation": [NAN, INF, NEG, "1.5", WORD],
                     "--max-depth": INT_POS + ["1"], "--seed": SEED, "--env-rotation-deg": [NAN, INF, "1e300", WORD]},
}

CASES = [(cmd, opt, v) for cmd, opts in OPTIONS.items() for opt, vals in opts.items() for v in vals]


@pytest.mark.parametrize("cmd,opt,value", CASES, ids=[f"{c}{o}={v[:12] or 'empty'}" for c, o, v in CASES])
def test_bad_number(cmd, opt, value, work):
    args = [a.replace(W, str(work)) for a in BASE[cmd]]
    if opt in args:  # the base sets it: replace
        i = args.index(opt)
        args[i + 1] = value
    else:
        args += [opt, value]
    # with nothing to check, "train-views 5 of 4 views" would be valid: only out-of-range cases are listed
    refused(args, opt.lstrip("-").split("-")[0], value if value else opt, inputs=[work / "cap", work / "photos", work / "m.dam", work / "corpus"],
            outputs=[work / "out"], timeout=5)
