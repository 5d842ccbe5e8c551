#!/bin/bash
# uninstall.sh: removes the RCM agent installed by install.sh, keeping the package dependencies.
#
# Owns the installing user's half of the removal: it has sub_uninst.sh (through sudo when the user is not root)
# stop the daemon and remove rcmp_n, the rcm_platform package, the platform folder, the init script and its
# settings, then removes the catkin workspace the installation created. Where things are is read from
# /etc/default/<service name>, written at installation; running it again when nothing is installed is harmless.
set -eo pipefail
export LC_ALL=C
HERE=$(cd "$(dirname "$0")" && pwd)
PROG=uninstall.sh

usage() {
    cat <<USAGE
Usage: ./uninstall.sh [--service-name NAME] [--keep-workspace]

Stops the rcm daemon and removes every file the installation placed (rcmp_n, the rcm_platform package, the
platform folder with its configuration, data and logs, the init script, the catkin workspace). The package
dependencies installed with apt-get are kept.
  --service-name NAME   the init script name given to install.sh (default rcmpd)
  --keep-workspace      leave the catkin workspace in place
  -h, --help            this text
USAGE
}
die() { echo "$PROG: error: $1" >&2; exit "${2:-1}"; }

SERVICE=rcmpd
KEEP_WS=no
while [ $# -gt 0 ]; do
    case "$1" in
        -h|--help) usage; exit 0 ;;
        --keep-workspace) KEEP_WS=yes; shift ;;
        --service-name)
            [ $# -ge 2 ] || die "--service-name needs a value" 2
            [[ "$2" =~ ^[A-Za-z][A-Za-z0-9_]*$ ]] || die "--service-name: '$2' is not a valid name" 2
            SERVICE=$2; shift 2 ;;
        --service-name=*) set -- --service-name "${1#*=}" "${@:2}" ;;
        *) echo "$PROG: error: unknown option '$1'" >&2; echo "Try './uninstall.sh --help'." >&2; exit 2 ;;
    esac
done

RCMP_WS=
if [ -r "/etc/default/$SERVICE" ]; then
    RCMP_WS=$(sed -n 's/^RCMP_WS=//p' "/etc/default/$SERVICE" | sed -n 1p)
fi

if [ "$(id -u)" -eq 0 ]; then
    "$HERE/sub_uninst.sh" --service-name "$SERVICE"
else
    command -v sudo >/dev/null || die "the next step needs root and sudo is not installed: run ./uninstall.sh as root"
    echo "$PROG: the next step needs administration rights: sudo sub_uninst.sh"
    sudo "$HERE/sub_uninst.sh" --service-name "$SERVICE"
fi

if [ "$KEEP_WS" = no ] && [ -n "$RCMP_WS" ] && [ -d "$RCMP_WS" ]; then
    if [ -e "$RCMP_WS/.catkin_workspace" ] || [ -d "$RCMP_WS/src" ]; then
        rm -rf -- "$RCMP_WS"
        echo "Removed the workspace $RCMP_WS"
    else
        echo "$PROG: $RCMP_WS does not look like a catkin workspace: left in place" >&2
    fi
fi
echo "RCM uninstalled (package dependencies kept)."
