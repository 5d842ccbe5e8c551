#!/usr/bin/env bash
# The compatibility matrix of tox.ini: every supported system's Python with that system's library versions.
#
#   bash scripts/compat/matrix.sh                     every environment, two at a time
#   bash scripts/compat/matrix.sh -e ubuntu2004 --parallel-live     one environment, its output shown
#   bash scripts/compat/matrix.sh -e debian13 -- tests/unit/rcm_platform -x    other tests than tests/unit
# (any arguments of `tox run-parallel`; --result-json FILE writes each environment's outcome)
#
# Makes build/compat/venv with the tox of scripts/compat/requirements.txt (again when that file changes), puts
# pyenv's interpreters first on PATH (they are never downloaded: a missing one is an error naming it) and runs
# tox. Its environments live in build/compat/tox; tox makes one again when its pins in tox.ini change, so a second
# run only runs the tests. ROS's Python packages come from this machine's Debian packages (./run deps) and
# robotics_msgs from the catkin workspace (./run build).
set -euo pipefail
root=$(cd "$(dirname "$0")/../.." && pwd)
cd "$root"
PROG=compat-matrix
die() { echo "$PROG: $*" >&2; exit 1; }

# pyenv's interpreters: pyenv root, else $PYENV_ROOT, else ~/.pyenv
pyenv_root=
if command -v pyenv >/dev/null 2>&1; then pyenv_root=$(pyenv root); fi
[ -n "$pyenv_root" ] || pyenv_root=${PYENV_ROOT:-$HOME/.pyenv}
[ -d "$pyenv_root/versions" ] || die "no pyenv interpreters in $pyenv_root/versions: the matrix needs pyenv's CPython 3.8 to 3.13"
bins=()
while IFS= read -r version; do
    [[ "$version" =~ ^[0-9]+\.[0-9]+\.[0-9]+$ ]] && [ -d "$pyenv_root/versions/$version/bin" ] || continue
    bins+=("$pyenv_root/versions/$version/bin")
done < <(ls "$pyenv_root/versions" | sort -V -r)   # the newest release of each minor version first
path_prefix=$(IFS=:; echo "${bins[*]}")
export PATH="$path_prefix:$PATH"
for python in $(sed -n 's/^base_python *= *//p' tox.ini); do
    command -v "$python" >/dev/null || die "$python is not installed in $pyenv_root/versions (pyenv install it)"
done

# tox itself, in a venv of the newest interpreter, remade when the pins change
venv=build/compat/venv
base=$(command -v python3.13 || command -v python3.12 || command -v python3.11) \
    || die "no Python 3.11 to 3.13 to run tox with"
key="$(sha256sum scripts/compat/requirements.txt | cut -d' ' -f1) $base"
if [ ! -x "$venv/bin/tox" ] || [ "$(cat "$venv/.key" 2>/dev/null)" != "$key" ]; then
    echo "$PROG: installing tox into $venv ($base)"
    rm -rf "$venv"
    "$base" -m venv "$venv"
    "$venv/bin/python" -m pip install -q --disable-pip-version-check -r scripts/compat/requirements.txt \
        || die "pip could not install scripts/compat/requirements.txt"
    echo "$key" >"$venv/.key"
fi

# two at a time (the machine's two cores); a failed environment's output is shown, --parallel-live shows all
exec "$venv/bin/tox" run-parallel --parallel 2 --parallel-no-spinner "$@"
