#!/usr/bin/env bash
# Installs MuJoCo 3.17.0 (the version mujoco-rs 7 binds) into a project-local folder.
#
# Debian's MuJoCo (2.2.2) is too old for mujoco-rs, and only the package registries are
# reachable, so the official shared library is taken from PyPI's `mujoco==3.17.0` wheel:
# pip downloads the wheel, we extract `libmujoco.so.3.17.0` into `.mujoco/lib/` and link
# `libmujoco.so` beside it. `.cargo/config.toml` points MUJOCO_DYNAMIC_LINK_DIR there, and
# sim-bridge's build script adds an rpath so binaries run without LD_LIBRARY_PATH.
#
# Idempotent: a second run with the library in place does nothing.
# Usage: deploy/install-mujoco.sh [DEST_DIR]   (default: <repo>/.mujoco)
set -euo pipefail

VERSION=3.17.0
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DEST="${1:-$ROOT/.mujoco}"
LIB_DIR="$DEST/lib"
LIB="$LIB_DIR/libmujoco.so.$VERSION"

if [[ -f "$LIB" && -L "$LIB_DIR/libmujoco.so" ]]; then
    echo "MuJoCo $VERSION already installed in $LIB_DIR"
    exit 0
fi

PYTHON="${PYTHON:-}"
if [[ -z "$PYTHON" ]]; then
    for candidate in python3 python; do
        if command -v "$candidate" >/dev/null 2>&1 && "$candidate" -m pip --version >/dev/null 2>&1; then
            PYTHON="$candidate"
            break
        fi
    done
fi
if [[ -z "$PYTHON" ]]; then
    cat >&2 <<MSG
error: pip is needed to fetch MuJoCo $VERSION from PyPI, and no 'python3 -m pip' was found.
  Debian/Ubuntu: sudo apt-get install python3-pip
  Or install MuJoCo $VERSION yourself and run cargo with
  MUJOCO_DYNAMIC_LINK_DIR=/path/to/mujoco-$VERSION/lib
MSG
    exit 1
fi

case "$(uname -m)" in
    x86_64) PLATFORMS=(manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64) ;;
    aarch64) PLATFORMS=(manylinux_2_28_aarch64 manylinux_2_27_aarch64 manylinux_2_17_aarch64 manylinux2014_aarch64) ;;
    *) echo "error: no MuJoCo wheel for $(uname -m)" >&2; exit 1 ;;
esac
PLATFORM_ARGS=()
for p in "${PLATFORMS[@]}"; do PLATFORM_ARGS+=(--platform "$p"); done

WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT

echo "Downloading the mujoco==$VERSION wheel from PyPI ..."
# The wheel's ABI tag does not matter: we only take the C library out of it.
"$PYTHON" -m pip download --quiet --no-deps --only-binary=:all: "${PLATFORM_ARGS[@]}" \
    --python-version 3.12 --implementation cp -d "$WORK" "mujoco==$VERSION"
WHEEL="$(ls "$WORK"/mujoco-"$VERSION"-*.whl | head -n 1)"

mkdir -p "$LIB_DIR"
"$PYTHON" - "$WHEEL" "$LIB_DIR" "$VERSION" <<'PY'
import sys, zipfile, os
wheel, dest, version = sys.argv[1], sys.argv[2], sys.argv[3]
name = f"libmujoco.so.{version}"
with zipfile.ZipFile(wheel) as z:
    members = [m for m in z.namelist() if m.endswith("/" + name)]
    if not members:
        sys.exit(f"error: {name} not found in {wheel}")
    tmp = os.path.join(dest, name + ".part")
    with z.open(members[0]) as src, open(tmp, "wb") as dst:
        dst.write(src.read())
    os.chmod(tmp, 0o755)
    os.replace(tmp, os.path.join(dest, name))
PY
ln -sfn "libmujoco.so.$VERSION" "$LIB_DIR/libmujoco.so"
echo "MuJoCo $VERSION installed in $LIB_DIR"
