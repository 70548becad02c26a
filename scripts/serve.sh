#!/usr/bin/env bash
# Set up (once) and replay a sequence in the browser: scripts/serve.sh [DIR] [mistool serve options]
# With no DIR it serves the bundled sample_masks/.
source "$(dirname "$0")/_env.sh" ""
exec "$ROOT/.venv/bin/mistool" serve "$@"
