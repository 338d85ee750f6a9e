#!/usr/bin/env bash
# Installs the Debian packages the build and the tests need, when their commands are missing:
#   protoc   (protobuf-compiler)  the etcd client's build compiles etcd's gRPC definitions
#   etcd     (etcd-server)        the fleet's ownership store; the fleet tests start one
# Single daemons do not need etcd at run time; only the build needs protoc.
#
# Idempotent: commands already on PATH are left alone. Needs root (or sudo) and apt-get.
# Usage: deploy/install-debian-packages.sh protoc [etcd]
set -euo pipefail

declare -A PACKAGE=([protoc]=protobuf-compiler [etcd]=etcd-server)
missing=()
for command in "$@"; do
    package="${PACKAGE[$command]:-}"
    if [[ -z "$package" ]]; then
        echo "error: unknown command '$command' (known: ${!PACKAGE[*]})" >&2
        exit 2
    fi
    command -v "$command" >/dev/null 2>&1 || missing+=("$package")
done
if [[ ${#missing[@]} -eq 0 ]]; then
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "error: install ${missing[*]} (Debian/Ubuntu package names) with your package manager" >&2
    exit 1
fi
SUDO=""
if [[ $(id -u) -ne 0 ]]; then
    command -v sudo >/dev/null 2>&1 || { echo "error: run as root, or install sudo, to install ${missing[*]}" >&2; exit 1; }
    SUDO=sudo
fi
echo "installing ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
