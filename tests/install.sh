#!/usr/bin/env bash
# Everything the test suite needs, on a fresh machine: the system's Chromium, which the browser
# tests drive (a Playwright browser download does not work here: docs/architecture.md, "Tests"),
# then vservo with its test extra at the versions constraints.txt pins. Run by tests/run.sh
# (the README's test command) and by CI (.ci/run).
set -euo pipefail
cd "$(dirname "$0")/.."
chromium="${VSERVO_CHROMIUM:-/usr/bin/chromium}"
if [ ! -x "$chromium" ]; then
    if [ -n "${VSERVO_CHROMIUM:-}" ]; then
        echo "tests/install.sh: VSERVO_CHROMIUM=$VSERVO_CHROMIUM is not an executable Chromium; unset it to install Debian's /usr/bin/chromium" >&2
        exit 1
    elif ! command -v apt-get > /dev/null; then
        echo "tests/install.sh: Chromium is missing at /usr/bin/chromium and there is no apt-get to install it: install Chromium and set VSERVO_CHROMIUM to it" >&2
        exit 1
    elif [ "$(id -u)" -ne 0 ]; then
        echo "tests/install.sh: Chromium is missing at /usr/bin/chromium and installing it needs root: run \`sudo apt-get install chromium\`, or run this script with sudo" >&2
        exit 1
    fi
    echo "tests/install.sh: installing Chromium (apt-get install chromium)" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium > /dev/null
fi
# tests/project/test_deploy.py checks the service unit with systemd-analyze (Debian's systemd package).
if ! command -v systemd-analyze > /dev/null; then
    if ! command -v apt-get > /dev/null || [ "$(id -u)" -ne 0 ]; then
        echo "tests/install.sh: systemd-analyze is missing and installing it needs apt-get as root: run \`sudo apt-get install systemd\`" >&2
        exit 1
    fi
    echo "tests/install.sh: installing systemd-analyze (apt-get install systemd)" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq --no-install-recommends systemd > /dev/null
fi
python -m pip install -c constraints.txt -e '.[test]'
