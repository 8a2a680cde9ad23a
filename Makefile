# damcap: two commands for a newcomer, `make demo` and `make test`.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.installed
APT_PACKAGES := libusb-1.0-0 libllvm19 libgomp1 chromium libjs-three

.PHONY: demo test wheel-check bench export-truth tables system venv blender clean

# System packages the stack needs (open3d: libusb; mitsuba llvm_ad_rgb: libLLVM 19; the viewer's
# browser test: chromium; the glTF and three.js exports' browser tests: three.js r111 with its GLTFLoader).
system:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing >/dev/null \
	    || { echo "error: could not install system packages:$$missing (run as root or with sudo)"; exit 1; }; \
	fi

# Everything: the core, every optional extra (synth: Mitsuba, pidng; onnx) and the test tools.
# setuptools >= 77 in the venv too: wheel-check builds the wheel with it, offline.
$(STAMP): constraints.txt pyproject.toml setup.py
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip 'setuptools>=77' -c constraints.txt
	$(PIP) install -q -c constraints.txt -e '.[all,test]'
	@$(PY) -c "import torch; assert torch.__version__.startswith('2.13.0'), torch.__version__"
	@touch $(STAMP)

# nerfstudio's dataparser for the export test, in its own folder (tests/nerfstudio-reader.txt says why)
NS_READER := $(VENV)/nerfstudio-reader
$(NS_READER)/.installed: tests/nerfstudio-reader.txt $(STAMP)
	$(PIP) install -q --no-deps --target $(NS_READER) -r tests/nerfstudio-reader.txt
	@touch $@

venv: system $(STAMP)

# Blender 5.0.1 as a Python module, in its own venv (tests/blender.txt says why): the export test
# renders `damcap export --format blender`'s materials with Cycles. PyPI's bpy is CPython 3.11 only.
BLENDER_VENV := .venv-blender
BLENDER_PYTHON ?= python3.11
$(BLENDER_VENV)/.installed: tests/blender.txt
	@test -x $(BLENDER_VENV)/bin/python || $(BLENDER_PYTHON) -m venv $(BLENDER_VENV) \
	  || { echo "error: could not make $(BLENDER_VENV) with $(BLENDER_PYTHON) (PyPI's bpy needs CPython 3.11; set BLENDER_PYTHON=...)"; exit 1; }
	$(BLENDER_VENV)/bin/python -m pip install -q --upgrade pip
	$(BLENDER_VENV)/bin/python -m pip install -q -r tests/blender.txt
	@touch $@

blender: $(BLENDER_VENV)/.installed

DAMCAP := $(VENV)/bin/damcap
PHOTOS := samples/photos_studio
DEMO_OUT ?= demo_out

# The main job, photos to appearance, on the bundled photos (24 path-traced JPEGs of a bunny in
# red plastic, gold and aluminium on a printed board, with masks; samples/README.md): register and
# reconstruct a capture folder (16 train views spread over both camera rings, the other 8 kept as
# novel views), validate it, segment it into its 3 materials, fit one DAM,
# predict one with the shipped predictor (+300 refinement steps), render the fitted one into the
# novel views, evaluate all of them, carry the segmentation onto a new shape (a torus damcap
# generates) and export the three materials on it as a turntable, and write the viewer page.
demo: venv
	$(DAMCAP) reconstruct $(PHOTOS)/images -o $(DEMO_OUT)/capture --masks $(PHOTOS)/masks --split spread --train-views 16
	$(DAMCAP) inspect $(DEMO_OUT)/capture
	$(DAMCAP) segment $(DEMO_OUT)/capture -o $(DEMO_OUT)/segmentation --materials 3
	$(DAMCAP) fit $(DEMO_OUT)/capture -o $(DEMO_OUT)/model.dam
	$(DAMCAP) predict $(DEMO_OUT)/capture -o $(DEMO_OUT)/predicted.dam --refine-steps 300
	$(DAMCAP) render $(DEMO_OUT)/model.dam $(DEMO_OUT)/capture -o $(DEMO_OUT)/renders --split test
	$(DAMCAP) evaluate $(DEMO_OUT)/capture --model $(DEMO_OUT)/model.dam --model $(DEMO_OUT)/predicted.dam --segmentation $(DEMO_OUT)/segmentation --json $(DEMO_OUT)/evaluation.json
	$(DAMCAP) shape torus $(DEMO_OUT)/torus.obj
	$(DAMCAP) segment-labels $(DEMO_OUT)/segmentation --mesh $(DEMO_OUT)/torus.obj -o $(DEMO_OUT)/torus_labels.npy
	$(DAMCAP) export $(DEMO_OUT)/segmentation/material_0.dam $(DEMO_OUT)/segmentation/material_1.dam $(DEMO_OUT)/segmentation/material_2.dam --mesh $(DEMO_OUT)/torus.obj --labels $(DEMO_OUT)/torus_labels.npy -o $(DEMO_OUT)/export --views 24 --resolution 256 --video
	$(DAMCAP) view $(DEMO_OUT)/model.dam -o $(DEMO_OUT)/viewer.html --mesh $(DEMO_OUT)/torus.obj
	@echo
	@echo "demo results are in $(DEMO_OUT)/:"
	@echo "  capture/           the capture folder reconstructed from $(PHOTOS)/images (cameras, geometry, linear radiance)"
	@echo "  segmentation/      the 3 materials: material_*.dam (one DAM each), weights/*.exr, preview/*.png (which pixel is which)"
	@echo "  model.dam          one deep appearance map fitted to the whole object (safetensors + JSON metadata)"
	@echo "  predicted.dam      the DAM predicted from 4 train views by the shipped predictor, refined 300 steps"
	@echo "  renders/*.exr      the fitted model rendered into the test (novel) views (linear EXR)"
	@echo "  evaluation.json    mean and per-frame DSSIM of the models, the segmentation, RM++ and RM, same and novel view"
	@echo "  evaluation.png     per-frame DSSIM sorted, one curve per method"
	@echo "  export/            the 3 materials on a new shape (torus.obj, labels carried over): frames/*.exr linear,"
	@echo "                     display/*.png sRGB, turntable.mp4 (H.264)"
	@echo "  viewer.html        model.dam on the torus in the browser (WebGL)"

# The suite on every core: pytest-xdist workers (CI has 2), each with torch on its share of the
# cores (tests/conftest.py). --dist loadgroup --no-loadscope-reorder hands the tests out one at a
# time, in collection order with the tests marked slow first (tests/conftest.py says why not by
# group); the 25 slowest tests are listed at the end. `make test TEST_JOBS=0` runs it in one process.
TEST_JOBS ?= auto
test: venv $(NS_READER)/.installed $(BLENDER_VENV)/.installed
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadgroup --no-loadscope-reorder --durations=25

# The wheel as users get it: build, install into a scratch venv, run damcap from outside the tree
wheel-check: venv
	bash .ci/wheel_check.sh $(VENV)

# Slow studies (never in CI): results in bench/results/*.json and bench/*.md
BENCHES ?= dam_core export hyper segment registration_sparse registration_gt clipped
bench: venv
	@set -e; for b in $(BENCHES); do echo "== python -m bench.$$b"; $(PY) -m bench.$$b; done

# The demo's export against the path-traced truth (bench/export_truth.md; runs the demo first)
export-truth: demo
	$(PY) -m bench.export_truth --demo $(DEMO_OUT) --transfer-bound

# The paper's Tables 1 and 2 (renders the held-out corpora first when missing; resumable)
SMALL := bench/.cache/synth_small
SEGMENT := bench/.cache/synth_segment
CAPE := bench/.cache/reconstruct/realworld/cape-8-256
tables: venv
	$(VENV)/bin/damcap synth-set $(SMALL) --preset small
	$(VENV)/bin/damcap synth-set $(SEGMENT) --preset segment
	$(VENV)/bin/damcap tables --table1 $(SMALL) --table1 $(SEGMENT) --out bench/tables
	@test -f $(CAPE)/transforms.json || $(PY) -m bench.reconstruct --part realworld
	$(VENV)/bin/damcap tables --table2 $(CAPE) --out bench/tables

clean:
	rm -rf $(VENV) $(BLENDER_VENV) $(DEMO_OUT)
