#!/usr/bin/env bash
# One entry point for a fresh machine: creates .venv on first use, installs zernet into it,
# then runs `demo`, `test`, or any zernet subcommand.
#   bash scripts/run.sh demo     train + evaluate on the built-in data, print metrics and pictures
#   bash scripts/run.sh test     run the test suite
#   bash scripts/run.sh lint     ruff check and ruff format --check (configured in pyproject.toml)
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=.venv
PY="$VENV/bin/python"
STAMP="$VENV/.zernet-installed"
if [ ! -x "$PY" ]; then
    python3 -m venv "$VENV"
fi
# Reinstall only when the dependency list changed.
WANT="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
    "$PY" -m pip install --quiet --upgrade pip
    # The CPU build of torch first: a bare `torch` requirement would pull a multi-GB CUDA build.
    "$PY" -c "import torch" 2>/dev/null || "$PY" -m pip install --quiet "torch==2.13.0"
    "$PY" -m pip install --quiet -e ".[dev,bodies]"
    echo "$WANT" > "$STAMP"
fi
cmd="${1:-demo}"
shift || true
case "$cmd" in
    test) exec "$PY" -m pytest "$@" ;;
    lint) "$VENV/bin/ruff" check . && exec "$VENV/bin/ruff" format --check . ;;
    *) exec "$VENV/bin/zernet" "$cmd" "$@" ;;
esac
