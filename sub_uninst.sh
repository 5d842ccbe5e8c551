#!/bin/bash
# sub_uninst.sh: the privileged half of uninstall.sh (run as root, through sudo when needed).
#
# Owns removing what sub_inst.sh placed: it stops the daemon (the agent stops everything it started), removes
# the update-rc.d links, /etc/init.d/NAME, /etc/default/NAME, the pid file, rcmp_n, the rcm_platform package and
# the platform folder (configuration, robotics data, logs, rosconsole.config). apt-get packages are kept.
set -eo pipefail
export LC_ALL=C
PROG=sub_uninst.sh
export PATH=/usr/bin:/bin:/usr/sbin:/sbin:$PATH
die() { echo "$PROG: error: $1" >&2; exit "${2:-1}"; }
[ "$(id -u)" -eq 0 ] || die "must run as root (uninstall.sh runs it through sudo)"

SERVICE=rcmpd
while [ $# -gt 0 ]; do
    case "$1" in
        --service-name)
            [ $# -ge 2 ] || die "--service-name needs a value" 2
            [[ "$2" =~ ^[A-Za-z][A-Za-z0-9_]*$ ]] || die "--service-name: '$2' is not a valid name" 2
            SERVICE=$2; shift 2 ;;
        *) die "unknown option '$1'" 2 ;;
    esac
done

# where things are: the settings written at installation, else the standard places
RCMP_BIN=/usr/local/bin/rcmp_n
RCMP_HOME=/opt/rcm-platform
RCMP_PYLIB=$(/usr/bin/python3 -c 'import site; print(site.getsitepackages()[0])')  # install.sh's default
if [ ! -r "/etc/default/$SERVICE" ] && [ "$SERVICE" != rcmpd ]; then
    # an installation's places are known only from its settings: never guess the standard ones
    RCMP_BIN='' RCMP_HOME='' RCMP_PYLIB=''
    echo "$PROG: /etc/default/$SERVICE is missing: only the init script $SERVICE is removed" >&2
elif [ -r "/etc/default/$SERVICE" ]; then
    # only the known keys, never the file as a script
    while IFS='=' read -r key value; do
        case "$key" in RCMP_BIN|RCMP_HOME|RCMP_PYLIB) [ -z "$value" ] || printf -v "$key" '%s' "$value" ;; esac
    done <"/etc/default/$SERVICE"
fi
if [ -n "$RCMP_BIN$RCMP_HOME$RCMP_PYLIB" ]; then
    for v in RCMP_BIN RCMP_HOME RCMP_PYLIB; do
        case "${!v}" in /?*) ;; *) die "/etc/default/$SERVICE: $v='${!v}' is not an absolute path" ;; esac
    done
fi

if [ -e "/etc/init.d/$SERVICE" ]; then
    if [ -x "/etc/init.d/$SERVICE" ]; then
        "/etc/init.d/$SERVICE" stop || die "the daemon did not stop: nothing removed"
    fi
    update-rc.d -f "$SERVICE" remove >/dev/null 2>&1 || true
    rm -f "/etc/init.d/$SERVICE"
    echo "Removed /etc/init.d/$SERVICE"
fi
rm -f "/etc/default/$SERVICE" "/run/$SERVICE.pid"

if [ -n "$RCMP_BIN" ] && [ -f "$RCMP_BIN" ]; then
    rm -f "$RCMP_BIN"
    echo "Removed $RCMP_BIN"
fi
if [ -n "$RCMP_PYLIB" ] && [ -d "$RCMP_PYLIB/rcm_platform" ]; then
    rm -rf -- "$RCMP_PYLIB/rcm_platform"
    echo "Removed $RCMP_PYLIB/rcm_platform"
fi
if [ -n "$RCMP_HOME" ] && [ -d "$RCMP_HOME" ]; then
    # the platform folder holds the configuration, the robotics data and the logs; refuse anything else
    if [ -e "$RCMP_HOME/.init.cfg" ] || [ -e "$RCMP_HOME/init.cfg" ] || [ -e "$RCMP_HOME/rosconsole.config" ] \
            || [ "$(basename "$RCMP_HOME")" = rcm-platform ]; then
        if [ -d "$RCMP_HOME/vpn" ]; then
            # the platform's VPN: the agent stopped its OpenVPN (last) above; one still running on these files is ended
            own_mnt=$(readlink /proc/self/ns/mnt)
            for pid_dir in /proc/[0-9]*; do
                [ "$(readlink "$pid_dir/exe" 2>/dev/null)" = /usr/sbin/openvpn ] || continue
                [ "$(readlink "$pid_dir/ns/mnt" 2>/dev/null)" = "$own_mnt" ] || continue  # another machine's files
                if tr '\0' '\n' <"$pid_dir/cmdline" 2>/dev/null | grep -qxF -e "$RCMP_HOME/vpn" -e "$RCMP_HOME/vpn/server.conf" \
                        -e "$RCMP_HOME/vpn/client.conf"; then
                    kill "${pid_dir#/proc/}" 2>/dev/null && echo "Stopped OpenVPN ${pid_dir#/proc/} of $RCMP_HOME/vpn"
                fi
            done
            rm -rf -- "$RCMP_HOME/vpn"
            echo "Removed the platform's VPN ($RCMP_HOME/vpn: its certificates, keys and configuration)"
        fi
        rm -rf -- "$RCMP_HOME"
        echo "Removed $RCMP_HOME"
    else
        echo "$PROG: $RCMP_HOME does not look like an RCM platform folder: left in place" >&2
    fi
fi
