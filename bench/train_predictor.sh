#!/usr/bin/env bash
# The recipe of the multi-view predictors (dam-predictor-v2 and -v3, retired, and the start of the shipped -v10): train on
# random closed-form scenes rendered on the fly on the training device (a GPU where one is
# present), for a wall-clock budget: 20 calibration steps measure the seconds per step, then the
# run takes as many steps as fit the budget, writing snapshots at 1/4, 1/2 and 3/4 of it
# (bench/hyper.py scores them: out-of-distribution error against training compute).
#
# usage: [NAME=dam-predictor-vN] bench/train_predictor.sh OUT_DIR [SECONDS] [extra train-hyper options, which win]
# e.g. on a GPU:      NAME=dam-predictor-v2 bench/train_predictor.sh runs/v2 390
#      v3 (retired; at commit d796965, its .json there holds the exact command) = v2 trained further (v2 from the history:
#        git show f25b5a5:appearance/hyper/predictors/dam-predictor-v2.safetensors > v2.safetensors):
#                        NAME=dam-predictor-v3 bench/train_predictor.sh runs/v3 470 --init v2.safetensors --learning-rate 2e-4
#        or the file itself: git show d796965:appearance/hyper/predictors/dam-predictor-v3.safetensors > v3.safetensors
#      v4 = v3 trained through predict's readout solve (ran on the 2-core CPU, 1489 s; its .json holds the command):
#        damcap train-hyper -o v4.safetensors --procedural 1 --input-views 4 --input-size 128 --channels 16,32,64,128,128,256,256
#          --pixels 4096 --scene-px 64 --scene-env-grid 8 --device cpu --init v3.safetensors --checkpoint-every 100 --learning-rate 1e-4
#          --batch-size 8 --steps 400 --eval-every 50 --val-scenes 16 --readout-iterations 3
#        (on a GPU: this script with --init v3.safetensors --readout-iterations 3 --learning-rate 1e-4)
#      v6 (retired; at commit 11dc441) = v4 + 800 steps (--init v4 --seed 1 -o v5.safetensors, 1684 s; not shipped; today
#        git show db45094:appearance/hyper/predictors/dam-predictor-v4.safetensors > v4.safetensors, --init v4.safetensors)
#        + 800 steps (--init v5.safetensors --seed 2 -o v6.safetensors, 1364 s), each v4's command with
#        --steps 800 --eval-every 100 --snapshot-every 200 (v4 is at commit db45094; bench/hyper_ood.md)
#      v8 (retired; at commit 2d3e413) = v6 + 800 steps (--init v6 --seed 3 -o v7.safetensors, 1151 s; not shipped)
#        + 800 steps (--init v7.safetensors --seed 4 -o v8.safetensors, 1126 s), each v6's command with
#        --scene-lights-only 0.55 --scene-env-only 0.3 (more distant-light scenes; bench/hyper_ood.md, history "v8")
#      v10 (shipped, the default) = v8 + 3 x 800 steps in the light orientation, each v8's command with --orientation light
#        (its recorded command spells it --frame light, the old spelling, which still parses)
#        --learning-rate 2e-4: --init v8 --seed 7 -o light1.safetensors (1296 s), --init light1.safetensors --seed 8
#        -o light2.safetensors (1353 s), --init light2.safetensors --seed 9 --val-scenes 32 -o v10.safetensors (1617 s)
#        (bench/hyper_ood.md, history "v10")
# On a machine where damcap is not installed, put it on the module path first (a damcap/ folder
# whose rooms link to the repository's; see bench/hyper_ood.md) and run from outside the repository.
#      several GPUs:  PYTHON="torchrun --nproc-per-node 4 -m" would need the module form below
set -euo pipefail
out=$1
budget=${2:-390}
shift $(( $# >= 2 ? 2 : 1 ))
py=${PYTHON:-python3}
name=${NAME:-dam-predictor-v3}
mkdir -p "$out"
recipe=(--procedural 1 --input-views 4 --input-size 128 --channels 16,32,64,128,128,256,256 --batch-size 64
        --pixels 4096 --learning-rate 5e-4 --scene-px 128 --scene-env-grid 8 --val-scenes 128 --device auto)
$py -m damcap.cli.main train-hyper -o "$out/calib.safetensors" "${recipe[@]}" --steps 20 --eval-every 20 \
    --checkpoint-every 0 --no-resume "$@" 2>&1 | tail -2
steps=$($py -c "import json; d = json.load(open('$out/calib.json')); print(max(100, int($budget / (d['seconds'] / 20)) // 100 * 100))")
rm -f "$out"/calib.*
echo "calibrated: $steps steps fit $budget s"
$py -m damcap.cli.main train-hyper -o "$out/$name.safetensors" "${recipe[@]}" --steps "$steps" \
    --eval-every $(( steps / 20 )) --checkpoint-every $(( steps / 10 )) --snapshot-every $(( steps / 4 )) "$@" 2>&1 \
    | grep -v "it/s\]" | tail -30
rm -f "$out/$name.step$steps.safetensors"  # the last snapshot is the run's end; the predictor is its best step
