# objcam: `make demo` (set up, make the bundled synthetic scene, run everything) and `make test`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
OBJCAM := $(BIN)/objcam
STAMP  := $(VENV)/.objcam-setup
CAPTURE ?= demo/capture
ARGS   ?=
DEMO_SYNTH_ARGS ?= --object bunny --envmap forest

STAGES := scene transport solve evaluate analysis report

.PHONY: setup demo test bench status run clean-demo $(STAGES)

setup: $(STAMP)
$(STAMP): pyproject.toml requirements.lock scripts/setup.sh
	@PYTHON=$(PYTHON) bash scripts/setup.sh

demo: $(STAMP)
	@[ -f demo/capture/capture.toml ] || $(OBJCAM) synth demo/capture $(DEMO_SYNTH_ARGS)
	$(OBJCAM) run demo/capture $(ARGS)
	$(OBJCAM) evaluate demo/capture --quiet
	@echo "report:  demo/capture/objcam/report/index.html (open it in a browser)"
	@echo "outputs: demo/capture/objcam/solve/t0/ (envmap.exr, prediction.exr, residual.exr, *.png)"
	@echo "         demo/capture/objcam/evaluate/ (metrics.json, t0/overview.png: target | truth | recovered)"

test: $(STAMP)
	$(BIN)/python -m pytest -q $(ARGS)

bench: $(STAMP)
	$(BIN)/python -m bench.run $(ARGS)

run: $(STAMP)
	$(OBJCAM) run $(CAPTURE) $(ARGS)

status: $(STAMP)
	$(OBJCAM) status $(CAPTURE)

$(STAGES): $(STAMP)
	$(OBJCAM) $@ $(CAPTURE) $(ARGS)

clean-demo:
	rm -rf demo
