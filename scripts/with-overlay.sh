#!/usr/bin/env bash
# Run a command inside the catkin workspace overlay, with /usr/bin first on PATH (the PATH trap).
set -eo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
overlay="$root/build/rcmp_ws/devel/setup.bash"
if [ ! -f "$overlay" ]; then
  echo "with-overlay: $overlay is missing; run 'make build' first" >&2
  exit 1
fi
export PATH=/usr/bin:/bin:/usr/sbin:/sbin:$PATH
# shellcheck disable=SC1090
source "$overlay"
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}"
cd "$root"
exec "$@"
