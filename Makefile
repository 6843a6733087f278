# fmusa: build the ScrewVertebra FMU, run the study, test, benchmark.
# GNU make. `make test` and `make sweep` are the two entry points; both build what they need.

SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

FMU := dist/ScrewVertebra.fmu
FMU_BUILD := build/fmu
FMU_SO := $(FMU_BUILD)/binaries/linux64/ScrewVertebra.so
SRC_STAMP := build/.fmu-sources
FMU_C := fmu/fmi2.c fmu/model.c fmu/solver.c sv_generated.c
# The model's equations: C generated from the Modelica source by fmu/codegen.py (pymoca and CasADi, the `fmu`
# extra), carried in the FMU's sources with the hand-written FMI layer and solver.
FMU_GEN := $(FMU_BUILD)/sources/sv_generated.c $(FMU_BUILD)/sources/sv_generated.h $(FMU_BUILD)/sources/sv_model.h
FMU_SRC := $(wildcard fmu/*.c) $(wildcard fmu/*.h)
FMI_HEADERS := fmi2Functions.h fmi2FunctionTypes.h fmi2TypesPlatform.h
CC := gcc
CFLAGS := -std=c99 -O3 -fPIC -shared -Wall -Wextra -fvisibility=hidden
# win64: the same sources cross-compiled with Debian's gcc-mingw-w64-x86-64, where it is installed
# (`MINGW_CC=` builds linux64 only). fmi2Functions.h exports the fmi2 functions with
# __declspec(dllexport) under _WIN32; -static-libgcc keeps the DLL's imports to Windows system DLLs
# (KERNEL32, msvcrt).
FMU_DLL := $(FMU_BUILD)/binaries/win64/ScrewVertebra.dll
MINGW_CC ?= x86_64-w64-mingw32-gcc
MINGW_CFLAGS := -std=c99 -O3 -shared -Wall -Wextra -static-libgcc -s -Wl,--no-insert-timestamp
HAVE_MINGW := $(if $(MINGW_CC),$(shell command -v $(MINGW_CC) 2>/dev/null))
FMU_BINARIES := $(FMU_SO) $(if $(HAVE_MINGW),$(FMU_DLL))

.PHONY: all fmu modelica-venv sweep test identifiability slow bench diagnose docs reference clean
.DELETE_ON_ERROR:

all: fmu

# ---------------------------------------------------------------- virtual environment
$(STAMP): pyproject.toml
	test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/pip install -e '.[test,fmu]'
	touch $@

$(VENV): $(STAMP)

# ---------------------------------------------------------------- second Modelica tool
# tests/test_second_tool.py simulates modelica/ScrewVertebra.mo with a second tool, the pure-Python `modelica`
# package (tests/second_tool/requirements.txt pins it), which needs Python >= 3.12: its own venv, built from
# the first interpreter of $(MODELICA_PYTHON) and pyenv's 3.12+ (a pyenv shim that cannot run counts as
# none). Without one the recipe says how to get one and the test skips, saying so too.
MODELICA_PYTHON ?= python3.12
MODELICA_VENV := build/modelica-venv
MODELICA_STAMP := $(MODELICA_VENV)/.installed
MODELICA_REQ := tests/second_tool/requirements.txt

$(MODELICA_STAMP): $(MODELICA_REQ)
	@py=; for c in $(MODELICA_PYTHON) python3.13 $${PYENV_ROOT:-$$HOME/.pyenv}/versions/3.1[2-9].*/bin/python; do \
	  if "$$c" -c 'import sys; sys.exit(sys.version_info < (3, 12))' >/dev/null 2>&1; then py=$$c; break; fi; \
	done; \
	if [ -z "$$py" ]; then \
	  echo "NOTE: no Python >= 3.12 for the second Modelica tool (tests/test_second_tool.py will skip): install one" \
	       "(pyenv install 3.12, or apt-get install python3.12) or name it with MODELICA_PYTHON=/path/to/python3.12"; \
	  exit 0; \
	fi; \
	echo "second Modelica tool: $$("$$py" -V) -> $(MODELICA_VENV)"; \
	rm -rf $(MODELICA_VENV) && "$$py" -m venv $(MODELICA_VENV) && \
	$(MODELICA_VENV)/bin/pip install -q -r $(MODELICA_REQ) && touch $@

modelica-venv: $(MODELICA_STAMP)

# ---------------------------------------------------------------- FMU
# The FMU carries its C sources (plus the FMI 2 headers taken from fmpy) so that other tools, or
# fmpy.build.build_platform_binary, can rebuild the binary from them.
# modelDescription.xml and variables.h are derived from the public declarations of the Modelica model,
# parsed with modelica-builder (the fmu extra): the venv's python, order-only on the venv like the headers.
$(FMU_BUILD)/modelDescription.xml $(FMU_BUILD)/sources/variables.h &: fmu/generate.py modelica/ScrewVertebra.mo | $(STAMP)
	$(VPY) fmu/generate.py $(FMU_BUILD)

$(FMU_GEN) &: fmu/codegen.py fmu/generate.py modelica/ScrewVertebra.mo | $(STAMP)
	$(VPY) fmu/codegen.py $(FMU_BUILD)/sources

# The headers come from the installed fmpy: order-only on the venv, so reinstalling it does not
# force a rebuild.
$(SRC_STAMP): $(FMU_SRC) $(FMU_GEN) $(FMU_BUILD)/sources/variables.h | $(STAMP)
	mkdir -p $(FMU_BUILD)/sources
	cp $(FMU_SRC) $(FMU_BUILD)/sources/
	cc_dir=$$($(VPY) -c 'import fmpy, os; print(os.path.join(os.path.dirname(fmpy.__file__), "c-code"))') && \
	  for h in $(FMI_HEADERS); do cp "$$cc_dir/$$h" $(FMU_BUILD)/sources/; done
	touch $@

$(FMU_SO): $(SRC_STAMP)
	mkdir -p $(dir $@)
	$(CC) $(CFLAGS) -I$(FMU_BUILD)/sources -o $@ $(addprefix $(FMU_BUILD)/sources/,$(notdir $(FMU_C))) -lm

$(FMU_DLL): $(SRC_STAMP)
	mkdir -p $(dir $@)
	$(MINGW_CC) $(MINGW_CFLAGS) -I$(FMU_BUILD)/sources -o $@ $(addprefix $(FMU_BUILD)/sources/,$(notdir $(FMU_C)))

# Without the cross compiler the FMU carries linux64 only (and no win64 DLL left from an older build).
$(FMU): $(FMU_BINARIES) $(FMU_BUILD)/modelDescription.xml
	$(if $(HAVE_MINGW),,@echo "NOTE: no win64 binary in $@: $(if $(MINGW_CC),the cross compiler $(MINGW_CC) was not found (apt-get install gcc-mingw-w64-x86-64),MINGW_CC is empty)")
	$(if $(HAVE_MINGW),,rm -rf $(FMU_BUILD)/binaries/win64)
	mkdir -p $(dir $@)
	rm -f $@
	if command -v zip >/dev/null 2>&1; then \
	  cd $(FMU_BUILD) && zip -q -r -X $(abspath $@) modelDescription.xml binaries sources; \
	else \
	  cd $(FMU_BUILD) && $(PYTHON) -m zipfile -c $(abspath $@) modelDescription.xml binaries sources; \
	fi

# ---------------------------------------------------------------- interface element FMU
# The same generators (fmu/generate.py, fmu/codegen.py) on modelica/InterfaceElement.mo, the shared FMI layer
# fmu/fmi2.c (with model exchange and FMU state, switched on by fmu/element/model.h) and the element's glue.
EL_FMU := dist/InterfaceElement.fmu
EL_BUILD := build/element
EL_MO := modelica/InterfaceElement.mo
EL_SO := $(EL_BUILD)/binaries/linux64/InterfaceElement.so
EL_DLL := $(EL_BUILD)/binaries/win64/InterfaceElement.dll
EL_STAMP := build/.element-sources
EL_C := fmi2.c element.c el_generated.c
EL_GEN := $(EL_BUILD)/sources/el_generated.c $(EL_BUILD)/sources/el_generated.h $(EL_BUILD)/sources/el_model.h
EL_SRC := fmu/fmi2.c $(wildcard fmu/element/*.c) $(wildcard fmu/element/*.h)
EL_BINARIES := $(EL_SO) $(if $(HAVE_MINGW),$(EL_DLL))

$(EL_BUILD)/modelDescription.xml $(EL_BUILD)/sources/variables.h &: fmu/generate.py $(EL_MO) | $(STAMP)
	$(VPY) fmu/generate.py $(EL_BUILD) $(EL_MO)

$(EL_GEN) &: fmu/codegen.py $(EL_MO) | $(STAMP)
	$(VPY) fmu/codegen.py $(EL_BUILD)/sources $(EL_MO)

$(EL_STAMP): $(EL_SRC) $(EL_GEN) $(EL_BUILD)/sources/variables.h | $(STAMP)
	mkdir -p $(EL_BUILD)/sources
	cp $(EL_SRC) $(EL_BUILD)/sources/
	cc_dir=$$($(VPY) -c 'import fmpy, os; print(os.path.join(os.path.dirname(fmpy.__file__), "c-code"))') && \
	  for h in $(FMI_HEADERS); do cp "$$cc_dir/$$h" $(EL_BUILD)/sources/; done
	touch $@

$(EL_SO): $(EL_STAMP)
	mkdir -p $(dir $@)
	$(CC) $(CFLAGS) -I$(EL_BUILD)/sources -o $@ $(addprefix $(EL_BUILD)/sources/,$(EL_C)) -lm

$(EL_DLL): $(EL_STAMP)
	mkdir -p $(dir $@)
	$(MINGW_CC) $(MINGW_CFLAGS) -I$(EL_BUILD)/sources -o $@ $(addprefix $(EL_BUILD)/sources/,$(EL_C))

$(EL_FMU): $(EL_BINARIES) $(EL_BUILD)/modelDescription.xml
	$(if $(HAVE_MINGW),,rm -rf $(EL_BUILD)/binaries/win64)
	mkdir -p $(dir $@)
	rm -f $@
	if command -v zip >/dev/null 2>&1; then \
	  cd $(EL_BUILD) && zip -q -r -X $(abspath $@) modelDescription.xml binaries sources; \
	else \
	  cd $(EL_BUILD) && $(PYTHON) -m zipfile -c $(abspath $@) modelDescription.xml binaries sources; \
	fi

fmu: $(FMU) $(EL_FMU)

# ---------------------------------------------------------------- study, tests, benchmark
sweep: $(STAMP) $(FMU)
	$(VENV)/bin/fmusa sweep studies/paper.yaml --out out/paper

test: $(STAMP) $(FMU) $(EL_FMU) $(MODELICA_STAMP)
	$(VENV)/bin/pytest -q -p no:cacheprovider --durations=30 tests

# The whole identifiability table through the FMU (`make test` runs a representative subset of its cells).
identifiability: $(STAMP) $(FMU)
	$(VENV)/bin/pytest -q -p no:cacheprovider --run-slow tests/test_identifiability.py

# Every test marked slow (kept out of `make test`): the identifiability cells and hidden-effect cells it skips.
slow: $(STAMP) $(FMU) $(EL_FMU)
	$(VENV)/bin/pytest -q -p no:cacheprovider --run-slow -m slow tests

# The diagnosis of the real C6/C7 shear tests (data/shear-c67) against the authors' own analysis.
diagnose: $(STAMP) $(FMU)
	$(VENV)/bin/fmusa diagnose-shear --data data/shear-c67 --out out/diagnose

bench: $(STAMP) $(FMU)
	$(VPY) -m fmusa.bench --out out/bench/bench.json

# ---------------------------------------------------------------- documentation
# The site (mkdocs.yml, docs/) into out/site: --strict turns every warning, a broken link or anchor among
# them, into an error. The generated pages (study file keys, the model, errors, API) and the figures are
# made during the build by docs/_gen/ from the code and the FMU; docs/assets/tour-pullout.png, the README's
# one figure, is redrawn by the same `fmusa pullout` call the README shows. mkdocs stays below 2.0
# (pyproject's docs extra), so Material's notice about MkDocs 2.0 is switched off.
DOCS_STAMP := $(VENV)/.installed-docs

$(DOCS_STAMP): pyproject.toml | $(STAMP)
	$(VENV)/bin/pip install -e '.[test,docs]'
	touch $@

# The generated pages that are committed (study keys, model, troubleshooting, the identifiability table in
# docs/diagnosing.md), so that they read on the repository page: rewritten from the code (docs/_gen/reference.py);
# tests/test_docs.py and the docs build fail when one is out of date.
reference: $(STAMP)
	$(VPY) docs/_gen/reference.py

docs: $(DOCS_STAMP) $(FMU)
	$(VENV)/bin/fmusa pullout --out build/docs/tour
	cp build/docs/tour/pullout.png docs/assets/tour-pullout.png
	DISABLE_MKDOCS_2_WARNING=true NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --clean --site-dir out/site

clean:
	rm -rf build dist out
