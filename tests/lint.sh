#!/usr/bin/env bash
# Lint and types: ruff's checks and format, then mypy over vservo.core and vservo.app.
# Exits non-zero on any finding. Run from anywhere: bash tests/lint.sh
#
# The type checker is mypy, not pyright: mypy is a Python package on PyPI, installed and
# pinned by pip and constraints.txt like every other tool here. pyright is TypeScript; its
# PyPI package is a wrapper that, at its first run, installs pyright itself from the npm
# registry with npm, and needs Node.js for it (the one on PATH, else a Node build that
# nodeenv downloads from nodejs.org, which a machine that reaches only package registries
# cannot fetch; or its nodejs extra, Node in a wheel). That is a second runtime and a
# run-time download outside constraints.txt, for a check mypy does from PyPI alone.
set -euo pipefail
cd "$(dirname "$0")/.."

ruff check .
ruff format --check .

# core/, app/, ... are installed under the import name vservo by a setuptools package-dir
# mapping (pyproject.toml) that mypy cannot follow, so it reads them through a tree of
# symlinks laid out as the installed package. The tree's temporary folder is named after this
# checkout and kept between runs, with mypy's cache beside it: the cache records the paths it
# read, and findings replayed from a cache made through another tree would name that tree.
tree="${TMPDIR:-/tmp}/vservo-mypy-$(printf %s "$PWD" | sha1sum | cut -c1-12)"
mkdir -p "$tree/vservo"
for folder in core app robot_models static; do
    ln -sfn "$PWD/$folder" "$tree/vservo/$folder"
done
# Findings name the files as the repository does (core/..., not the temporary tree).
MYPYPATH="$tree" mypy --cache-dir "$tree/.mypy_cache" -p vservo.core -p vservo.app 2>&1 | sed "s#^$tree/vservo/##"
