#!/usr/bin/env bash
# The wheel as users get it: build it from the working tree, install it into a scratch venv and run
# damcap from there, in a folder outside the repository (so the source tree is not on the path).
#
# Offline and fast: the wheel is built with the project venv's setuptools (no build isolation) and
# installed without dependencies; the scratch venv sees the project venv's installed packages
# through a plain .pth path line (which does not run the project's editable-install hook, so
# `damcap` can only come from the wheel). Usage: .ci/wheel_check.sh [VENV] (default .venv).
set -euo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
VENV="$(cd "$REPO" && cd "${1:-.venv}" && pwd)"
PY="$VENV/bin/python"
[ -x "$PY" ] || { echo "error: $PY not found (run make venv first)" >&2; exit 1; }

WORK="$(mktemp -d "${TMPDIR:-/tmp}/damcap-wheel-check.XXXXXX")"
trap 'rm -rf "$WORK"' EXIT
start=$SECONDS
step() { echo "== wheel-check [$((SECONDS - start))s] $*"; }

step "build the wheel"
# a copy of what the distribution is built from (keeps build/ and *.egg-info out of the tree)
ROOMS="$(cd "$REPO" && "$PY" -c 'import importlib.util as u
s = u.spec_from_file_location("damcap_setup", "setup.py"); m = u.module_from_spec(s); s.loader.exec_module(m)
print(*m.ROOMS)')"
mkdir -p "$WORK/src"
# shellcheck disable=SC2086  # ROOMS is a list of folder names
(cd "$REPO" && tar -cf - --exclude=__pycache__ --exclude='*.pyc' pyproject.toml setup.py README.md LICENSE damcap $ROOMS) \
  | tar -xf - -C "$WORK/src"
"$PY" -m pip wheel -q --no-deps --no-build-isolation --no-index -w "$WORK/dist" "$WORK/src"
WHEEL="$(ls "$WORK"/dist/damcap-*.whl)"
echo "built $(basename "$WHEEL") ($(du -k "$WHEEL" | cut -f1) KiB)"

step "install it into a scratch venv"
"$PY" -m venv --without-pip "$WORK/venv"
SCRATCH_SITE="$("$WORK/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
"$PY" -c 'import sysconfig; print(*sorted({sysconfig.get_paths()[k] for k in ("purelib", "platlib")}), sep="\n")' \
  > "$SCRATCH_SITE/damcap_ci_dependencies.pth"
"$WORK/venv/bin/python" -m pip install -q --no-deps --no-index --ignore-installed "$WHEEL"
DAMCAP="$WORK/venv/bin/damcap"

mkdir -p "$WORK/run"
cd "$WORK/run"
unset PYTHONPATH
step "damcap comes from the wheel"
"$WORK/venv/bin/python" - "$WORK/venv" <<'EOF'
import sys
from pathlib import Path

import damcap
import damcap.appearance
import damcap.common

scratch = Path(sys.argv[1]).resolve()
for module in (damcap, damcap.common, damcap.appearance):
    where = Path(module.__file__).resolve()
    if scratch not in where.parents:
        sys.exit(f"error: {module.__name__} imported from {where}, not from the installed wheel in {scratch}")
if damcap.__version__ in ("", "0+unknown"):
    sys.exit(f"error: damcap.__version__ is {damcap.__version__!r}")
missing = [name for name in damcap.__all__ if getattr(damcap, name, None) is None]
if missing:
    sys.exit(f"error: damcap's public API names that do not resolve: {missing}")
print(f"damcap {damcap.__version__} from {Path(damcap.__file__).parent}")
EOF
VERSION="$("$WORK/venv/bin/python" -c 'import damcap; print(damcap.__version__)')"

step "damcap --version"
out="$("$DAMCAP" --version)"
echo "$out"
grep -qF "$VERSION" <<<"$out" || { echo "error: damcap --version printed no $VERSION" >&2; exit 1; }

step "damcap closed-form, inspect, predict (shipped predictor), view (HTML template)"
"$DAMCAP" closed-form capture --views 4 --train-views 2 --res 16 >/dev/null
"$DAMCAP" inspect capture
"$DAMCAP" predict capture -o predicted.dam
"$DAMCAP" view predicted.dam -o page.html
test -s page.html || { echo "error: damcap view wrote no page.html" >&2; exit 1; }
step "passed"
