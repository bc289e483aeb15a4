# All set-up lives here: a fresh machine needs only python3 (3.11) and make.
VENV  ?= .venv
PY    := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

.PHONY: install browser demo test bench clean
APT_STAMP := $(VENV)/.apt-stamp
SUDO  := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e ".[dev]"
	$(PY) -m pip install -q -c constraints.txt --no-build-isolation deepspeed==0.19.8
	touch $(STAMP)

install: $(STAMP)

# Debian's Chromium + ChromeDriver for the review-page test (nothing is downloaded by the tests themselves).
$(APT_STAMP): | $(STAMP)
	command -v chromium >/dev/null && command -v chromedriver >/dev/null || \
	  ($(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq chromium chromium-driver >/dev/null)
	touch $(APT_STAMP)

browser: $(APT_STAMP)

# The main job on the embedded default, all on CPU: PyBullet episodes (success/failure pairs) -> keyframe strips
# -> the VQA dataset (512x512 grids of 8 keyframes, 128 px cells, 256 visual tokens, keep the tiny model fast)
# -> the tiny Qwen3-VL trained from scratch -> the bench table with majority/blind baselines -> one infer.py diagnosis.
DEMO_EPISODES ?= 200
DEMO_EPOCHS   ?= 10
DEMO_GRID     := grid.width=512 grid.height=512 grid.max_frames=8 grid.columns=4
demo: $(STAMP)
	$(PY) scripts/generate.py backend=pybullet num_episodes=$(DEMO_EPISODES) out_dir=outputs/demo_shards seed=0 workers=2
	$(PY) scripts/render_strips.py outputs/demo_shards outputs/demo_strips
	$(PY) scripts/build_dataset.py shards=outputs/demo_shards out_dir=outputs/demo_dataset $(DEMO_GRID)
	$(PY) train.py preset=tiny dataset_dir=outputs/demo_dataset output_dir=outputs/demo_train epochs=$(DEMO_EPOCHS)
	$(PY) scripts/evaluate.py model=outputs/demo_train/final dataset_dir=outputs/demo_dataset split=test
	$(PY) infer.py --grid "$$(ls outputs/demo_dataset/images/*.png | head -1)" --task "a laboratory task"

test: $(STAMP) $(APT_STAMP)
	LABROBFAIL_REQUIRE_BROWSER=1 $(PY) -m pytest -q tests

bench: $(STAMP)
	$(PY) scripts/bench_grid.py
	$(PY) scripts/bench_sim.py
	$(PY) scripts/bench_train.py
	$(PY) scripts/bench_infer.py

clean:
	rm -rf outputs
