# Shared set-up for scripts/serve.sh and scripts/test.sh (sourced, not run).
# Creates .venv in the repository (once) and installs mistool into it, editable, with the
# extras named by $1 ("" or "[test]"); skipped when pyproject.toml is unchanged.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  echo "setting up .venv (first run only) ..." >&2
  "$PY" -m venv .venv
fi
VPY="$ROOT/.venv/bin/python"
STAMP=".venv/.mistool-installed$1"
WANT="$(sha256sum < pyproject.toml | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  LOG=".venv/install.log"
  if ! { "$VPY" -m pip install -q --upgrade pip && "$VPY" -m pip install -q -e ".$1"; } \
      >"$LOG" 2>&1; then
    cat "$LOG" >&2
    echo "set-up failed: pip install -e \".$1\" (log above, also in $LOG)" >&2
    exit 1
  fi
  echo "$WANT" > "$STAMP"
fi
# numba's cache of the compiled kernels (mistool/kernels): compiled once (about a minute),
# again only after a kernel source changed (its stamp); otherwise a Python start
"$VPY" -m mistool.kernels --if-stale >/dev/null
