#!/usr/bin/env bash
# The README's test command: all set-up (tests/install.sh), then the test suite, from the
# repository's root. Arguments go to pytest: `bash tests/run.sh -m "not browser and not slow"`
# is the fast loop, `bash tests/run.sh tests/geometry` one layer.
set -euo pipefail
cd "$(dirname "$0")/.."
bash tests/install.sh
# Two worker processes, each test file whole to one (its module fixtures, a virtual cell or a
# served page, are made once): most of the suite waits on processes, browsers and cells.
exec python -m pytest -n 2 --dist loadfile "$@"
