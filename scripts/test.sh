#!/usr/bin/env bash
# The whole test suite, as README's Quick start and CI (.ci/run) run it:
#
#   bash scripts/test.sh [pytest options]
#
# 1. system packages the tests use, when missing and this user may install them (root, or
#    passwordless sudo): Debian's mosquitto and mosquitto-clients (the runtime tests start
#    their own brokers) and chromium (the dashboard's browser tests; Playwright drives it, nothing is downloaded);
#    tests whose package is missing are skipped with the reason;
# 2. pip install -e ".[dev]";
# 3. python -m pytest with two workers per core (pytest-xdist, one test file per worker at a
#    time so that a file's module fixtures — rendered references, brokers — are built once;
#    tests/conftest.py hands the files out longest first, from tests/file_durations.json,
#    so that no long file is left to run alone at the end). Two per core, not one: the
#    broker, fault and `cblrs up` files spend most of their time waiting on the processes
#    they start (the fault tests: 31 CPU-s in 143 s), and another worker's
#    file uses the core meanwhile (docs/getting-started.md has the figures);
#    CBLRS_TEST_WORKERS=N sets the number of workers, 0 runs in this process.
set -euo pipefail
cd "$(dirname "$0")/.."
export PIP_DISABLE_PIP_VERSION_CHECK=1
# The suite starts a few hundred `cblrs` processes: Python keeps the package's compiled modules,
# and pytest its rewritten test modules, in __pycache__ (git-ignored) instead of compiling them
# again in every process, even where PYTHONDONTWRITEBYTECODE is set (measured: 0.27 s of CPU
# less per `cblrs matcher` start, and half the CPU of collecting the tests on each worker).
unset PYTHONDONTWRITEBYTECODE

missing=()
command -v mosquitto > /dev/null 2>&1 || [[ -x /usr/sbin/mosquitto ]] || missing+=(mosquitto)
command -v mosquitto_pub > /dev/null 2>&1 || missing+=(mosquitto-clients)
[[ -x /usr/bin/chromium ]] || missing+=(chromium)
if (( ${#missing[@]} )) && command -v apt-get > /dev/null 2>&1; then
    sudo=()
    if [[ "$(id -u)" != 0 ]]; then
        if command -v sudo > /dev/null 2>&1 && sudo -n true 2> /dev/null; then
            sudo=(sudo -n)
        else
            sudo=(false)
        fi
    fi
    echo "installing ${missing[*]} (Debian packages) for the tests" >&2
    if ! { "${sudo[@]}" apt-get update -qq \
           && DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y -qq \
              --no-install-recommends "${missing[@]}"; } > /dev/null; then
        echo "could not install ${missing[*]}: the tests that need them will be skipped" >&2
    fi
fi

pip install -q -e ".[dev]"
cores=$(nproc 2> /dev/null || echo 2)
python -m pytest -n "${CBLRS_TEST_WORKERS:-$(( 2 * cores ))}" --dist loadfile "$@"
