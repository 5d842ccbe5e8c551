#!/bin/bash
# install.sh: installs the RCM agent of this distribution package (rcm_platform_master or rcm_platform_robot).
#
# Owns the installing user's half of the installation: the step-by-step configuration wizard (or, with
# --non-interactive, the same answers from flags), the catkin workspace ~/rcmp_ws (with firos, rcm and
# robotics_msgs unpacked into src/ on a master with FIWARE support) and the configuration file's content.
# Everything that needs root (apt-get, /usr/local/bin/rcmp_n, the rcm_platform package, /opt/rcm-platform,
# /etc/init.d/rcmpd) is done by sub_inst.sh, run through sudo when the user is not root; sub_inst.sh also says
# which ROS installation (its setup script) and which package names this machine gets. The workspace is built
# inside that setup script's environment, so the workspace chains onto that ROS.
# Run it again to change the configuration: the current values are the defaults.
set -eo pipefail
export LC_ALL=C

HERE=$(cd "$(dirname "$0")" && pwd)
PROG=install.sh
if [ -f "$HERE/rcm_platform/rcmp_ext_connector.py" ]; then ROLE=master; else ROLE=robot; fi
DEFAULT_PORTS="10100, 10101, 10102, 10103"
DEFAULT_VPN_SUBNET=10.11.12.0/24   # the original guide's example (docs/VPN.md)
DEFAULT_VPN_PORT=1194
COMPONENT_ZIPS=(firos.zip rcm_driver.zip robotics_msgs.zip)

usage() {
    cat <<EOF
Usage: ./install.sh [options]

Installs the rcm $ROLE agent from this folder. Without options it asks every question step by step
(choices in ( ), the default in [ ]; Enter takes the default). Any answer given as an option is not asked.

Answers:
  --replace-ws yes|no      replace an existing workspace (default yes)
EOF
    if [ "$ROLE" = master ]; then cat <<EOF
  --fiware yes|no          FIWARE support: firos, rcm_driver and robotics_msgs into the workspace
                           (default yes when their zips are in this folder)
  --inbound-ports LIST     inbound open ports, comma separated (default "$DEFAULT_PORTS")
  --vpn yes|no             create the platform's own VPN (OpenVPN, 'rcmp_n vpn init') (default yes)
  --no-vpn                 the same as --vpn no: the VPN is the administrator's, as in the original platform
  --vpn-subnet CIDR        the VPN's subnet; the master takes its first address (default $DEFAULT_VPN_SUBNET)
  --vpn-port N             the VPN's UDP port (default $DEFAULT_VPN_PORT)
  --vpn-remote HOST        the address robots reach the master at (default: the address of ext_interface)
EOF
    else cat <<EOF
  --robot yes|no           this machine is a robot (no: a server virtual machine) (default yes)
  --name NAME              platform instance name, as provisioned on the master (default: host name)
  --vpn-config FILE        the client file 'rcmp_n vpn client NAME' (a server VM: 'rcmp_n vpn client NAME
                           --server') wrote on the master: the agent runs the platform's VPN with it (installed
                           as HOME/vpn/client.conf); 'none': the VPN is the administrator's (default: none, or
                           keep the one installed)
  --ip-master ADDRESS      the master's VPN address (default: this machine's VPN address, last octet 1)
EOF
    fi
    cat <<EOF
  --start yes|no           start (or restart) the rcm daemon at the end (default yes)
  -n, --non-interactive    ask nothing: options, then the current configuration, then defaults

Optional configuration keys (written only when given; a re-run keeps the current ones):
  --vpn-interface IF  --vpn-address ADDRESS  --ic-port PORT  --ros-port-base PORT
  --ros-setup FILE|none    the ROS installation's setup script, for the workspace build, the agent and its
                           nodes (default: the first /opt/ros/*/setup.bash, noetic first; none: ROS is on the
                           system's paths, as Debian's packages put it)
EOF
    if [ "$ROLE" = master ]; then cat <<EOF
  --ext-interface IF  --ext-address ADDRESS  --ext-port PORT
EOF
    fi
    cat <<EOF

Installation places:
  --home DIR               platform folder (default /opt/rcm-platform)
  --workspace DIR          catkin workspace (default ~/rcmp_ws)
  --service-name NAME      init script /etc/init.d/NAME (default rcmpd)
  --bin-dir DIR            where rcmp_n goes (default /usr/local/bin)
  --lib-dir DIR            where the rcm_platform package goes (default: /usr/bin/python3's site dist-packages)
  --skip-deps              do not run apt-get: the dependencies are installed already, or ROS is a source
                           build (give its setup script with --ros-setup)
  --dry-run                ask (or take) every answer, show the configuration and the steps, change nothing
  -h, --help               this text
EOF
}

die() { echo "$PROG: error: $1" >&2; exit "${2:-1}"; }
usage_error() { echo "$PROG: error: $*" >&2; echo "Try './install.sh --help'." >&2; exit 2; }
trim() { local s=$1; s=${s#"${s%%[![:space:]]*}"}; s=${s%"${s##*[![:space:]]}"}; printf '%s' "$s"; }

# --- answer checkers: print the normalized value, or an explanation and return 1 ---------------------------------
check_yesno() {
    case "${1,,}" in
        y|yes) echo yes ;;
        n|no) echo no ;;
        *) echo "Please answer yes or no."; return 1 ;;
    esac
}
check_port() {
    if [[ "$1" =~ ^[0-9]{1,5}$ ]] && [ "$((10#$1))" -ge 1 ] && [ "$((10#$1))" -le 65535 ]; then
        echo "$((10#$1))"
    else
        echo "'$1' is not a port number (1-65535)."; return 1
    fi
}
check_ports() {
    local item out=() seen=" " p
    IFS=',' read -r -a items <<<"$1"
    for item in "${items[@]}"; do
        item=$(trim "$item")
        p=$(check_port "$item") || { echo "'$item' in '$1' is not a port number (1-65535)."; return 1; }
        case "$seen" in *" $p "*) echo "Port $p is listed twice in '$1'."; return 1 ;; esac
        seen="$seen$p "
        out+=("$p")
    done
    [ ${#out[@]} -gt 0 ] || { echo "At least one port is needed."; return 1; }
    local joined; joined=$(printf '%s, ' "${out[@]}"); echo "${joined%, }"
}
check_ipv4() {
    local o1 o2 o3 o4
    if [[ "$1" =~ ^([0-9]{1,3})\.([0-9]{1,3})\.([0-9]{1,3})\.([0-9]{1,3})$ ]]; then
        o1=${BASH_REMATCH[1]} o2=${BASH_REMATCH[2]} o3=${BASH_REMATCH[3]} o4=${BASH_REMATCH[4]}
        if [ $((10#$o1)) -le 255 ] && [ $((10#$o2)) -le 255 ] && [ $((10#$o3)) -le 255 ] && [ $((10#$o4)) -le 255 ]; then
            echo "$((10#$o1)).$((10#$o2)).$((10#$o3)).$((10#$o4))"; return 0
        fi
    fi
    echo "'$1' is not an IPv4 address (like 10.11.12.1)."; return 1
}
check_subnet() {  # an IPv4 network in CIDR form, /8 to /29, its host bits zero (rcmp_n vpn init checks again)
    local addr bits a o1 o2 o3 o4
    if [[ "$1" =~ ^([0-9.]+)/([0-9]{1,2})$ ]]; then
        bits=$((10#${BASH_REMATCH[2]}))
        if a=$(check_ipv4 "${BASH_REMATCH[1]}") && [ "$bits" -ge 8 ] && [ "$bits" -le 29 ]; then
            IFS=. read -r o1 o2 o3 o4 <<<"$a"
            addr=$(( (o1 << 24) | (o2 << 16) | (o3 << 8) | o4 ))
            if [ $(( addr & ((1 << (32 - bits)) - 1) )) -eq 0 ]; then echo "$a/$bits"; return 0; fi
            echo "'$1' has host bits set (a network address, like 10.11.12.0/24, is needed)."; return 1
        fi
    fi
    echo "'$1' is not an IPv4 subnet from /8 to /29 (like 10.11.12.0/24)."; return 1
}
check_host() {
    if [[ "$1" =~ ^[A-Za-z0-9]([A-Za-z0-9.-]{0,251}[A-Za-z0-9])?$ ]]; then echo "$1"
    else echo "'$1' is not a host name or IPv4 address."; return 1; fi
}
check_vpn_config() {  # none, keep (when one is installed), or a client file written by 'rcmp_n vpn client'
    case "$1" in
        none) echo "$1"; return 0 ;;
        keep) check_vpn_role "${VPN_DIR:-}/client.conf" "the installed client file" || return 1; echo "$1"; return 0 ;;
    esac
    local f=$1
    [[ "$f" = /* ]] || f=$PWD/$f
    if [ ! -f "$f" ] || [ ! -r "$f" ]; then echo "'$1' is not a readable file."; return 1; fi
    if ! grep -q '^client[[:space:]]*$' "$f" || ! grep -q '^<key>' "$f" || ! grep -q '^<cert>' "$f"; then
        echo "'$1' is not an OpenVPN client file written by 'rcmp_n vpn client NAME' (client, <cert>, <key>)."
        return 1
    fi
    check_vpn_role "$f" "'$1'" || return 1
    echo "$f"
}
check_vpn_role() {  # FILE WHAT: once the machine's kind is known, its client file must hold a certificate for it
    local role what
    [ -n "${ANS[robot]:-}" ] && [ -r "$1" ] || return 0
    role=$(sed -n 's/^# Certificate role: \([a-z]*\)$/\1/p' "$1" | head -n 1)
    if [ "${ANS[robot]}" = no ] && [ "$role" != server ]; then
        if [ -n "$role" ]; then what="a robot's certificate"; else what="a certificate issued before certificate roles, which counts as a robot's"; fi
        echo "$2 holds $what; a server VM needs a server certificate: on the master, 'rcmp_n vpn client NAME --server -o FILE'."
        return 1
    fi
    if [ "${ANS[robot]}" = yes ] && [ "$role" = server ]; then
        echo "$2 holds a server VM's certificate; a robot needs a robot certificate: on the master, 'rcmp_n vpn client NAME -o FILE'."
        return 1
    fi
}
check_name() {
    if [[ "$1" =~ ^[A-Za-z][A-Za-z0-9_]*$ ]]; then echo "$1"
    else echo "'$1' is not a valid name: a letter, then letters, digits and underscores."; return 1; fi
}
check_ifname() {
    if [[ "$1" =~ ^[A-Za-z0-9_.:-]{1,15}$ ]]; then echo "$1"
    else echo "'$1' is not a network interface name."; return 1; fi
}
check_ros_setup() {  # none, or the absolute path of a readable file
    case "$1" in
        none) echo none; return 0 ;;
        /*) if [[ "$1" != *[[:cntrl:]]* ]] && [ -f "$1" ] && [ -r "$1" ]; then echo "$1"; return 0; fi ;;
    esac
    echo "'$1' is not a readable setup script given by its absolute path (like /opt/ros/noetic/setup.bash), nor none."
    return 1
}
check_path() {
    case "$1" in
        /) echo "'/' cannot be used here."; return 1 ;;
        /*) echo "${1%/}" ;;
        *) echo "'$1' is not an absolute path."; return 1 ;;
    esac
}

# --- command line ----------------------------------------------------------------------------------------------
INTERACTIVE=yes
SKIP_DEPS=no
DRY_RUN=no
declare -A OPT=()
set_opt() {  # set_opt KEY CHECKER OPTION VALUE
    local v
    v=$("$2" "$4") || usage_error "$3: $v"
    OPT[$1]=$v
}
while [ $# -gt 0 ]; do
    opt=$1
    case "$opt" in
        -h|--help) usage; exit 0 ;;
        -n|--non-interactive) INTERACTIVE=no; shift; continue ;;
        --no-vpn)
            [ "$ROLE" = master ] || usage_error "unknown option '$opt' for the rcm robot installer"
            OPT[vpn]=no; shift; continue ;;
        --skip-deps) SKIP_DEPS=yes; shift; continue ;;
        --dry-run) DRY_RUN=yes; shift; continue ;;
        --*=*) set -- "${opt%%=*}" "${opt#*=}" "${@:2}"; continue ;;
    esac
    case "$opt" in
        --replace-ws|--start|--inbound-ports|--vpn-interface|--vpn-address|--ic-port|--ros-port-base|--home) ;;
        --ros-setup) ;;
        --workspace|--bin-dir|--lib-dir|--service-name) ;;
        --fiware|--ext-interface|--ext-address|--ext-port|--vpn|--vpn-subnet|--vpn-port|--vpn-remote)
            [ "$ROLE" = master ] || usage_error "unknown option '$opt' for the rcm robot installer" ;;
        --robot|--name|--ip-master|--vpn-config)
            [ "$ROLE" = robot ] || usage_error "unknown option '$opt' for the rcm master installer" ;;
        *) usage_error "unknown option '$opt'" ;;
    esac
    [ $# -ge 2 ] || usage_error "$opt needs a value"
    val=$2
    case "$opt" in
        --replace-ws) set_opt replace_ws check_yesno "$opt" "$val" ;;
        --start) set_opt start check_yesno "$opt" "$val" ;;
        --inbound-ports) set_opt inbound_open_ports check_ports "$opt" "$val" ;;
        --vpn-interface) set_opt vpn_interface check_ifname "$opt" "$val" ;;
        --vpn-address) set_opt vpn_address check_ipv4 "$opt" "$val" ;;
        --ic-port) set_opt ic_port check_port "$opt" "$val" ;;
        --ros-port-base) set_opt ros_port_base check_port "$opt" "$val" ;;
        --ros-setup) set_opt ros_setup check_ros_setup "$opt" "$val" ;;
        --home) set_opt home check_path "$opt" "$val" ;;
        --workspace) set_opt workspace check_path "$opt" "$val" ;;
        --bin-dir) set_opt bin_dir check_path "$opt" "$val" ;;
        --lib-dir) set_opt lib_dir check_path "$opt" "$val" ;;
        --service-name) set_opt service_name check_name "$opt" "$val" ;;
        *)
            if [ "$ROLE" = master ]; then
                case "$opt" in
                    --fiware) set_opt fiware check_yesno "$opt" "$val" ;;
                    --ext-interface) set_opt ext_interface check_ifname "$opt" "$val" ;;
                    --ext-address) set_opt ext_address check_ipv4 "$opt" "$val" ;;
                    --ext-port) set_opt ext_port check_port "$opt" "$val" ;;
                    --vpn) set_opt vpn check_yesno "$opt" "$val" ;;
                    --vpn-subnet) set_opt vpn_subnet check_subnet "$opt" "$val" ;;
                    --vpn-port) set_opt vpn_port check_port "$opt" "$val" ;;
                    --vpn-remote) set_opt vpn_remote check_host "$opt" "$val" ;;
                    *) usage_error "unknown option '$opt' for the rcm master installer" ;;
                esac
            else
                case "$opt" in
                    --robot) set_opt robot check_yesno "$opt" "$val" ;;
                    --name) set_opt name check_name "$opt" "$val" ;;
                    --ip-master) set_opt ip_master check_ipv4 "$opt" "$val" ;;
                    --vpn-config) set_opt vpn_config check_vpn_config "$opt" "$val" ;;
                    *) usage_error "unknown option '$opt' for the rcm robot installer" ;;
                esac
            fi ;;
    esac
    shift 2
done

if [ -n "${OPT[vpn_subnet]+set}${OPT[vpn_port]+set}${OPT[vpn_remote]+set}" ]; then
    [ "${OPT[vpn]:-yes}" = yes ] || usage_error "--no-vpn (--vpn no) cannot go with --vpn-subnet, --vpn-port or --vpn-remote"
    OPT[vpn]=yes  # settings for the VPN answer the question
fi
HOME_DIR=${OPT[home]:-/opt/rcm-platform}
VPN_DIR=$HOME_DIR/vpn
WS=${OPT[workspace]:-$HOME/rcmp_ws}
SERVICE=${OPT[service_name]:-rcmpd}
BIN_DIR=${OPT[bin_dir]:-/usr/local/bin}
# the first site folder of the system's python: /usr/local/lib/python3.X/dist-packages on Debian and Ubuntu, on its
# sys.path (Ubuntu 20.04's sysconfig names a folder that is not)
LIB_DIR=${OPT[lib_dir]:-$(/usr/bin/python3 -c 'import site; print(site.getsitepackages()[0])')}
if [ "$ROLE" = master ]; then CFG_FILE=$HOME_DIR/.init.cfg; else CFG_FILE=$HOME_DIR/init.cfg; fi

# --- the current configuration gives the defaults of a re-run ---------------------------------------------------
cfg_get() {  # the value of KEY in the current configuration file, or nothing
    [ -r "$CFG_FILE" ] || return 0
    local line value=
    while IFS= read -r line; do
        if [[ "$line" =~ ^[[:space:]]*$1[[:space:]]*[=:](.*)$ ]]; then value=$(trim "${BASH_REMATCH[1]}"); fi
    done <"$CFG_FILE"
    printf '%s' "$value"
}
current() {  # current KEY CHECKER: the configured value if it is valid
    local v; v=$(cfg_get "$1"); [ -n "$v" ] || return 0
    local out; if out=$("$2" "$v"); then printf '%s' "$out"; fi
}

vpn_guess() {  # this machine's VPN address: --vpn-address, or the address of the VPN interface
    if [ -n "${ANS[vpn_address]}" ]; then echo "${ANS[vpn_address]}"; return; fi
    ip -4 -o addr show dev "${ANS[vpn_interface]:-tun0}" 2>/dev/null | sed -n 's/.* inet \([0-9.]*\)\/.*/\1/p' | sed -n 1p
}

# --- the wizard --------------------------------------------------------------------------------------------------
declare -A ANS=()
ask() {  # ask KEY CHECKER DEFAULT QUESTION: the option's value, or the user's answer (Enter = DEFAULT)
    local key=$1 checker=$2 default=$3 question=$4 answer value
    if [ -n "${OPT[$key]+set}" ]; then ANS[$key]=${OPT[$key]}; return; fi
    if [ "$INTERACTIVE" = no ]; then
        [ -n "$default" ] || die "no value for '$key': give it as an option (see --help)" 2
        ANS[$key]=$default; return
    fi
    while true; do
        printf '%s ' "$question"
        IFS= read -r answer || { echo; die "no answer to \"$question\" (end of input)"; }
        [ -t 0 ] || echo "$answer"  # answers from a pipe or file: show them, as a terminal would
        answer=$(trim "$answer")
        [ -n "$answer" ] || answer=$default
        if [ -z "$answer" ]; then echo "An answer is needed."; continue; fi
        if value=$("$checker" "$answer"); then ANS[$key]=$value; return; fi
        echo "$value"
    done
}
yn_question() {  # the ([Y]es/no) or (yes/[N]o) suffix
    if [ "$1" = yes ]; then echo "([Y]es/no)?"; else echo "(yes/[N]o)?"; fi
}
with_default() { if [ -n "$1" ]; then echo " [$1]:"; else echo ":"; fi; }

echo "RCM $ROLE installation from $HERE"
if [ -d "$WS" ]; then
    ask replace_ws check_yesno yes "The workspace $(basename "$WS") already exists: do you wanna replace it $(yn_question yes)"
else
    ANS[replace_ws]=yes
fi

# optional keys: options first, then the current configuration; never asked
for key in vpn_interface vpn_address ic_port ros_port_base ext_interface ext_address ext_port ros_setup; do
    if [ -n "${OPT[$key]+set}" ]; then ANS[$key]=${OPT[$key]}; continue; fi
    case $key in
        vpn_address|ext_address) ANS[$key]=$(current "$key" check_ipv4) ;;
        ic_port|ros_port_base|ext_port) ANS[$key]=$(current "$key" check_port) ;;
        ros_setup) ANS[$key]=$(current "$key" check_ros_setup) ;;
        *) ANS[$key]=$(current "$key" check_ifname) ;;
    esac
done

# the ROS installation: ros_setup, else the first /opt/ros/*/setup.bash (noetic first), else none (sub_inst.sh)
ROS_SETUP=$("$HERE/sub_inst.sh" ros-setup "${ANS[ros_setup]}") || exit 2
if [ -n "${ANS[ros_setup]}" ]; then
    how="given as ros_setup"
elif [ "$ROS_SETUP" != none ]; then
    how="found in /opt/ros; --ros-setup chooses another, or none"
else
    how="no /opt/ros/*/setup.bash"
fi
if [ "$ROS_SETUP" = none ]; then
    echo "ROS setup script: none ($how): ROS is on the system's paths, as Debian's packages put it"
else
    echo "ROS setup script: $ROS_SETUP ($how)"
fi

if [ "$ROLE" = master ]; then
    have_zips=yes
    for z in "${COMPONENT_ZIPS[@]}"; do [ -f "$HERE/$z" ] || have_zips=no; done
    check_fiware() {
        local v; v=$(check_yesno "$1") || { echo "$v"; return 1; }
        if [ "$v" = yes ] && [ "$have_zips" = no ]; then
            echo "firos.zip, rcm_driver.zip and robotics_msgs.zip are not in $HERE: answer no and install them" \
                 "by hand into the workspace's src/, or use robotics.zip."
            return 1
        fi
        echo "$v"
    }
    if [ -n "${OPT[fiware]+set}" ]; then
        msg=$(check_fiware "${OPT[fiware]}") || usage_error "--fiware: $msg"
    fi
    ask fiware check_fiware "$have_zips" "Do you want FIWARE support (firos, rcm_driver and robotics_msgs in the workspace) $(yn_question "$have_zips")"
    ports_default=$(current inbound_open_ports check_ports); ports_default=${ports_default:-$DEFAULT_PORTS}
    ask inbound_open_ports check_ports "$ports_default" "Inbound open ports, comma separated$(with_default "$ports_default")"
    if [ -e "$VPN_DIR/server.conf" ]; then
        # an existing VPN is kept: a new one would need a new client file on every robot
        if [ -n "${OPT[vpn_subnet]+set}${OPT[vpn_port]+set}${OPT[vpn_remote]+set}" ]; then
            die "the platform's VPN already exists in $VPN_DIR and is kept: --vpn-subnet, --vpn-port and --vpn-remote only make a new one (to replace it, and every robot's client file: rcmp_n vpn init --force ...). Nothing was changed." 2
        fi
        ANS[vpn]=keep
    else
        ask vpn check_yesno yes "Do you want the platform to create its own VPN (OpenVPN; no: you run the VPN yourself) $(yn_question yes)"
    fi
    ANS[vpn_subnet]=${OPT[vpn_subnet]:-$DEFAULT_VPN_SUBNET}
    ANS[vpn_port]=${OPT[vpn_port]:-$DEFAULT_VPN_PORT}
    ANS[vpn_remote]=${OPT[vpn_remote]:-}
else
    robot_default=$(current robot check_yesno); robot_default=${robot_default:-yes}
    ask robot check_yesno "$robot_default" "Is this machine a robot (no: a virtual machine on the server side) $(yn_question "$robot_default")"
    name_default=$(current name check_name)
    if [ -z "$name_default" ]; then
        name_default=$(check_name "$(hostname -s 2>/dev/null | tr '.-' '__')") || name_default=
    fi
    ask name check_name "$name_default" "Name of this platform instance (as provisioned on the master)$(with_default "$name_default")"
    if [ -e "$VPN_DIR/client.conf" ]; then vpn_default=keep; else vpn_default=none; fi
    if [ "${ANS[robot]}" = no ]; then issue="rcmp_n vpn client NAME --server"; else issue="rcmp_n vpn client NAME"; fi
    ask vpn_config check_vpn_config "$vpn_default" "OpenVPN client file of this machine, from '$issue' on the master (none: you run the VPN yourself)$(with_default "$vpn_default")"
    # an option (read before the machine's kind was known) or a default taken without asking: checked for its role
    msg=$(check_vpn_config "${ANS[vpn_config]}") || usage_error "--vpn-config: $msg"
    if [ "${ANS[vpn_config]}" = keep ] && [ ! -e "$VPN_DIR/client.conf" ]; then
        die "--vpn-config keep: no client file is installed in $VPN_DIR" 2
    fi
    master_default=$(current ip_master check_ipv4)
    if [ -z "$master_default" ]; then
        own=$(vpn_guess || true)
        [ -n "$own" ] && master_default=${own%.*}.1
    fi
    if [ -z "$master_default" ] && [ -z "${OPT[ip_master]+set}" ] && [ "${ANS[vpn_config]}" != none ]; then
        # the platform's VPN is not up yet: the agent takes its own VPN address with the last octet 1
        ANS[ip_master]=
        echo "VPN address of the rcm master: this machine's VPN address with the last octet 1, once the VPN is up (--ip-master to choose)"
    else
        ask ip_master check_ipv4 "$master_default" "VPN address of the rcm master$(with_default "$master_default")"
    fi
    ANS[inbound_open_ports]=${OPT[inbound_open_ports]:-$(current inbound_open_ports check_ports)}
fi
ask start check_yesno yes "Do you want to start the rcm daemon now $(yn_question yes)"
if [ "$ROLE" = robot ] && [ "${ANS[robot]}" = yes ] && [ -n "${ANS[ros_port_base]}" ]; then
    if [ -n "${OPT[ros_port_base]+set}" ]; then
        die "ros_port_base (--ros-port-base) is only for a server virtual machine (--robot no): nothing was changed" 2
    fi
    ANS[ros_port_base]=  # kept from a server VM's configuration: a robot has no service spaces of its own
fi

# --- the configuration file ----------------------------------------------------------------------------------------
CFG_TMP=$(mktemp)
trap 'rm -f "$CFG_TMP"' EXIT
{
    if [ "$ROLE" = master ]; then
        echo "# .init.cfg: configuration of the rcm master, written by install.sh (run it again to change it)"
        echo "[main]"
        echo "inbound_open_ports=${ANS[inbound_open_ports]}"
        keys="ext_interface ext_address ext_port vpn_interface vpn_address ic_port ros_port_base ros_setup"
    else
        echo "# init.cfg: configuration of this rcm instance, written by install.sh (run it again to change it)"
        echo "[main]"
        echo "name=${ANS[name]}"
        echo "robot=${ANS[robot]}"
        [ -z "${ANS[ip_master]}" ] || echo "ip_master=${ANS[ip_master]}"
        [ -z "${ANS[inbound_open_ports]}" ] || echo "inbound_open_ports=${ANS[inbound_open_ports]}"
        keys="vpn_interface vpn_address ic_port ros_port_base ros_setup"
    fi
    for key in $keys; do
        [ -z "${ANS[$key]}" ] || echo "$key=${ANS[$key]}"
    done
    # keys the wizard does not manage (heartbeat_interval, log_max_bytes, ...) survive a re-run as they were
    if [ -r "$CFG_FILE" ]; then
        if [ "$ROLE" = master ]; then managed=" inbound_open_ports $keys "
        else managed=" name robot ip_master inbound_open_ports $keys ext_interface ext_address ext_port ros_port_base "; fi
        while IFS= read -r line; do
            if [[ "$line" =~ ^[[:space:]]*([A-Za-z_][A-Za-z0-9_]*)[[:space:]]*[=:] ]]; then
                case "$managed" in *" ${BASH_REMATCH[1]} "*) ;; *) echo "$(trim "$line")" ;; esac
            fi
        done <"$CFG_FILE"
    fi
} >"$CFG_TMP"
chmod 0644 "$CFG_TMP"

vpn_steps() {  # what happens to the platform's VPN
    if [ "$ROLE" = master ]; then
        case "${ANS[vpn]}" in
            yes) echo "  - create the platform's VPN in $VPN_DIR: subnet ${ANS[vpn_subnet]}, UDP port ${ANS[vpn_port]}, remote ${ANS[vpn_remote]:-the address of the external interface}" ;;
            keep) echo "  - keep the platform's VPN in $VPN_DIR" ;;
            *) echo "  - not create a VPN (the administrator runs it)" ;;
        esac
    else
        case "${ANS[vpn_config]}" in
            none) echo "  - not install a VPN client file (the administrator runs the VPN)" ;;
            keep) echo "  - keep the VPN client file $VPN_DIR/client.conf" ;;
            *) echo "  - install ${ANS[vpn_config]} as $VPN_DIR/client.conf (mode 0600)" ;;
        esac
    fi
}

if [ "$DRY_RUN" = yes ]; then
    missing=
    if [ "$SKIP_DEPS" = no ]; then
        plan=$("$HERE/sub_inst.sh" deps "$ROLE" --ros-setup "$ROS_SETUP" --dry-run) || exit 2
        grep -v '^Missing:' <<<"$plan" || true
        missing=$(sed -n 's/^Missing: *//p' <<<"$plan")
    fi
    echo "Dry run: nothing was changed. The installation would:"
    if [ "$SKIP_DEPS" = yes ]; then
        echo "  - not install dependencies (--skip-deps)"
    elif [ -n "$missing" ]; then
        echo "  - install the missing dependencies of the rcm $ROLE with apt-get: $missing"
    else
        echo "  - install no dependencies: everything the rcm $ROLE needs is installed"
    fi
    if [ -d "$WS" ] && [ "${ANS[replace_ws]}" = yes ]; then echo "  - replace the workspace $WS"
    elif [ -d "$WS" ]; then echo "  - keep the workspace $WS"
    else echo "  - create the workspace $WS"; fi
    if [ "$ROLE" = master ] && [ "${ANS[fiware]}" = yes ]; then
        echo "  - unpack ${COMPONENT_ZIPS[*]} into $WS/src"
    fi
    if [ -f "$WS/devel/setup.bash" ] && [ "${ANS[replace_ws]}" = no ] && [ "${ANS[fiware]:-no}" = no ]; then
        echo "  - keep the workspace's build"
    elif [ "$ROS_SETUP" = none ]; then
        echo "  - build the workspace with catkin_make"
    else
        echo "  - build the workspace with catkin_make in the environment of $ROS_SETUP"
    fi
    echo "  - install $BIN_DIR/rcmp_n, $LIB_DIR/rcm_platform, $HOME_DIR/rosconsole.config and /etc/init.d/$SERVICE"
    vpn_steps
    if [ "${ANS[start]}" = yes ]; then echo "  - start the rcm daemon ($SERVICE)"; else echo "  - not start the rcm daemon"; fi
    echo "  - write $CFG_FILE:"
    sed 's/^/    /' "$CFG_TMP"
    exit 0
fi

as_root() {
    if [ "$(id -u)" -eq 0 ]; then "$@"; else
        command -v sudo >/dev/null || die "the next step needs root and sudo is not installed: run ./install.sh as root"
        echo "$PROG: the next step needs administration rights: sudo $(basename "$1") ${2:-}"
        sudo "$@"
    fi
}

# --- 1. dependencies (root) ------------------------------------------------------------------------------------------
if [ "$SKIP_DEPS" = no ]; then
    as_root "$HERE/sub_inst.sh" deps "$ROLE" --ros-setup "$ROS_SETUP"
fi

# --- 2. the workspace (the installing user) -----------------------------------------------------------------------
build_needed=no
if [ -d "$WS" ] && [ "${ANS[replace_ws]}" = yes ]; then
    echo "Replacing the workspace $WS"
    rm -rf -- "$WS"
fi
if [ ! -d "$WS/src" ]; then build_needed=yes; fi
mkdir -p "$WS/src"
if [ "$ROLE" = master ] && [ "${ANS[fiware]}" = yes ]; then
    for z in "${COMPONENT_ZIPS[@]}"; do
        root=$(unzip -Z1 "$HERE/$z" | sed -n 1p); root=${root%%/*}
        if [ ! -e "$WS/src/$root" ]; then
            echo "Unpacking $z into $WS/src"
            unzip -q -o "$HERE/$z" -d "$WS/src"
            build_needed=yes
        fi
    done
fi
[ -f "$WS/devel/setup.bash" ] || build_needed=yes
build_workspace() (  # a subshell: the ROS setup script's environment stays in it
    export PATH=/usr/bin:/bin:/usr/sbin:/sbin:$PATH   # the system's python3 before any other (pyenv, venvs)
    if [ "$ROS_SETUP" != none ]; then
        set --            # a sourced catkin setup.bash hands the caller's arguments to its _setup_util.py
        set +e +u
        # shellcheck disable=SC1090
        source "$ROS_SETUP" || { echo "$PROG: error: $ROS_SETUP failed" >&2; exit 1; }
        set -e
    fi
    if ! command -v catkin_make >/dev/null; then
        echo "$PROG: error: catkin_make was not found (ROS setup script: $ROS_SETUP): install ROS, or give" \
             "its setup script with --ros-setup; nothing was installed" >&2
        exit 3
    fi
    cd "$WS"
    catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3 -DCATKIN_ENABLE_TESTING=OFF >"$WS/build.log" 2>&1
)
if [ "$build_needed" = yes ]; then
    echo "Building the workspace $WS with catkin_make (log: $WS/build.log)"
    if build_workspace; then :; else
        rc=$?
        [ "$rc" -ne 3 ] || exit 1
        tail -n 30 "$WS/build.log" >&2
        die "catkin_make failed in $WS; nothing was installed (full log: $WS/build.log)"
    fi
fi

# --- 3. files, configuration and the init script (root) ----------------------------------------------------------
VPN_ARGS=()
if [ "$ROLE" = master ] && [ "${ANS[vpn]}" = yes ]; then
    VPN_ARGS=(--vpn-subnet "${ANS[vpn_subnet]}" --vpn-port "${ANS[vpn_port]}")
    [ -z "${ANS[vpn_remote]}" ] || VPN_ARGS+=(--vpn-remote "${ANS[vpn_remote]}")
elif [ "$ROLE" = robot ] && [ "${ANS[vpn_config]}" != none ] && [ "${ANS[vpn_config]}" != keep ]; then
    VPN_ARGS=(--vpn-config "${ANS[vpn_config]}")
fi
as_root "$HERE/sub_inst.sh" install --role "$ROLE" --src "$HERE" --home "$HOME_DIR" --bin-dir "$BIN_DIR" \
    --lib-dir "$LIB_DIR" --service-name "$SERVICE" --workspace "$WS" --config "$CFG_TMP" "${VPN_ARGS[@]}"

# --- 4. the daemon ---------------------------------------------------------------------------------------------------
if [ "${ANS[start]}" = yes ]; then
    as_root "$HERE/sub_inst.sh" restart --service-name "$SERVICE"
else
    echo "The rcm daemon was not started: start it with 'sudo service $SERVICE start'" \
         "(or 'sudo service $SERVICE restart' if it was already running)."
fi
echo "RCM $ROLE installed: configuration $CFG_FILE, workspace $WS."
