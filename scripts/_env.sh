# Sourced by scripts/test, scripts/demo and scripts/bench: create or refresh
# .venv (Python 3.11) with the pinned requirements and the package installed
# in editable mode. Re-installs only when requirements.txt or setup.py change.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3.11}"
if ! command -v "$PY" >/dev/null 2>&1; then
  echo "has_control: $PY not found; install Python 3.11 or set PYTHON=/path/to/python3.11" >&2
  exit 2
fi
if [ ! -x "$VENV/bin/python" ]; then
  echo "has_control: creating $VENV" >&2
  "$PY" -m venv "$VENV"
fi
STAMP="$VENV/.has_control-installed"
WANT="$(cat "$ROOT/requirements.txt" "$ROOT/setup.py" "$ROOT/setup.cfg" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  echo "has_control: installing dependencies into $VENV" >&2
  "$VENV/bin/python" -m pip install --quiet --upgrade pip >&2
  "$VENV/bin/python" -m pip install --quiet -r "$ROOT/requirements.txt" >&2
  "$VENV/bin/python" -m pip install --quiet --no-deps -e "$ROOT" >&2
  echo "$WANT" > "$STAMP"
fi
export PATH="$VENV/bin:$PATH"
# numba's on-disk cache lives beside the sources (ignored by git)
export NUMBA_CACHE_DIR="${NUMBA_CACHE_DIR:-$ROOT/.venv/numba-cache}"
cd "$ROOT"
