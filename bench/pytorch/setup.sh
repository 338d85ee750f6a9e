#!/usr/bin/env bash
# Installs CPU-only PyTorch into bench/pytorch/.venv (ignored by git) for bench/pytorch/cem.py.
#
# PyTorch's own CPU wheel index (a small CPU-only build) is tried first. Where it cannot be
# reached, PyPI's torch is installed with its dependencies: PyPI's Linux wheel links the CUDA
# runtime libraries (nvidia-* packages, a few GB) and will not import without them, although the
# benchmark never touches a GPU. Usage: bench/pytorch/setup.sh (PYTHON=python3.x to choose).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
python="${PYTHON:-python3}"
venv="$here/.venv"
if [[ ! -x "$venv/bin/python" ]]; then
    "$python" -m venv "$venv"
fi
pip=("$venv/bin/python" -m pip install --disable-pip-version-check --quiet)
if ! "${pip[@]}" --index-url https://download.pytorch.org/whl/cpu torch 2>/dev/null; then
    echo "PyTorch's CPU index is unreachable: installing PyPI's torch (with its CUDA libraries)" >&2
    "${pip[@]}" torch
fi
"$venv/bin/python" -c 'import torch; print("torch", torch.__version__, "CPU threads", torch.get_num_threads())'
