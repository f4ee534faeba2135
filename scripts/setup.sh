#!/usr/bin/env bash
# Sets up objcam: Debian's libllvm19 (Mitsuba's fast llvm variant needs it) and chromium (the report's browser test),
# and .venv with pinned packages.
# Idempotent; prints one clear line and exits non-zero when something cannot be done.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

die() { echo "objcam setup: $*" >&2; exit 1; }

have_llvm19() { ldconfig -p 2>/dev/null | grep -qE 'libLLVM(-19\.so|\.so\.19)'; }
if ! have_llvm19; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  if command -v apt-get >/dev/null 2>&1 && { [ -z "$SUDO" ] || command -v sudo >/dev/null 2>&1; }; then
    echo "objcam setup: installing libllvm19 (for Mitsuba's llvm_ad_rgb variant)"
    { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libllvm19; } >/tmp/objcam-apt.log 2>&1 \
      || die "could not install libllvm19 with apt-get (log: /tmp/objcam-apt.log); install it by hand, or objcam falls back to Mitsuba's slow scalar_rgb variant"
  else
    echo "objcam setup: warning: libllvm19 missing and apt-get unavailable; Mitsuba will use the slow scalar_rgb variant" >&2
  fi
fi

# headless Chromium: the report's browser test (tests/test_report_browser.py) drives it over the DevTools pipe.
# Needed for `make test`: when it cannot be installed, that test fails and says so.
have_chromium() { command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1; }
if ! have_chromium; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  if command -v apt-get >/dev/null 2>&1 && { [ -z "$SUDO" ] || command -v sudo >/dev/null 2>&1; }; then
    echo "objcam setup: installing chromium (headless browser for the report test)"
    { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq chromium; } >/tmp/objcam-apt-chromium.log 2>&1 \
      || echo "objcam setup: warning: could not install chromium with apt-get (log: /tmp/objcam-apt-chromium.log); tests/test_report_browser.py will fail until it is installed" >&2
  else
    echo "objcam setup: warning: chromium missing and apt-get unavailable; tests/test_report_browser.py will fail until it is installed" >&2
  fi
fi

"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' \
  || die "Python 3.11+ is needed (found $($PY --version 2>&1)); set PYTHON=/path/to/python3.11"
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv || die "could not create .venv (on Debian: apt-get install python3-venv)"
fi
LOG=.venv/objcam-pip.log
.venv/bin/python -m pip install -q --upgrade pip >"$LOG" 2>&1 || true
echo "objcam setup: installing pinned packages into .venv (log: $LOG)"
.venv/bin/python -m pip install -q -r requirements.lock >>"$LOG" 2>&1 \
  || { tail -n 20 "$LOG" >&2; die "pip could not install requirements.lock (log: $LOG)"; }
.venv/bin/python -m pip install -q --no-deps -e . >>"$LOG" 2>&1 \
  || { tail -n 20 "$LOG" >&2; die "pip could not install objcam itself (log: $LOG)"; }
.venv/bin/python - <<'PY' || die "installed packages do not import; see the message above"
import mitsuba as mi, numpy, scipy, pycolmap, cv2, rawpy, pymeshlab, xatlas, OpenImageIO, zarr, objcam
v = "llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb"
try:
    mi.set_variant("llvm_ad_rgb"); v = "llvm_ad_rgb"
except Exception:
    mi.set_variant("scalar_rgb"); v = "scalar_rgb (slow: libllvm19 missing)"
print(f"objcam setup: ready (.venv, Mitsuba {mi.__version__} {v})")
PY
touch .venv/.objcam-setup
