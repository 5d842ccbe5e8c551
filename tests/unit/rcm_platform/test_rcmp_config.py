"""rcmp_config: loading the configuration files (every key, the roles' defaults, one-line errors), ``make_config``
and the derived addresses."""

import os

import pytest

from rcm_platform.rcmp_config import (ConfigError, folder_problem, load_config, make_config, platform_address,
                                      rdapi_address, ros_setup_script)
from tests.support.paths import REPO

SEED_MASTER = "# .init.cfg\n\n[main]\ninbound_open_ports=10100, 10101, 10102, 10103\n"
SEED_ROBOT = "# init.cfg\n\n[main]\nname=robot1\nrobot=yes\nip_master=10.11.12.1\n"


def write(home, name, text):
    path = os.path.join(str(home), name)
    with open(path, "w") as f:
        f.write(text)
    return path


def test_master_without_file_uses_defaults(tmp_path):
    config = load_config(tmp_path)
    assert config.role == "master" and config.config_file is None
    assert config.name == "master"
    assert config.inbound_open_ports == [10100, 10101, 10102, 10103]
    assert (config.ext_port, config.ic_port, config.ros_port_base) == (80, 9999, 11311)
    assert (config.vpn_interface, config.ext_interface) == ("tun0", "eth0")
    assert config.vpn_address is None and config.ext_address is None
    assert (config.heartbeat_interval, config.heartbeat_misses) == (2.0, 3)
    assert config.log_max_bytes == 1024 * 1024


def test_seed_files_work_unchanged(tmp_path):
    path = write(tmp_path, ".init.cfg", SEED_MASTER)
    config = load_config(tmp_path)
    assert config.role == "master" and config.config_file == path
    assert config.inbound_open_ports == [10100, 10101, 10102, 10103]

    robot_home = tmp_path / "robot"
    robot_home.mkdir()
    path = write(robot_home, "init.cfg", SEED_ROBOT)
    config = load_config(robot_home)
    assert (config.role, config.name, config.ip_master, config.config_file) == ("robot", "robot1", "10.11.12.1",
                                                                                  path)
    assert config.inbound_open_ports == [] and config.ic_port == 9999


def test_template_is_all_comments_and_loads(tmp_path):
    with open(os.path.join(REPO, "cfg", "init_template.cfg")) as f:
        text = f.read()
    assert "[main]" in text and "# ip_master=10.xx.yy.1" in text
    write(tmp_path, "init.cfg", text + "name=from_template\n")
    config = load_config(tmp_path)
    assert config.role == "robot" and config.name == "from_template"


def test_server_vm_and_every_ext_key(tmp_path):
    write(tmp_path, "init.cfg", "[main]\nname=vm1\nrobot=no\nip_master=198.51.100.1\ninbound_open_ports=10200\n"
                                "vpn_interface=lo\nvpn_address=198.51.100.7\nic_port=9000\nros_port_base=12000\n"
                                "heartbeat_interval=0.5\nheartbeat_misses=4\nlog_max_bytes=4096\n")
    config = load_config(tmp_path)
    assert config.role == "server" and config.name == "vm1"
    assert config.inbound_open_ports == [10200]
    assert (config.vpn_interface, config.vpn_address, config.ic_port, config.ros_port_base) == (
        "lo", "198.51.100.7", 9000, 12000)
    assert (config.heartbeat_interval, config.heartbeat_misses, config.log_max_bytes) == (0.5, 4, 4096)
    assert platform_address(config) == "198.51.100.7"


def test_master_ext_keys_and_addresses(tmp_path):
    write(tmp_path, ".init.cfg", "[main]\nname=hub\ninbound_open_ports=\nvpn_interface=lo\next_interface=lo\n"
                                 "ext_port=8080\nic_port=9998\n")
    config = load_config(tmp_path)
    assert config.name == "hub" and config.inbound_open_ports == []
    assert platform_address(config) == "127.0.0.1" and rdapi_address(config) == "127.0.0.1"
    config.ext_address = "127.0.0.5"
    assert rdapi_address(config) == "127.0.0.5"
    config.vpn_interface = "nosuch0"
    assert platform_address(config) is None


def test_robot_default_ip_master_is_own_vpn_address_with_last_octet_1(tmp_path):
    write(tmp_path, "init.cfg", "[main]\nname=r1\nvpn_address=198.51.100.6\n")
    assert load_config(tmp_path).ip_master == "198.51.100.1"
    write(tmp_path, "init.cfg", "[main]\nname=r1\nvpn_interface=nosuch0\n")
    assert load_config(tmp_path).ip_master is None  # not known until the VPN is up


def test_make_config_gives_what_load_config_gives(tmp_path):
    """The defaults live in one place: a Config built in code equals the one read from a file with those keys."""
    assert make_config("master", str(tmp_path)) == load_config(tmp_path)
    path = write(tmp_path, "init.cfg", "[main]\nname=r1\nrobot=no\nvpn_interface=nosuch0\nros_port_base=12000\n")
    assert make_config("server", str(tmp_path), path, name="r1", vpn_interface="nosuch0",
                       ros_port_base=12000) == load_config(tmp_path)
    with pytest.raises(TypeError):
        make_config("robot", str(tmp_path), name="r1", no_such_key=1)


def test_servers_allow_list(tmp_path):
    assert load_config(tmp_path).servers is None                 # unset: no list
    write(tmp_path, ".init.cfg", "[main]\nservers=vm1, vm2@10.11.12.40 ,\n")
    assert load_config(tmp_path).servers == {"vm1": None, "vm2": "10.11.12.40"}
    write(tmp_path, ".init.cfg", "[main]\nservers=\n")
    assert load_config(tmp_path).servers == {}                   # empty: no server VM may join
    assert make_config("master", str(tmp_path), os.path.join(str(tmp_path), ".init.cfg"), servers={}) == \
        load_config(tmp_path)


BAD = [
    (".init.cfg", "[main]\next_port=abc\n", "key 'ext_port': not a port number: 'abc'"),
    (".init.cfg", "[main]\next_port=0\n", "key 'ext_port': not a port number"),
    (".init.cfg", "[main]\nic_port=70000\n", "key 'ic_port': not a port number"),
    (".init.cfg", "[main]\ninbound_open_ports=10100, x\n", "key 'inbound_open_ports': not a port number: 'x'"),
    (".init.cfg", "[main]\ninbound_open_ports=10100, 10100\n", "key 'inbound_open_ports': port 10100 is listed twice"),
    (".init.cfg", "[main]\nvpn_address=198.51.100.300\n", "key 'vpn_address': not an IPv4 address"),
    (".init.cfg", "[main]\nnmae=x\n", "unknown key 'nmae'"),
    (".init.cfg", "[main]\nrobot=yes\n", "key 'robot': not used by the master"),
    (".init.cfg", "[main]\nip_master=198.51.100.1\n", "key 'ip_master': not used by the master"),
    (".init.cfg", "inbound_open_ports=10100\n", "line 1: a key before the [main] section"),
    (".init.cfg", "[other]\nx=1\n", "no [main] section"),
    (".init.cfg", "[main]\n[extra]\n", "unknown section [extra]"),
    (".init.cfg", "[main]\next_port=1\next_port=2\n", "key 'ext_port': given twice"),
    (".init.cfg", "[main]\next_port=8080\nic_port=8080\n", "must all differ"),
    (".init.cfg", "[main]\nheartbeat_interval=-1\n", "key 'heartbeat_interval'"),
    (".init.cfg", "[main]\nheartbeat_misses=zero\n", "key 'heartbeat_misses': not a whole number"),
    (".init.cfg", "[main]\nlog_max_bytes=10\n", "key 'log_max_bytes': must be between"),
    (".init.cfg", "[main]\nvpn_interface=a b\n", "key 'vpn_interface': not a network interface name"),
    ("init.cfg", "[main]\nname=r1\nrobot=maybe\n", "key 'robot': expected yes or no: 'maybe'"),
    ("init.cfg", "[main]\nname=robot/1\n", "key 'name': not a valid instance name"),
    ("init.cfg", "[main]\nname=r1\nip_master=master.local\n", "key 'ip_master': not an IPv4 address"),
    ("init.cfg", "[main]\nname=r1\next_port=8080\n", "key 'ext_port': not used by a robot"),
    ("init.cfg", "[main]\nname=r1\nrobot=no\next_address=1.2.3.4\n", "key 'ext_address': not used by a server VM"),
    ("init.cfg", "[main]\nname=r1\nmax_service_spaces=5\n", "key 'max_service_spaces': not used by a robot"),
    (".init.cfg", "[main]\nmax_service_spaces=-1\n", "key 'max_service_spaces': must be between 0 and 100000"),
    (".init.cfg", "[main]\nmax_service_spaces=100001\n", "key 'max_service_spaces': must be between 0 and 100000"),
    ("init.cfg", b"[main]\nname=\xff\n", "not a UTF-8 text file"),
    (".init.cfg", "[main]\nservers=vm1, vm-2\n", "key 'servers': not a valid instance name"),
    (".init.cfg", "[main]\nservers=vm1, vm1@198.51.100.2\n", "key 'servers': server vm1 is listed twice"),
    (".init.cfg", "[main]\nservers=vm1@198.51.100.300\n", "key 'servers': not an IPv4 address"),
    ("init.cfg", "[main]\nname=r1\nrobot=no\nservers=vm1\n", "key 'servers': not used by a server VM"),
    ("init.cfg", "[main]\nname=r1\nros_setup=opt/ros/noetic/setup.bash\n",
     "key 'ros_setup': neither none nor the absolute path of a setup script"),
    (".init.cfg", "[main]\nros_setup=\n", "key 'ros_setup': neither none nor the absolute path"),
    (".init.cfg", "[main]\nros_setup=None\n", "key 'ros_setup': neither none nor the absolute path"),
]


@pytest.mark.parametrize("name,text,expected", BAD)
def test_bad_configuration_is_one_line_naming_file_and_key(tmp_path, name, text, expected):
    path = os.path.join(str(tmp_path), name)
    with open(path, "wb") as f:
        f.write(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(path + ": "), message
    assert expected in message, message


def test_missing_home(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nothing")


@pytest.mark.parametrize("make,expected", [
    (lambda base: base / "nothing", "the platform folder does not exist"),
    (lambda base: (base / "f").write_text("x") and base / "f", "the platform folder is a file, not a folder"),
    (lambda base: (base / "f").write_text("x") and base / "f" / "home",
     "the platform folder cannot exist: {base}/f is a file, not a folder"),
    (lambda base: os.symlink(base / "gone", base / "l") or base / "l",
     "the platform folder is a symbolic link to '{base}/gone', which does not exist"),
    (lambda base: os.mkfifo(base / "p") or base / "p", "the platform folder is a named pipe, not a folder"),
])
def test_each_wrong_kind_of_platform_folder_is_named(tmp_path, make, expected):
    path = make(tmp_path)
    expected = expected.format(base=tmp_path)
    assert folder_problem(str(path)) == expected
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == f"{path}: {expected}"


def test_a_device_is_not_a_platform_folder():
    assert folder_problem("/dev/null") == "the platform folder is a character device, not a folder"
    assert folder_problem("/dev/null", what="the agent's log folder") == \
        "the agent's log folder is a character device, not a folder"


def test_a_usable_folder_has_no_problem(tmp_path):
    assert folder_problem(str(tmp_path)) is None and folder_problem(str(tmp_path), write=True) is None


# -- where ROS is: the rule of sub_inst.sh ros-setup ----------------------------------------------------------------

def setup_scripts(root, *distros):
    for distro in distros:
        (root / distro).mkdir(parents=True)
        (root / distro / "setup.bash").write_text("# ROS's setup script\n")


def test_ros_setup_is_the_given_script_else_the_first_under_opt_ros_noetic_first_else_none(tmp_path):
    ros = tmp_path / "ros"
    write(tmp_path, ".init.cfg", "[main]\n")
    config = load_config(tmp_path)
    assert config.ros_setup is None
    assert ros_setup_script(config, str(ros)) == (None, f"no {ros}/*/setup.bash")   # Debian: ROS in /usr
    setup_scripts(ros, "melodic", "kinetic")
    (ros / "aaa").mkdir()                                      # a folder without a setup script does not count
    assert ros_setup_script(config, str(ros)) == (str(ros / "kinetic" / "setup.bash"), f"found in {ros}")
    setup_scripts(ros, "noetic")
    assert ros_setup_script(config, str(ros)) == (str(ros / "noetic" / "setup.bash"), f"found in {ros}")

    # given: none keeps the system's ROS beside an /opt/ros; a file is taken as it is (the agent checks it)
    write(tmp_path, ".init.cfg", "[main]\nros_setup=none\n")
    assert ros_setup_script(load_config(tmp_path), str(ros)) == (None, "ros_setup=none")
    write(tmp_path, ".init.cfg", "[main]\nros_setup= /home/me/ros_catkin_ws/install_isolated/setup.bash\n")
    config = load_config(tmp_path)
    assert ros_setup_script(config, str(ros)) == ("/home/me/ros_catkin_ws/install_isolated/setup.bash", "ros_setup")
    robot = tmp_path / "robot"
    robot.mkdir()
    write(robot, "init.cfg", "[main]\nname=r1\nrobot=no\nros_setup=/opt/ros/noetic/setup.bash\n")
    assert load_config(robot).ros_setup == "/opt/ros/noetic/setup.bash"   # every role takes it
