#!/usr/bin/env bash
# One entry point for the quick start.
#   bash run.sh main [ARGS]   install (if needed) and run the main job
#   bash run.sh test [ARGS]   install (if needed) and run the default test suite
#   bash run.sh install       install only
set -euo pipefail
cd "$(dirname "$0")"
VENV=${HEC_VENV:-.venv}
PY=${PYTHON:-python3}

install() {
  local stamp="$VENV/.hec_installed"
  if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
  fi
  if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    "$VENV/bin/python" -m pip install -q --upgrade pip
    "$VENV/bin/python" -m pip install -q -e ".[test]"
    touch "$stamp"
  fi
}

cmd=${1:-test}
shift || true
case "$cmd" in
  install) install ;;
  main)
    install
    # a fresh run folder each time (a run never writes into an existing one without --overwrite)
    exec "$VENV/bin/python" experiments/catching.py \
      --out "${HEC_OUT:-runs/catching-$(date -u +%Y%m%dT%H%M%SZ)}" "$@"
    ;;
  test)
    install
    # Two worker processes, one test file each at a time (module fixtures and their compiles
    # stay in one process); HEC_TEST_WORKERS=0 or `-n 0` runs serially.
    exec "$VENV/bin/python" -m pytest -n "${HEC_TEST_WORKERS:-2}" --dist loadfile --durations=12 "$@"
    ;;
  *) echo "usage: bash run.sh {main|test|install} [ARGS]" >&2; exit 2 ;;
esac
