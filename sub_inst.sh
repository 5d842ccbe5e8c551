#!/bin/bash
# sub_inst.sh: the privileged half of install.sh (run as root, through sudo when needed).
#
# Owns everything of the installation that lives outside the installing user's home, and what the installation
# finds on the machine: the system (/etc/os-release), the ROS installation and the dependencies it needs.
#   sub_inst.sh ros-setup [VALUE]        print the setup script of the ROS installation to use: VALUE (a file, or
#                                        none), else the first /opt/ros/*/setup.bash (noetic first), else none
#                                        (ROS on the system's paths, as Debian's packages put it). No root needed.
#   sub_inst.sh deps master|robot [--ros-setup FILE|none] [--dry-run]
#                                        say which system and which package names it chose, then apt-get install
#                                        the missing dependencies (installed ones are kept); with --dry-run only
#                                        list the missing ones ("Missing: NAME..."), which needs no root
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
need_root() { [ "$(id -u)" -eq 0 ] || die "must run as root (install.sh runs it through sudo)"; }

# The dependencies come from one source of ROS packages, never two (their Python libraries conflict):
# - ROS on the system's paths (no setup script): the system's own packages. Debian's names below (the ROS list of
#   scripts/install-deps.sh); Ubuntu's own archive uses the same names.
ROS_PACKAGES=(ros-core rosbash rospack-tools python3-rospy python3-roslaunch python3-rosmaster python3-rosgraph
  python3-rostopic python3-rosnode python3-rosservice python3-rosparam python3-std-msgs python3-geometry-msgs
  python3-sensor-msgs python3-genpy python3-genmsg catkin python3-catkin-pkg ros-message-generation
  ros-message-runtime libstd-msgs-dev libgeometry-msgs-dev libroscpp-dev cmake g++)
# - ROS from ROS's own apt repository in /opt/ros/DISTRO (Ubuntu 20.04 with Noetic): the same pieces under ROS's
#   names, ros-DISTRO-NAME for each NAME below, plus catkin's Python library, which that repository ships as
#   python3-catkin-pkg (its C++ headers come with the message and roscpp packages).
ROS_REPOSITORY_PACKAGES=(ros-core rosbash rospack rospy roslaunch rosmaster rosgraph rostopic rosnode rosservice
  rosparam std-msgs geometry-msgs sensor-msgs genpy genmsg catkin message-generation message-runtime roscpp)
ROS_REPOSITORY_EXTRA=(python3-catkin-pkg cmake g++)
# - a ROS set up by a script elsewhere (a source build): its packages are the administrator's; none installed here.
# The agent's own needs and the tools the installer and the original guide's checks use, the same names on Debian and
# Ubuntu. python3-twisted on every agent: our robot agent speaks the agent protocol through Twisted too
# (docs/INSTALL.md); a robot needs nothing of the master's (no sqlite3 tool).
AGENT_PACKAGES=(python3-twisted python3-netifaces python3-yaml python3-cryptography openvpn unzip iproute2)
MASTER_PACKAGES=(sqlite3 python3-prometheus-client)   # the RDAPI's /metrics (docs/METRICS.md): master only
# the systems this release is tested on (README, "Supported systems"): ID VERSION_ID
SUPPORTED_SYSTEMS=("debian 12" "debian 13" "ubuntu 20.04" "ubuntu 22.04" "ubuntu 24.04")

os_release() {  # os_release KEY: KEY's value in /etc/os-release, read as KEY=value lines (never run)
    local file=/etc/os-release line value=
    [ -r "$file" ] || file=/usr/lib/os-release
    [ -r "$file" ] || return 0
    while IFS= read -r line || [ -n "$line" ]; do
        case "$line" in
            "$1="*) value=${line#*=}; value=${value#[\"\']}; value=${value%[\"\']} ;;
        esac
    done <"$file"
    printf '%s' "$value"
}

describe_system() {  # one line: the system, and whether it is one this release is tested on
    local id version name
    id=$(os_release ID) version=$(os_release VERSION_ID) name=$(os_release PRETTY_NAME)
    name=${name:-${id:-an unknown system} $version}
    local s
    for s in "${SUPPORTED_SYSTEMS[@]}"; do
        if [ "$s" = "$id $version" ]; then echo "System: $name"; return 0; fi
    done
    echo "System: $name (not one of the systems this release is tested on: Debian 12 and 13, Ubuntu 20.04," \
         "22.04 and 24.04; continuing with the packages below)"
}

do_ros_setup() {  # do_ros_setup [VALUE]: see the usage above
    local value=${1:-} f
    case "$value" in
        none) echo none; return 0 ;;
        '') ;;
        /*)
            [[ "$value" != *[[:cntrl:]]* ]] && [ -f "$value" ] && [ -r "$value" ] \
                || die "ros_setup: '$value' is not a readable file" 2
            echo "$value"; return 0 ;;
        *) die "ros_setup: '$value' is neither an absolute path nor none" 2 ;;
    esac
    for f in /opt/ros/noetic/setup.bash /opt/ros/*/setup.bash; do
        if [ -f "$f" ]; then echo "$f"; return 0; fi
    done
    echo none
}

do_deps() {  # do_deps ROLE [--ros-setup FILE|none] [--dry-run]
    local role=$1 setup='' dry_run=no packages=() missing=() p distro
    shift
    while [ $# -gt 0 ]; do
        case "$1" in
            --ros-setup) [ $# -ge 2 ] || die "deps: --ros-setup needs a value" 2; setup=$(do_ros_setup "$2"); shift 2 ;;
            --dry-run) dry_run=yes; shift ;;
            *) die "deps: unknown option '$1'" 2 ;;
        esac
    done
    [ -n "$setup" ] || setup=$(do_ros_setup)
    case "$role" in
        master|robot) ;;
        *) die "deps: role must be master or robot, not '$role'" 2 ;;
    esac
    describe_system
    if [ "$setup" = none ]; then
        packages=("${ROS_PACKAGES[@]}")
        echo "ROS packages: the system's own, as ROS is on the system's paths (ros-core, python3-rospy, ...)"
    elif [[ "$setup" =~ ^/opt/ros/([a-z][a-z0-9_]*)/setup\.bash$ ]]; then
        distro=${BASH_REMATCH[1]}
        for p in "${ROS_REPOSITORY_PACKAGES[@]}"; do packages+=("ros-$distro-$p"); done
        packages+=("${ROS_REPOSITORY_EXTRA[@]}")
        echo "ROS packages: ROS's own for $distro, from ROS's apt repository (ros-$distro-rospy, ...);" \
             "none of the system's ROS packages"
    else
        echo "ROS packages: none ($setup is not a ROS from packages: what it lacks is yours to build);" \
             "only the agent's own dependencies"
    fi
    packages+=("${AGENT_PACKAGES[@]}")
    [ "$role" = robot ] || packages+=("${MASTER_PACKAGES[@]}")
    local installed
    # (dpkg-query fails for names it has never heard of: that only means they are missing)
    installed=" $({ dpkg-query -W -f='${Package} ${Status}\n' "${packages[@]}" 2>/dev/null || true; } \
                  | sed -n 's/^\([^ ]*\) install ok installed$/\1/p' | tr '\n' ' ') "
    for p in "${packages[@]}"; do
        case "$installed" in *" $p "*) ;; *) missing+=("$p") ;; esac
    done
    if [ "$dry_run" = yes ]; then
        echo "Missing: ${missing[*]}"
        return 0
    fi
    if [ ${#missing[@]} -eq 0 ]; then
        echo "Dependencies: all ${#packages[@]} packages are already installed"
        return 0
    fi
    need_root
    echo "Dependencies: installing ${missing[*]} with apt-get"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq || die "apt-get update failed"
    if ! apt-get install -y -qq --no-install-recommends "${missing[@]}"; then
        if [ -n "$distro" ]; then
            die "apt-get could not install ${missing[*]}: is ROS's apt repository for $distro set up" \
                "(docs/INSTALL.md)? For a ROS built from source, run install.sh with --skip-deps"
        fi
        die "apt-get install failed"
    fi
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

    # the platform's VPN (docs/VPN.md): HOME/vpn is root's alone (0700); the agent runs OpenVPN with it
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
    ros-setup) [ $# -le 2 ] || die "usage: sub_inst.sh ros-setup [FILE|none]" 2; do_ros_setup "${2:-}" ;;
    deps) [ $# -ge 2 ] || die "usage: sub_inst.sh deps master|robot [--ros-setup FILE|none] [--dry-run]" 2
          shift; do_deps "$@" ;;
    install) need_root; shift; do_install "$@" ;;
    start|restart) need_root; do_service "$@" ;;
    *) die "usage: sub_inst.sh ros-setup|deps|install|start|restart ... (run by install.sh)" 2 ;;
esac
