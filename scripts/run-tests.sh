#!/usr/bin/env bash
# Run the whole test suite (or the pytest arguments given) inside the catkin overlay.
set -eo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
exec bash "$root/scripts/with-overlay.sh" /usr/bin/python3 -m pytest -p no:cacheprovider "$@"
