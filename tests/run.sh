#!/usr/bin/env bash
# The README's test command: all set-up (tests/install.sh), then the test suite, from the
# repository's root. Arguments go to pytest: `bash tests/run.sh -m "not browser and not slow"`
# is the fast loop, `bash tests/run.sh tests/geometry` one layer.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tests/install.sh
exec python -m pytest "$@"
