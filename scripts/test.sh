#!/usr/bin/env bash
# Set up (once) and run every check: lint, format, types (mypy, zero errors), then the test
# suite (the browser tests included).
# Installs Debian's chromium when it is missing (needs root or sudo), as CI does.
source "$(dirname "$0")/_env.sh" "[test]"
if [ ! -x /usr/bin/chromium ]; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi
"$VPY" -m ruff check mistool tests scripts
"$VPY" -m ruff format --check mistool tests scripts
"$VPY" -m mypy  # checks mistool/ with the settings in pyproject.toml
set +e
"$VPY" -m pytest -n 2 "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "scripts/test.sh: pytest collected no tests; that is a failure" >&2
  exit 1
fi
exit "$rc"
