#!/usr/bin/env bash
# Create (if missing) the repo's .venv and install ROS 2 Jazzy wheels plus this
# package into it. Idempotent: re-running re-installs the package from source.
#   bash tools/setup.sh            (from any directory)
set -euo pipefail

cd "$(dirname -- "${BASH_SOURCE[0]}")/.."
export PIP_NO_INPUT=1 PIP_DISABLE_PIP_VERSION_CHECK=1

say() { echo "setup.sh: $*"; }
# -qq: errors only (pip warnings, e.g. about index locations, stay out of the log)
pip_q() { .venv/bin/python -m pip install -qq "$@"; }

if ! .venv/bin/python -c '' 2>/dev/null; then
    py=${PYTHON:-python3}
    if ! "$py" -c 'import sys; sys.exit(not (3, 10) <= sys.version_info[:2] <= (3, 13))'; then
        say "error: $py is $("$py" --version 2>&1); the ROS 2 Jazzy wheels need Python 3.10-3.13" >&2
        say "       (set PYTHON=/path/to/python3.x to choose another interpreter)" >&2
        exit 1
    fi
    say "creating .venv with $("$py" --version 2>&1)"
    if ! "$py" -m venv --clear .venv; then
        say "error: '$py -m venv' failed; on Debian/Ubuntu: apt-get install python3-venv" >&2
        exit 1
    fi
else
    say "using existing .venv ($(.venv/bin/python --version 2>&1))"
fi

say "upgrading pip"
pip_q --upgrade pip

say "installing ROS 2 Jazzy wheels (requirements-ros.txt)"
pip_q -r requirements-ros.txt

say "installing dea_array_twin with extras [test,plot,cluster]"
# setuptools never prunes build/lib: a module deleted from the source tree would
# otherwise still be copied into the wheel.
rm -rf build/lib build/bdist.*
pip_q ".[test,plot,cluster]"

say "done: $(.venv/bin/python -c 'import sys; print(sys.prefix)')"
