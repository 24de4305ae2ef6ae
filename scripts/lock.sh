#!/usr/bin/env bash
# Refreshes requirements.lock: every package that pyproject.toml's dependencies and its `test` extra need, pinned
# with the SHA-256 of each file pip may install, for Python 3.11 on Linux x86_64 with torch's CPU build. The README's
# install command and CI (.ci/run) install from it; tests/test_lock.py checks that it agrees with pyproject.toml.
#
#   bash scripts/lock.sh               keeps every pin that pyproject.toml still allows; resolves only what changed
#   bash scripts/lock.sh -P numpy      moves one package to the newest release that pyproject.toml allows
#   bash scripts/lock.sh --upgrade     moves every package to the newest release that pyproject.toml allows
#
# Other arguments go to pip-compile, e.g. `--extra-index-url https://download.pytorch.org/whl/cpu` where pip is not
# already set up to find torch's CPU wheel (it is not on PyPI). A refresh that changes a pin changes the numbers of
# the learned methods and JTORATC: rerun the README's demo tables and write the new lock's SHA-256 beside them.
set -euo pipefail
cd "$(dirname "$0")/.."

PIP_TOOLS="pip-tools==7.6.2"
TOOLS="${LOCK_TOOLS_VENV:-${TMPDIR:-/tmp}/dswm-lock-tools}"   # pip-tools lives in a venv of its own, not the project's

python3 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || {
  echo "scripts/lock.sh: the lock is for Python 3.11; python3 here is $(python3 -V 2>&1)" >&2; exit 1; }
if [ ! -x "$TOOLS/bin/pip-compile" ]; then
  python3 -m venv "$TOOLS"
  "$TOOLS/bin/pip" install -q "$PIP_TOOLS"
fi

# pip-compile reads the current pins from its output file and rewrites it: it works on a copy, which replaces the
# lock only once it is complete and checked.
new="$(mktemp requirements.lock.XXXXXX)"
trap 'rm -f "$new"' EXIT
[ ! -f requirements.lock ] || cp requirements.lock "$new"

# --allow-unsafe: torch and osqp need setuptools at run time, and --require-hashes refuses a package without a pin.
CUSTOM_COMPILE_COMMAND="bash scripts/lock.sh" "$TOOLS/bin/pip-compile" --quiet --generate-hashes --allow-unsafe \
  --strip-extras --extra test --no-emit-index-url --no-emit-find-links --output-file "$new" "$@" pyproject.toml

grep -qE '^torch==[^ ]*\+cpu ' "$new" || {
  echo "scripts/lock.sh: the new lock pins $(grep -oE '^torch==[^ ]*' "$new"), not torch's CPU build (a version" \
    "ending in +cpu); requirements.lock is unchanged. Let pip find that wheel" \
    "(--extra-index-url https://download.pytorch.org/whl/cpu) and run again" >&2
  exit 1
}
chmod 644 "$new"
mv "$new" requirements.lock
echo "requirements.lock: $(grep -cE '^[A-Za-z0-9]' requirements.lock) packages," \
  "SHA-256 $(sha256sum requirements.lock | cut -d' ' -f1) (the README's results name the lock they came from by it)"
