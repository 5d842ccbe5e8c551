#!/bin/bash
# sub_inst.sh: the privileged half of install.sh (run as root, through sudo when needed).
#
# Owns everything of the installation that lives outside the installing user's home:
#   sub_inst.sh deps master|robot        apt-get install the missing dependencies (installed ones are kept)
#   sub_inst.sh install --role R --src DIR --home DIR --bin-dir DIR --lib-dir DIR --service-name NAME
#                       --workspace DIR --config FILE
#                       [--vpn-subnet CIDR --vpn-port N [--vpn-remote HOST]]   (master: create the VPN)
#                       [--vpn-config FILE]                                    (robot: its VPN client file)
#                                        rcmp_n, the rcm_platform package, the platform folder with its
#                                        configuration file and rosconsole.config, /etc/default/NAME and
#                                        /etc/init.d/NAME registered with update-rc.d; the platform's VPN
#                                        ('rcmp_n vpn init' on a master, HOME/vpn/client.conf 0600 on a robot)
#   sub_inst.sh start|restart --service-name NAME
#                                        start the daemon through `service` (restart when it runs)
# install.sh validates every value before calling it; this script checks them again and changes nothing
# when one is wrong. Running it twice gives the same result.
set -eo pipefail
export LC_ALL=C
PROG=sub_inst.sh
export PATH=/usr/bin:/bin:/usr/sbin:/sbin:$PATH

die() { echo "$PROG: error: $1" >&2; exit "${2:-1}"; }
[ "$(id -u)" -eq 0 ] || die "must run as root (install.sh runs it through sudo)"

# ROS 1 from Debian (the ROS part of scripts/install-deps.sh), the agent's own needs, and the tools the
# installer and the seed guide's checks use. python3-twisted on every agent: our robot agent speaks the
# agent protocol through Twisted too (docs/INSTALL.md).
ROS_PACKAGES=(ros-core rosbash rospack-tools python3-rospy python3-roslaunch python3-rosmaster python3-rosgraph
  python3-rostopic python3-rosnode python3-rosservice python3-rosparam python3-std-msgs python3-geometry-msgs
  python3-sensor-msgs python3-genpy python3-genmsg catkin python3-catkin-pkg ros-message-generation
  ros-message-runtime libstd-msgs-dev libgeometry-msgs-dev libroscpp-dev cmake g++)
AGENT_PACKAGES=(python3-twisted python3-netifaces python3-yaml openvpn unzip iproute2)
MASTER_PACKAGES=(sqlite3 python3-prometheus-client)   # the RDAPI's /metrics (docs/METRICS.md): master only

do_deps() {
    local role=$1 packages missing=()
    case "$role" in
        master) packages=("${ROS_PACKAGES[@]}" "${AGENT_PACKAGES[@]}" "${MASTER_PACKAGES[@]}") ;;
        robot) packages=("${ROS_PACKAGES[@]}" "${AGENT_PACKAGES[@]}") ;;
        *) die "deps: role must be master or robot, not '$role'" 2 ;;
    esac
    for p in "${packages[@]}"; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || missing+=("$p")
    done
    if [ ${#missing[@]} -eq 0 ]; then
        echo "Dependencies: all ${#packages[@]} packages are already installed"
        return 0
    fi
    echo "Dependencies: installing ${missing[*]} with apt-get"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq || die "apt-get update failed"
    apt-get install -y -qq --no-install-recommends "${missing[@]}" || die "apt-get install failed"
}

abs_dir() {  # abs_dir OPTION VALUE: an absolute path other than /
    case "$2" in
        /) die "$1: '/' cannot be used here" 2 ;;
        /*) printf '%s' "${2%/}" ;;
        *) die "$1: '$2' is not an absolute path" 2 ;;
    esac
}
check_service() {
    [[ "$1" =~ ^[A-Za-z][A-Za-z0-9_]*$ ]] || die "--service-name: '$1' is not a valid name" 2
    printf '%s' "$1"
}

do_install() {
    local role='' src='' home='' bin='' lib='' service='' ws='' config=''
    local vpn_subnet='' vpn_port='' vpn_remote='' vpn_config=''
    while [ $# -gt 0 ]; do
        [ $# -ge 2 ] || die "install: $1 needs a value" 2
        case "$1" in
            --role) role=$2 ;;
            --src) src=$(abs_dir "$1" "$2") ;;
            --home) home=$(abs_dir "$1" "$2") ;;
            --bin-dir) bin=$(abs_dir "$1" "$2") ;;
            --lib-dir) lib=$(abs_dir "$1" "$2") ;;
            --service-name) service=$(check_service "$2") ;;
            --workspace) ws=$(abs_dir "$1" "$2") ;;
            --config) config=$2 ;;
            --vpn-subnet) [[ "$2" =~ ^[0-9.]+/[0-9]{1,2}$ ]] || die "--vpn-subnet: '$2' is not a subnet" 2; vpn_subnet=$2 ;;
            --vpn-port) [[ "$2" =~ ^[0-9]{1,5}$ ]] || die "--vpn-port: '$2' is not a port" 2; vpn_port=$2 ;;
            --vpn-remote) [[ "$2" =~ ^[A-Za-z0-9][A-Za-z0-9.-]*$ ]] || die "--vpn-remote: '$2' is not a host" 2; vpn_remote=$2 ;;
            --vpn-config) vpn_config=$2 ;;
            *) die "install: unknown option '$1'" 2 ;;
        esac
        shift 2
    done
    case "$role" in master|robot) ;; *) die "install: --role must be master or robot" 2 ;; esac
    for v in src home bin lib service ws config; do
        [ -n "${!v}" ] || die "install: a value for --${v/_/-} is missing" 2
    done
    [ -r "$config" ] || die "install: the configuration file $config cannot be read" 2
    if [ -n "$vpn_subnet$vpn_port$vpn_remote" ]; then
        [ "$role" = master ] || die "install: --vpn-subnet, --vpn-port and --vpn-remote are for a master" 2
        [ -n "$vpn_subnet" ] && [ -n "$vpn_port" ] || die "install: --vpn-subnet and --vpn-port go together" 2
    fi
    if [ -n "$vpn_config" ]; then
        [ "$role" = robot ] || die "install: --vpn-config is for a robot or server VM" 2
        [ -f "$vpn_config" ] && [ -r "$vpn_config" ] || die "install: the VPN client file $vpn_config cannot be read" 2
    fi
    for f in rcmp_n rcmpd ros/rosconsole.config rcm_platform/__init__.py; do
        [ -f "$src/$f" ] || die "install: $src/$f is missing: is $src an unpacked distribution package?" 2
    done

    local cfg_name stale_cfg
    if [ "$role" = master ]; then cfg_name=.init.cfg; stale_cfg=init.cfg; else cfg_name=init.cfg; stale_cfg=.init.cfg; fi

    # the agent program, its #! line pointing at the system python (the one that sees Debian's ROS)
    mkdir -p "$bin"
    { echo '#!/usr/bin/python3'; sed '1{/^#!/d}' "$src/rcmp_n"; } >"$bin/.rcmp_n.new"
    chmod 0755 "$bin/.rcmp_n.new"
    mv -f "$bin/.rcmp_n.new" "$bin/rcmp_n"
    echo "Installed $bin/rcmp_n"

    # the rcm_platform package: replaced as a whole, so no module of an earlier installation is left
    mkdir -p "$lib"
    rm -rf "$lib/.rcm_platform.new"
    mkdir "$lib/.rcm_platform.new"
    install -m 0644 "$src"/rcm_platform/*.py "$lib/.rcm_platform.new/"
    if [ -d "$src/rcm_platform/console" ]; then  # the master's console (static files, no subfolders)
        install -d -m 0755 "$lib/.rcm_platform.new/console"
        install -m 0644 "$src"/rcm_platform/console/* "$lib/.rcm_platform.new/console/"
    fi
    rm -rf "$lib/rcm_platform"
    mv "$lib/.rcm_platform.new" "$lib/rcm_platform"
    echo "Installed $lib/rcm_platform"

    # the platform folder: configuration, rosconsole.config (data and logs are the agent's)
    mkdir -p "$home/log"
    chmod 0755 "$home"
    install -m 0644 "$src/ros/rosconsole.config" "$home/rosconsole.config"
    install -m 0644 "$config" "$home/$cfg_name"
    if [ -e "$home/$stale_cfg" ]; then
        # a master is a master because init.cfg is absent; a robot ignores .init.cfg: keep only ours
        rm -f "$home/$stale_cfg"
        echo "Removed $home/$stale_cfg of an earlier installation of the other role"
    fi
    echo "Configured $home/$cfg_name"

    # the platform's VPN (CONTRACTS section 7): HOME/vpn is root's alone (0700); the agent runs OpenVPN with it
    if [ -n "$vpn_subnet" ]; then
        if [ -e "$home/vpn/server.conf" ]; then
            echo "Kept the platform's VPN in $home/vpn"
        else
            local -a remote=()
            [ -z "$vpn_remote" ] || remote=(--remote "$vpn_remote")
            PYTHONPATH=$lib "$bin/rcmp_n" vpn init --home "$home" --subnet "$vpn_subnet" --port "$vpn_port" \
                "${remote[@]}" || die "rcmp_n vpn init failed: the platform's VPN was not created"
            echo "Created the platform's VPN in $home/vpn (subnet $vpn_subnet, UDP port $vpn_port)"
        fi
    fi
    if [ -n "$vpn_config" ]; then
        install -d -m 0700 "$home/vpn"
        chmod 0700 "$home/vpn"
        install -m 0600 "$vpn_config" "$home/vpn/.client.conf.new"
        mv -f "$home/vpn/.client.conf.new" "$home/vpn/client.conf"
        echo "Installed the VPN client file as $home/vpn/client.conf"
    fi

    # the init script and its settings
    cat >"/etc/default/$service" <<EOF
# /etc/default/$service: settings of /etc/init.d/$service, written by sub_inst.sh (RCM $role agent).
# uninstall.sh reads it to find what the installation placed.
RCMP_ROLE=$role
RCMP_BIN=$bin/rcmp_n
RCMP_HOME=$home
RCMP_WS=$ws
RCMP_PYLIB=$lib
EOF
    chmod 0644 "/etc/default/$service"
    sed -e "s/^NAME=rcmpd\( \|\$\)/NAME=$service\1/" -e "s/^# Provides:\( *\)rcmpd\$/# Provides:\1$service/" \
        "$src/rcmpd" >"/etc/init.d/.$service.new"
    chmod 0755 "/etc/init.d/.$service.new"
    mv -f "/etc/init.d/.$service.new" "/etc/init.d/$service"
    update-rc.d "$service" defaults >/dev/null 2>&1 || die "update-rc.d $service defaults failed"
    echo "Installed /etc/init.d/$service (registered with update-rc.d)"
}

do_service() {  # start|restart --service-name NAME
    local action=$1 service=rcmpd
    shift
    while [ $# -gt 0 ]; do
        [ $# -ge 2 ] || die "$action: $1 needs a value" 2
        case "$1" in
            --service-name) service=$(check_service "$2") ;;
            *) die "$action: unknown option '$1'" 2 ;;
        esac
        shift 2
    done
    [ -x "/etc/init.d/$service" ] || die "/etc/init.d/$service is not installed"
    service "$service" "$action"
}

case "${1:-}" in
    deps) [ $# -eq 2 ] || die "usage: sub_inst.sh deps master|robot" 2; do_deps "$2" ;;
    install) shift; do_install "$@" ;;
    start|restart) do_service "$@" ;;
    *) die "usage: sub_inst.sh deps|install|start|restart ... (run by install.sh)" 2 ;;
esac
