"""Service spaces with real ROS: ServiceSpaceManager (server side) and ItemRunner (robot side, in process,
reached through a RemoteAgent that calls it directly), real rosmaster, real rosrun/roslaunch children of the
test package robotics_test, the real rcm_driver and FIROS. Each test checks that nothing it started is left."""

import json
import os
import random
import shutil
import signal
import socket
import subprocess
import tempfile

import rosgraph
from twisted.internet import defer, reactor, task, threads
from twisted.trial import unittest

from rcm_platform import rcmp_ms, rcmp_service_item
from rcm_platform.rcmp_config import make_config
from rcm_platform.rcmp_service_command import describe
from rcm_platform.rcmp_ms import ItemRunner, ServiceSpaceManager
from rcm_platform.rcmp_process import FAILED, LIVE_STATES, RUNNING, ProcessTable
from tests.support.polling import until_deferred
from tests.support.ports import port_accepts, ros_port_base
from tests.support.processes import ros_env
from tests.unit.rcm_platform.test_rcmp_service_item import launcher, node

MASTER_IP = "127.0.0.1"
ROBOT_IP = "127.0.0.2"   # the robot's agent and its R items live on another loopback address


def quiet_ports(count):
    """Free ports below the ephemeral range (32768+), so no client connection of a busy machine takes one
    between choosing and using it (the inbound ports must stay bindable for the whole test)."""
    ports = []
    for port in random.sample(range(20000, 32000), 400):
        if rcmp_ms._tcp_port_free(port):
            ports.append(port)
            if len(ports) == count:
                return ports
    raise AssertionError("no free ports between 20000 and 32000")


class InProcessRobot:
    """A RemoteAgent whose agent is an ItemRunner in this process (what rcmp_event does over TCP)."""

    def __init__(self, name, runner, address=ROBOT_IP):
        self.name = name
        self.address = address          # its session's source address: the master takes its ROS master only there
        self.runner = runner
        self.calls = []

    def start_items(self, ss_name, ros_master_uri, items, start_ros_master_port=None):
        self.calls.append(("start_items", ss_name, ros_master_uri, len(items), start_ros_master_port))
        return self.runner.start_items(ss_name, ros_master_uri, items, start_ros_master_port)

    def stop_items(self, ss_name):
        self.calls.append(("stop_items", ss_name))
        return self.runner.stop_items(ss_name)


def processes_with_env(name, value_prefix):
    """pids of living processes whose environment has ``name`` starting with ``value_prefix``."""
    wanted = f"{name}={value_prefix}".encode()
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    continue
            with open(f"/proc/{entry}/environ", "rb") as f:
                if any(var.startswith(wanted) for var in f.read().split(b"\0")):
                    found.append(int(entry))
        except (OSError, IndexError):
            continue
    return found


class ServiceSpaceTests(unittest.TestCase):
    timeout = 90

    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="ms-space-")
        self.env = ros_env()
        self.master_table = ProcessTable(reactor, os.path.join(self.tmp, "master-log"), settle_time=1.0,
                                         stop_timeouts=(3.0, 1.0))
        self.robot_table = ProcessTable(reactor, os.path.join(self.tmp, "robot-log"), settle_time=1.0,
                                        stop_timeouts=(3.0, 1.0))
        self.master_config = make_config("master", self.tmp, vpn_address=MASTER_IP, vpn_interface="lo",
                                         inbound_open_ports=quiet_ports(2), ros_port_base=ros_port_base())
        self.robot_config = make_config("robot", self.tmp, name="robot1", vpn_address=ROBOT_IP, vpn_interface="lo",
                                        ros_port_base=ros_port_base())
        self.exits = []
        self.states = []
        self.runner = ItemRunner(reactor, self.robot_table, self.robot_config, env=self.env,
                                      on_item_exited=self._robot_item_exited)
        self.manager = ServiceSpaceManager(reactor, self.master_table, self.master_config, "192.0.2.10",
                                           env=self.env, on_state=lambda *a: self.states.append(a[:2]))
        self.robot = InProcessRobot("robot1", self.runner)

    def _robot_item_exited(self, ss_name, report):
        self.exits.append((ss_name, report))
        self.manager.item_exited(ss_name, report)

    @defer.inlineCallbacks
    def tearDown(self):
        try:
            yield self.manager.teardown_all()
            yield self.runner.stop_all()
            yield self.master_table.stop_all()
            yield self.robot_table.stop_all()
            left = processes_with_env("ROS_LOG_DIR", self.tmp)
            for pid in left:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            self.assertEqual(left, [], "processes of the service spaces were left running")
        finally:
            shutil.rmtree(self.tmp, True)

    @defer.inlineCallbacks
    def wait_for(self, condition, timeout=15.0, what="condition"):
        deadline = reactor.seconds() + timeout
        while True:
            value = yield threads.deferToThread(_try, condition)
            if value:
                return value
            self.assertLess(reactor.seconds(), deadline, f"timed out waiting for {what}")
            yield task.deferLater(reactor, 0.05, lambda: None)

    def graph(self, uri):
        return rosgraph.Master("/ms_test", master_uri=uri)

    # -- tests --------------------------------------------------------------------------------------------

    @defer.inlineCallbacks
    def test_s_and_r_nodes_pair_and_teardown_leaves_nothing(self):
        logic = {"ss_side": "S", "sn_list": [node("s_talker", params="_topic:=s_chatter"),
                                             node("r_talker", side="R", params="_topic:=r_chatter")],
                 "sl_list": []}
        space = yield self.manager.create("robot1", logic, self.robot)
        self.assertTrue(space.paired, describe(self.manager, "robot1"))
        self.assertEqual(self.states, [("robot1", True)])
        uri = space.ros_master_uri
        self.assertTrue(uri.startswith(f"http://{MASTER_IP}:"))
        self.assertGreaterEqual(space.ros_master_port, self.master_config.ros_port_base)
        self.assertEqual(self.robot.calls[0], ("start_items", "robot1", uri, 1, None))

        topics = yield self.wait_for(lambda: {t for t, _ in self.graph(uri).getPublishedTopics("")} >=
                                     {"/s_chatter", "/r_chatter"}, what="both topics")
        self.assertTrue(topics)
        # the R node advertises the robot's address (ROS_IP), the S node the master's
        r_api = yield threads.deferToThread(self.graph(uri).lookupNode, "/r_talker")
        s_api = yield threads.deferToThread(self.graph(uri).lookupNode, "/s_talker")
        self.assertIn(f"//{ROBOT_IP}:", r_api)
        self.assertIn(f"//{MASTER_IP}:", s_api)

        described = describe(self.manager, "robot1")
        nodes = {n["sn_name"]: n for n in described["r_nodes"]}
        self.assertEqual(nodes["s_talker"]["i_name"], "master")
        self.assertEqual(nodes["r_talker"]["i_name"], "robot1")
        self.assertEqual({n["state"] for n in nodes.values()}, {RUNNING})
        self.assertEqual(described["public_ip"], "192.0.2.10")
        self.assertIsNone(described["inbound_port"])
        self.assertEqual(described["ros_master_uri"], uri)
        self.assertEqual(described["r_launchers"], [])

        order = []
        for managed in self.master_table.processes() + self.robot_table.processes():
            managed.listeners.append(lambda m, old, new: order.append((m.key, new)))
        yield self.manager.teardown("robot1")
        self.assertEqual(self.robot.calls[-1], ("stop_items", "robot1"))
        # R items on the robot, then S items, then rosout, then the ROS master; each gone before the next
        self.assertEqual([key for key, state in order if state == "exited"], [
            "robot/robot1/node/r_talker", "ss/robot1/node/s_talker", "ss/robot1/rosout", "ss/robot1/rosmaster"])
        self.assertEqual(self.states, [("robot1", True), ("robot1", False)])
        self.assertIsNone(describe(self.manager, "robot1"))
        self.assertEqual(processes_with_env("ROS_LOG_DIR", self.tmp), [])
        self.assertFalse(port_accepts(space.ros_master_port), "the ROS master still listens")

    @defer.inlineCallbacks
    def test_an_empty_service_logic_pairs_once_the_ros_master_runs_and_rosout_follows(self):
        space = yield self.manager.create("robot1", {"ss_side": "S", "sn_list": [], "sl_list": []}, self.robot)
        self.assertTrue(space.paired, describe(self.manager, "robot1"))
        # pairing waits for the ROS master only; rosout (logs) registers on its own shortly after
        yield until_deferred(lambda: space.rosout.state == RUNNING, timeout=10, message="rosout to register")
        self.assertEqual(self.robot.calls, [])  # nothing to ask the robot
        described = describe(self.manager, "robot1")
        self.assertEqual((described["r_nodes"], described["r_launchers"]), ([], []))
        yield self.manager.teardown("robot1")

    @defer.inlineCallbacks
    def test_launcher_nodes_are_associated_and_stopped(self):
        logic = {"sn_list": [], "sl_list": [launcher("two", params="prefix:=xx"),
                                            launcher("rtwo", side="R", params="prefix:=rr")]}
        space = yield self.manager.create("robot1", logic, self.robot)
        self.assertTrue(space.paired, describe(self.manager, "robot1"))
        described = describe(self.manager, "robot1")
        launchers = {entry["sl_name"]: entry for entry in described["r_launchers"]}
        self.assertEqual(sorted(launchers["two"]["associated_r_nodes"]), ["xx_talker_a", "xx_talker_b"])
        self.assertEqual(sorted(launchers["rtwo"]["associated_r_nodes"]), ["rr_talker_a", "rr_talker_b"])
        self.assertEqual(launchers["rtwo"]["i_name"], "robot1")
        r_nodes = {n["sn_name"]: n for n in described["r_nodes"]}
        self.assertEqual(r_nodes["xx_talker_a"]["sn_type"], "talker.py")
        self.assertEqual(r_nodes["xx_talker_a"]["i_name"], "master")
        self.assertEqual(r_nodes["rr_talker_b"]["i_name"], "robot1")
        yield self.wait_for(lambda: {"/xx_talker_a", "/xx_talker_b", "/rr_talker_a", "/rr_talker_b"} <=
                            _node_names(self.graph(space.ros_master_uri)), what="the launchers' nodes")
        yield self.manager.teardown("robot1")
        self.assertEqual(processes_with_env("ROS_LOG_DIR", self.tmp), [])

    @defer.inlineCallbacks
    def test_launcher_whose_node_cannot_start_is_failed_though_roslaunch_runs(self):
        # a throwaway package, first on ROS_PACKAGE_PATH for us (roslaunch's loader) and for the children
        pkg = os.path.join(self.tmp, "pkgs", "ms_bad_launch")
        os.makedirs(os.path.join(pkg, "launch"))
        with open(os.path.join(pkg, "package.xml"), "w") as f:
            f.write('<?xml version="1.0"?><package format="2"><name>ms_bad_launch</name><version>0.0.1</version>'
                    '<description>test</description><maintainer email="t@example.com">t</maintainer>'
                    '<license>MIT</license><buildtool_depend>catkin</buildtool_depend></package>')
        with open(os.path.join(pkg, "launch", "half.launch"), "w") as f:
            f.write('<launch><node pkg="robotics_test" type="talker.py" name="good_half" />'
                    '<node pkg="robotics_test" type="no_such_node.py" name="bad_half" /></launch>')
        package_path = os.path.join(self.tmp, "pkgs") + ":" + os.environ.get("ROS_PACKAGE_PATH", "")
        old = os.environ.get("ROS_PACKAGE_PATH")
        os.environ["ROS_PACKAGE_PATH"] = package_path
        self.addCleanup(lambda: os.environ.__setitem__("ROS_PACKAGE_PATH", old) if old is not None
                        else os.environ.pop("ROS_PACKAGE_PATH", None))
        self.env["ROS_PACKAGE_PATH"] = package_path
        self.manager.launcher_nodes_timeout = 3.0
        logic = {"sl_list": [launcher("half", package="ms_bad_launch", launch_file="half.launch")]}
        space = yield self.manager.create("robot1", logic, None)
        self.assertFalse(space.paired)
        entry = describe(self.manager, "robot1")["r_launchers"][0]
        self.assertEqual(sorted(entry["associated_r_nodes"]), ["bad_half", "good_half"])
        self.assertEqual(entry["state"], FAILED)
        self.assertIn("bad_half", entry["error"])
        self.assertNotIn("good_half,", entry["error"])
        self.assertIn("cannot launch node of type [robotics_test/no_such_node.py]", entry["error"])
        self.assertNotIn("\x1b", entry["error"])  # no colours or terminal titles
        launcher_proc = self.master_table.get("ss/robot1/launcher/half")
        self.assertEqual(launcher_proc.state, RUNNING)  # roslaunch itself carries on
        yield self.manager.teardown("robot1")

    @defer.inlineCallbacks
    def test_items_that_cannot_start_leave_the_space_unpaired_with_their_error(self):
        logic = {"sn_list": [node("good", params="_topic:=good"), node("ghost", package="no_such_pkg_x"),
                             node("crash", side="R", node_type="crasher.py")],
                 "sl_list": [launcher("nofile", launch_file="missing.launch")]}
        space = yield self.manager.create("robot1", logic, self.robot)
        self.assertFalse(space.paired)  # the missing launch file is known before anything runs
        self.assertEqual(self.states, [])

        def failed_ones():  # on a loaded machine an item may exit just after the settle time
            described = describe(self.manager, "robot1")
            states = {n["sn_name"]: n["state"] for n in described["r_nodes"]}
            return described if states["ghost"] == states["crash"] == FAILED else None
        described = yield self.wait_for(failed_ones, what="ghost and crash to fail")
        nodes = {n["sn_name"]: n for n in described["r_nodes"]}
        self.assertEqual(nodes["good"]["state"], RUNNING)
        self.assertNotIn("error", nodes["good"])
        self.assertEqual(nodes["ghost"]["state"], FAILED)
        self.assertIn("no_such_pkg_x", nodes["ghost"]["error"])
        self.assertEqual(nodes["crash"]["state"], FAILED)
        self.assertEqual(nodes["crash"]["i_name"], "robot1")
        self.assertIn("status 3", nodes["crash"]["error"])
        self.assertIn("cannot open /dev/imaginary_lidar", nodes["crash"]["error"])
        nofile = described["r_launchers"][0]
        self.assertEqual(nofile["state"], FAILED)
        self.assertIn("missing.launch", nofile["error"])
        self.assertFalse(described["paired"])
        self.assertTrue(described["reason"])
        yield self.manager.teardown("robot1")

    @defer.inlineCallbacks
    def test_items_that_die_later_unpair_the_space(self):
        logic = {"sn_list": [node("s_talker"), node("r_talker", side="R", params="_topic:=r_chatter")]}
        space = yield self.manager.create("robot1", logic, self.robot)
        self.assertTrue(space.paired)
        r_proc = self.robot_table.get("robot/robot1/node/r_talker")
        os.killpg(r_proc.pid, signal.SIGKILL)
        yield self.wait_for(lambda: not space.paired, what="the space to unpair")
        self.assertEqual(self.states, [("robot1", True), ("robot1", False)])
        self.assertEqual(self.exits[0][0], "robot1")
        self.assertEqual(self.exits[0][1]["name"], "r_talker")
        r_node = [n for n in describe(self.manager, "robot1")["r_nodes"] if n["sn_name"] == "r_talker"][0]
        self.assertEqual(r_node["state"], FAILED)
        self.assertIn(f"killed by signal {int(signal.SIGKILL)}", r_node["error"])

        s_proc = self.master_table.get("ss/robot1/node/s_talker")
        os.killpg(s_proc.pid, signal.SIGKILL)
        yield self.wait_for(lambda: s_proc.state == FAILED, what="the S node to fail")
        s_node = [n for n in describe(self.manager, "robot1")["r_nodes"] if n["sn_name"] == "s_talker"][0]
        self.assertEqual(s_node["state"], FAILED)
        yield self.manager.teardown("robot1")
        self.assertEqual(self.states[-1], ("robot1", False))
        self.assertEqual(len(self.states), 2)  # unpaired once, not again at teardown

    @defer.inlineCallbacks
    def test_ss_side_r_runs_the_ros_master_on_the_robot(self):
        logic = {"ss_side": "R", "sn_list": [node("s_talker", params="_topic:=s_chatter"),
                                             node("r_talker", side="R", params="_topic:=r_chatter")]}
        space = yield self.manager.create("robot1", logic, self.robot)
        self.assertTrue(space.paired, describe(self.manager, "robot1"))
        self.assertTrue(space.ros_master_uri.startswith(f"http://{ROBOT_IP}:"))
        self.assertEqual(self.robot.calls[0][4], self.master_config.ros_port_base)
        self.assertIsNotNone(self.robot_table.get("robot/robot1/rosmaster"))
        self.assertIsNone(self.master_table.get("ss/robot1/rosmaster"))
        yield self.wait_for(lambda: {"/s_talker", "/r_talker", "/rosout"} <=
                            _node_names(self.graph(space.ros_master_uri)), what="nodes on the robot's master")
        yield self.manager.teardown("robot1")
        self.assertEqual(processes_with_env("ROS_LOG_DIR", self.tmp), [])

    @defer.inlineCallbacks
    def test_two_robots_get_separate_spaces_and_ports(self):
        logic = {"sn_list": [node("s_talker")]}
        first = yield self.manager.create("robot1", logic, None)
        second = yield self.manager.create("robot2", logic, None)
        self.assertTrue(first.paired and second.paired)
        self.assertNotEqual(first.ros_master_port, second.ros_master_port)
        yield self.wait_for(lambda: "/s_talker" in _node_names(self.graph(second.ros_master_uri)),
                            what="robot2's node on robot2's master")
        yield self.manager.teardown("robot1")
        self.assertTrue(port_accepts(second.ros_master_port))
        self.assertIsNotNone(describe(self.manager, "robot2"))

    @defer.inlineCallbacks
    def test_a_ros_master_port_taken_after_it_was_chosen_fails_the_space_at_once_with_the_reason(self):
        # the race: the port is free when chosen and taken (here: bound, not listening) before rosmaster binds it
        holder = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.addCleanup(holder.close)
        holder.bind(("127.0.0.1", 0))
        taken = holder.getsockname()[1]
        self.manager._choose_ros_port = lambda base: taken
        started = reactor.seconds()
        space = yield self.manager.create("robot1", {"sn_list": [node("s_talker")]}, None)
        self.assertFalse(space.paired)
        self.assertIn(f"could not listen on port {taken}", space.reason)
        self.assertLess(reactor.seconds() - started, self.manager.master_timeout / 2)
        self.assertIn("could not listen", describe(self.manager, "robot1")["reason"])
        yield self.manager.teardown("robot1")
        self.assertEqual(processes_with_env("ROS_LOG_DIR", self.tmp), [])

    @defer.inlineCallbacks
    def test_bad_service_logic_is_refused_before_anything_starts(self):
        with self.assertRaises(ValueError):
            yield self.manager.create("robot1", {"sn_list": [{"sn_name": "x"}]}, None)
        with self.assertRaises(ValueError):
            yield self.manager.create("robot1", {"sn_list": [node("r", side="R")]}, None)
        self.assertIsNone(describe(self.manager, "robot1"))
        self.assertEqual(self.master_table.processes(), [])

    @defer.inlineCallbacks
    def test_teardown_while_creating_leaves_nothing(self):
        logic = {"sn_list": [node("s_talker"), node("r_talker", side="R")]}
        creating = self.manager.create("robot1", logic, self.robot)
        yield task.deferLater(reactor, 0.3, lambda: None)
        yield self.manager.teardown("robot1")
        space = yield creating
        self.assertFalse(space.paired)
        self.assertIsNone(describe(self.manager, "robot1"))
        yield self.wait_for(lambda: not processes_with_env("ROS_LOG_DIR", self.tmp), what="no process left")

    @defer.inlineCallbacks
    def test_firos_gets_an_inbound_port_until_none_is_left(self):
        logic = {"sn_list": [node("firos", package="firos", node_type="core.py")]}
        spaces = []
        for name in ("robot1", "robot2", "robot3"):
            space = yield self.manager.create(name, logic, None)
            spaces.append(space)
        ports = self.master_config.inbound_open_ports
        self.assertTrue(spaces[0].paired, describe(self.manager, "robot1"))
        self.assertTrue(spaces[1].paired, describe(self.manager, "robot2"))
        self.assertEqual(sorted([spaces[0].inbound_port, spaces[1].inbound_port]), sorted(ports))
        self.assertEqual(describe(self.manager, "robot1")["inbound_port"], spaces[0].inbound_port)
        yield self.wait_for(lambda: port_accepts(spaces[0].inbound_port), what="FIROS on its -P port")
        third = describe(self.manager, "robot3")
        self.assertFalse(spaces[2].paired)
        self.assertIsNone(third["inbound_port"])
        self.assertIn("no inbound open port left", third["reason"])
        self.assertIn("no inbound open port left", third["r_nodes"][0]["error"])

        yield self.manager.teardown("robot1")     # releases its port
        yield self.wait_for(lambda: not port_accepts(spaces[0].inbound_port), what="FIROS to let go of its port")
        again = yield self.manager.create("robot3", logic, None)
        self.assertTrue(again.paired, describe(self.manager, "robot3"))
        self.assertEqual(again.inbound_port, spaces[0].inbound_port)

    @defer.inlineCallbacks
    def _driver_says_connected_and_carries_events(self, space):
        """rcm_driver's latched /rcm/robot_event says robot1 CONNECTED, and a CB_Event comes back to the agent."""
        env = dict(self.env, ROS_MASTER_URI=space.ros_master_uri, ROS_IP=MASTER_IP,
                   ROS_LOG_DIR=os.path.join(self.tmp, "rostopic"))
        echoed = yield threads.deferToThread(subprocess.run, [
            "rostopic", "echo", "-n", "1", "/rcm/robot_event"], env=env, capture_output=True, text=True,
            timeout=30)
        self.assertIn("instance_name: \"robot1\"", echoed.stdout)
        self.assertIn("instance_status: 1", echoed.stdout)
        told = []       # what the observers (the console) could see each time they were told of robot1

        def observer(name):
            if name == "robot1":
                told.append(list((describe(self.manager, "robot1") or {}).get("rcm_driver_events", [])))
        self.manager.observers.append(observer)
        self.addCleanup(self.manager.observers.remove, observer)
        yield threads.deferToThread(subprocess.run, [
            "rostopic", "pub", "-1", "/firos/cb_event", "robotics_msgs/CB_Event",
            "{entity_name: robot1, entity_status: 1}"], env=env, capture_output=True, timeout=30)
        yield self.wait_for(lambda: describe(self.manager, "robot1").get("rcm_driver_events"),
                            what="e_created from rcm_driver")
        self.assertIn({"rcm_d_cmd": "e_created", "r_name": "robot1"},
                      describe(self.manager, "robot1")["rcm_driver_events"])
        # the observers were told when it came (the console describes again only the spaces they name)
        self.assertIn({"rcm_d_cmd": "e_created", "r_name": "robot1"}, told[-1] if told else [])

    @defer.inlineCallbacks
    def test_rcm_driver_is_told_about_the_robot(self):
        self.manager.driver_goodbye_timeout = 0.5
        logic = {"sn_list": [node("rcmdriver", package="rcm", node_type="rcm_driver.py")]}
        space = yield self.manager.create("robot1", logic, None)
        self.assertTrue(space.paired, describe(self.manager, "robot1"))
        driver = [i for i in space.items if i.special is rcmp_service_item.SPECIAL_ITEMS[("rcm", "rcm_driver.py")]][0]
        self.assertIn(f"port={driver.driver_port}", driver.process.argv)
        # rcm_driver's default port or the next free ones, never an ephemeral (port-0) one that a stranger can take
        self.assertTrue(rcmp_ms.RCM_DRIVER_PORT <= driver.driver_port < 32768, driver.driver_port)
        self.assertIsNotNone(space.driver_link)
        yield self._driver_says_connected_and_carries_events(space)
        yield self.manager.teardown("robot1")


    @defer.inlineCallbacks
    def test_rcm_driver_obeys_only_the_agent_that_started_it(self):
        """Issue 18: rcm_driver's local port took r_connection / r_disconnection from any local user. Now the agent
        starts it with a one-time key: a local user's lines are refused and their connections closed, silent
        ones cannot keep a slot, and the agent's own connection goes on working."""
        logic = {"sn_list": [node("rcmdriver", package="rcm", node_type="rcm_driver.py")]}
        space = yield self.manager.create("robot1", logic, None)
        self.assertTrue(space.paired, describe(self.manager, "robot1"))
        driver = [i for i in space.items if i.special is not None][0]
        self.assertNotIn(driver.driver_key, " ".join(driver.process.argv))   # not on the command line
        port = driver.driver_port

        def attack():
            closed = []
            for key in (None, "guessed", "0" * 32):
                for command in ("r_disconnection", "r_connection"):
                    with socket.create_connection(("127.0.0.1", port), timeout=15) as sock:
                        line = {"rcm_d_cmd": command, "r_name": "robot1"}
                        if key is not None:
                            line["key"] = key
                        sock.sendall(json.dumps(line).encode() + b"\n")
                        try:
                            closed.append(sock.recv(1) == b"")
                        except ConnectionResetError:
                            closed.append(True)
            squatters = [socket.create_connection(("127.0.0.1", port), timeout=15) for _ in range(40)]
            return closed, squatters
        closed, squatters = yield threads.deferToThread(attack)
        self.addCleanup(lambda: [s.close() for s in squatters])
        self.assertEqual(closed, [True] * 6)
        # no stranger's r_disconnection was published, and the agent's own connection still carries FIROS's
        # events back, with the squatters still there
        yield self._driver_says_connected_and_carries_events(space)
        output = driver.process.tail(200)
        self.assertEqual(output.count("r_disconnection robot1"), 0, output)
        self.assertIn("does not carry the key", output)
        yield self.manager.teardown("robot1")

    @defer.inlineCallbacks
    def test_a_lost_rcm_driver_connection_is_made_again(self):
        logic = {"sn_list": [node("rcmdriver", package="rcm", node_type="rcm_driver.py")]}
        space = yield self.manager.create("robot1", logic, None)
        first = space.driver_link
        self.assertIsNotNone(first)
        driver = [i for i in space.items if i.special is not None][0]
        yield self.wait_for(lambda: "connected with the key" in driver.process.tail(200),
                            what="rcm_driver to obey the agent")
        first.transport.abortConnection()                  # as rcm_driver closing it would
        yield self.wait_for(lambda: space.driver_link not in (None, first), what="a new connection to rcm_driver")
        yield self.wait_for(lambda: driver.process.tail(200).count("connected with the key") == 2,
                            what="rcm_driver to see the agent again")
        self.assertEqual(space.driver_reconnects, 1)
        yield self.manager.teardown("robot1")

    @defer.inlineCallbacks
    def test_a_space_placed_on_a_server_vm_runs_its_s_side_there(self):
        """The master's capacity 0: the space goes to server vm1 (an ItemRunner as a server VM's agent has
        it), whose ROS master starts from vm1's own ros_port_base at vm1's address, with rcm_driver told
        r_connection there; the robot's R node uses vm1's master; teardown leaves nothing."""
        server_ip = "127.0.0.3"
        self.master_config.max_service_spaces = 0
        self.manager = ServiceSpaceManager(reactor, self.master_table, self.master_config, "192.0.2.10",
                                           env=self.env, on_state=lambda *a: self.states.append(a[:2]))
        server_config = make_config("server", self.tmp, name="vm1", vpn_address=server_ip, vpn_interface="lo",
                                    ros_port_base=ros_port_base(server_ip))
        server_table = ProcessTable(reactor, os.path.join(self.tmp, "server-log"), settle_time=1.0,
                                    stop_timeouts=(3.0, 1.0))
        server = ItemRunner(reactor, server_table, server_config, env=self.env,
                                 on_item_exited=self.manager.item_exited)
        self.manager.add_server("vm1", InProcessRobot("vm1", server, server_ip), 2, server_ip)
        logic = {"sn_list": [node("rcmdriver", package="rcm", node_type="rcm_driver.py"),
                             node("r_talker", side="R", params="_topic:=r_chatter")]}
        space = yield self.manager.create("robot1", logic, self.robot)
        self.assertTrue(space.paired, describe(self.manager, "robot1"))
        described = describe(self.manager, "robot1")
        self.assertEqual((described["server"], described["public_ip"]), ("vm1", server_ip))
        self.assertEqual({n["sn_name"]: n["i_name"] for n in described["r_nodes"]},
                         {"rcmdriver": "vm1", "r_talker": "robot1"})
        self.assertTrue(space.ros_master_uri.startswith(f"http://{server_ip}:"), space.ros_master_uri)
        port = int(space.ros_master_uri.rstrip("/").rsplit(":", 1)[1])
        self.assertGreaterEqual(port, server_config.ros_port_base)
        self.assertIsNotNone(server.spaces["robot1"].driver_link, "rcm_driver on the server not told r_connection")
        self.assertEqual(self.master_table.processes(), [])        # nothing of the space runs on the master
        yield self.wait_for(lambda: _try(lambda: "/r_talker" in _node_names(self.graph(space.ros_master_uri))),
                            what="the robot's node at the server's ROS master")
        yield self.manager.teardown("robot1")
        self.assertEqual(server.spaces, {})
        self.assertEqual([p for p in server_table.processes() if p.state in LIVE_STATES], [])


def _try(condition):
    try:
        return condition()
    except Exception:
        return None


def _node_names(master):
    pubs, subs, srvs = master.getSystemState()
    return {n for _, members in pubs + subs + srvs for n in members}
