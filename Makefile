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
# novel views, evaluate all of them, then put the three materials on a new shape in three parts
# (a lidded pot damcap generates: body, lid, handle, its OBJ material groups) as a turntable and
# in the viewer page, and as Blender materials. On the bundled photos the segmentation's
# material_2 is the red plastic, material_0 the gold and material_1 the aluminium: the body takes
# the red, the lid the gold, the handle the aluminium (POT_MATERIALS, in the pot's part order;
# the order that leaves the least of each part facing normals the photos never showed its
# material at, bench/demo.md).
SEG := $(DEMO_OUT)/segmentation
POT_MATERIALS = $(SEG)/material_2.dam $(SEG)/material_0.dam $(SEG)/material_1.dam
demo: venv
	$(DAMCAP) reconstruct $(PHOTOS)/images -o $(DEMO_OUT)/capture --masks $(PHOTOS)/masks --split spread --train-views 16
	$(DAMCAP) inspect $(DEMO_OUT)/capture
	$(DAMCAP) segment $(DEMO_OUT)/capture -o $(SEG) --materials 3
	$(DAMCAP) fit $(DEMO_OUT)/capture -o $(DEMO_OUT)/model.dam
	$(DAMCAP) predict $(DEMO_OUT)/capture -o $(DEMO_OUT)/predicted.dam --refine-steps 300
	$(DAMCAP) render $(DEMO_OUT)/model.dam $(DEMO_OUT)/capture -o $(DEMO_OUT)/renders --split test
	$(DAMCAP) evaluate $(DEMO_OUT)/capture --model $(DEMO_OUT)/model.dam --model $(DEMO_OUT)/predicted.dam --segmentation $(SEG) --json $(DEMO_OUT)/evaluation.json
	$(DAMCAP) shape pot $(DEMO_OUT)/pot.obj
	$(DAMCAP) export $(POT_MATERIALS) --mesh $(DEMO_OUT)/pot.obj -o $(DEMO_OUT)/export --views 24 --resolution 256 --video
	$(DAMCAP) view $(POT_MATERIALS) --mesh $(DEMO_OUT)/pot.obj -o $(DEMO_OUT)/viewer.html
	$(DAMCAP) export $(POT_MATERIALS) --mesh $(DEMO_OUT)/pot.obj --format blender -o $(DEMO_OUT)/blender
	@echo
	@echo "demo results are in $(DEMO_OUT)/:"
	@echo "  capture/           the capture folder reconstructed from $(PHOTOS)/images (cameras, geometry, linear radiance)"
	@echo "  segmentation/      the 3 materials: material_*.dam (one DAM each), weights/*.exr, preview/*.png (which pixel is which)"
	@echo "  model.dam          one deep appearance map fitted to the whole object (safetensors + JSON metadata)"
	@echo "  predicted.dam      the DAM predicted from 4 train views by the shipped predictor, refined 300 steps"
	@echo "  renders/*.exr      the fitted model rendered into the test (novel) views (linear EXR)"
	@echo "  evaluation.json    mean and per-frame DSSIM of the models, the segmentation, RM++ and RM, same and novel view"
	@echo "  evaluation.png     per-frame DSSIM sorted, one curve per method"
	@echo "  pot.obj, pot.mtl   a new shape in three parts (OBJ material groups body, lid, handle), made by damcap shape pot"
	@echo "  export/            the 3 materials on the pot (body: material_2, lid: material_0, handle: material_1):"
	@echo "                     frames/*.exr linear, display/*.png sRGB, turntable.mp4 (H.264)"
	@echo "  blender/           the 3 materials as OSL shaders, the pot, and damcap_materials.py that builds them in Blender"
	@echo
	@echo "look at: $(DEMO_OUT)/viewer.html (the 3 materials on the pot in the browser, WebGL 2: drag to turn, wheel to zoom)"
	@echo "         $(DEMO_OUT)/export/turntable.mp4 (the pot turning, rendered by damcap)"
	@echo "         $(DEMO_OUT)/blender/damcap_materials.py (run it in Blender: the pot with the 3 materials, rendered in Cycles)"

# The suite on every core: pytest-xdist workers (CI has 2), each with torch on its share of the
# cores (tests/conftest.py). --dist loadgroup --no-loadscope-reorder hands the tests out in
# collection order, the tests marked slow and the modules with a module-scoped fixture first, each
# such module as one unit (its fixture built once), every other test one at a time (tests/conftest.py's
# pytest_xdist_make_scheduler); the 25 slowest tests are listed at the end. `make test TEST_JOBS=0` runs it in one process.
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
