"""The FIROS domain: which robots are connected, and what connecting, disconnecting and a broker notification do.

Owns the robot table and the rules of CONTRACTS §3 that tie the other modules together: connecting a robot
creates its entity (with `descriptions`), subscribes to its subscriber topics and keeps a broker subscription for
its publisher attributes; disconnecting undoes all of it; a notification whose `COMMAND` lists publisher topics
of a connected robot is published on them, FIROS's own updates excepted. Robots explicitly disconnected are not
brought back by graph discovery until they are connected again. Errors a client can cause raise `ApiError`.
"""

import logging
import re
import threading
from dataclasses import dataclass, field

from include import discovery
from include.config import ConfigError
from include.discovery import attribute_name, python_type, ros_type, topic_from_attribute
from include.ngsi_client import COMMAND, DESCRIPTIONS, BrokerError, BrokerUnavailable, NotificationError, \
    parse_notification
from include.ros_conversion import ConversionError, dict_to_message, load_message_class
from include.topics import structure
from include.whitelist import WhitelistError

log = logging.getLogger("firos.bridge")

_LITERAL_TOPIC = re.compile(r"[A-Za-z0-9_/]+")


class ApiError(Exception):
    """A request FIROS cannot honour; ``status`` is the HTTP status to answer with."""

    def __init__(self, status, reason):
        super().__init__(reason)
        self.status = status
        self.reason = reason


@dataclass
class Robot:
    name: str
    namespace: str                   # "/turtle1" for graph robots, "" for an RCM service space
    source: str                      # "graph" | "rcm"
    topics: dict = field(default_factory=dict)   # relative topic -> TopicInfo
    last_command: dict = field(default_factory=dict)  # attr -> value last published from the broker


class Firos:
    def __init__(self, settings, whitelist, descriptions, sender, subscriptions, topics, graph, read_client,
                 events=None):
        self.settings = settings
        self.whitelist = whitelist
        self.descriptions = descriptions
        self.sender = sender
        self.subscriptions = subscriptions
        self.topics = topics
        self.graph = graph
        self.read_client = read_client
        self.events = events               # object with created(robot) / removed(robot), or None
        self._lock = threading.RLock()
        # one membership change (and one look at the ROS graph: rosgraph's XML-RPC proxy is not thread-safe)
        # at a time, whichever thread asks: discovery loop, HTTP API, ROS control
        self._membership = threading.RLock()
        self.robots = {}
        self.disabled = set()              # disconnected on request: discovery leaves them alone
        self._announced = set()

    # --- connecting -------------------------------------------------------------------------------------------
    def scan(self, only=None):
        """Look at the ROS graph and connect new whitelisted robots and topics; returns the robots touched."""
        with self._membership:
            return self._scan(only)

    def _scan(self, only):
        found = discovery.robots_from_graph(self.graph.topics(), self.whitelist, only=only)
        touched = []
        for name, topics in sorted(found.items()):
            with self._lock:
                if name in self.disabled:
                    continue
                robot = self.robots.get(name)
                if robot is not None and robot.source != "graph":
                    continue
            if self._connect(name, "/" + name, "graph", topics):
                touched.append(name)
        return touched

    def connect(self, name=None):
        """Connect ``name`` (or every whitelisted robot of the graph) from the ROS graph; returns names."""
        with self._membership:
            with self._lock:
                if name is None:
                    self.disabled.clear()
                else:
                    self.disabled.discard(name)
            try:
                self._scan(only=name)
            except OSError as exc:
                raise ApiError(503, f"cannot read the ROS graph: {exc}") from None
        with self._lock:
            if name is None:
                return sorted(self.robots)
            return [name] if name in self.robots else []

    def connect_rcm(self, name, info):
        """Connect an RCM robot whose topics (the whole service space) come from rcm_driver's firos_info."""
        topics = discovery.robot_from_rcm(name, info, self.whitelist)
        with self._membership:
            with self._lock:
                self.disabled.discard(name)
            self._connect(name, "", "rcm", topics, force=True)

    def _connect(self, name, namespace, source, topics, force=False):
        """Create or extend a robot; True when something changed."""
        with self._lock:
            robot = self.robots.get(name)
            new = robot is None
            if new:
                robot = self.robots[name] = Robot(name, namespace, source)
            changed = new
            for relative, info in topics.items():
                old = robot.topics.get(relative)
                if old is None or old.kinds != info.kinds or old.msg_type != info.msg_type:
                    robot.topics[relative] = info
                    changed = True
        if new:
            static = {}
            if name in self.descriptions:
                static[DESCRIPTIONS] = ("DescriptionData", self.descriptions[name])
            self.sender.create(name, static)
            log.info("robot %s connected (%s)", name, source)
        if not (changed or force):
            return False
        for info in list(robot.topics.values()):
            if "subscriber" in info.kinds:
                try:
                    self.topics.subscribe(name, info)
                except ConversionError as exc:
                    log.error("cannot forward %s: %s", info.name, exc)
        self._update_subscription(robot)
        return True

    def _update_subscription(self, robot):
        attrs, wildcard = set(), False
        for info in robot.topics.values():
            if "publisher" in info.kinds:
                attrs.add(info.attribute)
        for rx, entry in self._whitelist_entries(robot.name):
            for pattern in entry.get("publisher", []):
                if _LITERAL_TOPIC.fullmatch(pattern):
                    attrs.add(attribute_name(pattern))
                elif not any(re.fullmatch(pattern, rel) for rel in robot.topics):
                    wildcard = True
        if attrs or wildcard:
            self.subscriptions.set(robot.name, [] if wildcard else sorted(attrs))
        else:
            self.subscriptions.remove(robot.name)

    def _whitelist_entries(self, name):
        return [(rx, entry) for rx, entry in self.whitelist.snapshot().items() if re.fullmatch(rx, name)]

    def disconnect(self, name):
        """Remove the robot: its entity, its subscription, its topics. ApiError 404 if it is not connected."""
        with self._membership:
            with self._lock:
                robot = self.robots.pop(name, None)
                self.disabled.add(name)
            if robot is None:
                raise ApiError(404, f"robot {name!r} is not connected")
            self.topics.drop_robot(name)
            self.subscriptions.remove(name)
            self.sender.delete(name)
        log.info("robot %s disconnected", name)

    def disconnect_all(self):
        with self._lock:
            names = list(self.robots)
        for name in names:
            try:
                self.disconnect(name)
            except ApiError:
                pass

    # --- entity events (from the sender thread) --------------------------------------------------------------
    def entity_created(self, name):
        with self._lock:
            if name in self._announced or name not in self.robots:
                return
            self._announced.add(name)
        if self.events:
            self.events.created(name)

    def entity_removed(self, name):
        with self._lock:
            if name not in self._announced:
                return
            self._announced.discard(name)
        if self.events:
            self.events.removed(name)

    def entity_lost(self, name):
        """The broker forgot a robot's subscription: its entity may be gone too."""
        self.sender.recreate(name)

    # --- broker → ROS -----------------------------------------------------------------------------------------
    def handle_notification(self, body):
        """Publish the commanded attributes of a v1/v2 notification; returns {robot: [attributes published]}."""
        try:
            entities = parse_notification(body)
        except NotificationError as exc:
            raise ApiError(400, str(exc)) from None
        jobs = []
        for eid, _etype, attrs in entities:
            with self._lock:
                robot = self.robots.get(eid)
            if robot is None:
                continue
            command = attrs.get(COMMAND, (None, []))[1]
            if command is None or command == "":
                command = []
            if isinstance(command, str):
                command = [command]
            if not isinstance(command, list) or not all(isinstance(c, str) for c in command):
                raise ApiError(400, f"COMMAND of {eid!r} must be a list of attribute names")
            for attr in command:
                if attr not in attrs or attr == COMMAND:
                    continue
                job = self._command_job(robot, attr, attrs[attr])
                if job is not None:
                    jobs.append(job)
        published = {}
        for robot, attr, topic, msg_type, msg, known, value in jobs:   # all converted: now publish
            self.topics.publish(robot.name, topic, msg_type, msg, known)
            with self._lock:
                robot.last_command[attr] = value
            published.setdefault(robot.name, []).append(attr)
        return published

    def _command_job(self, robot, attr, typed_value):
        attr_type, value = typed_value
        relative = topic_from_attribute(attr)
        info = robot.topics.get(relative)
        if info is not None and "publisher" in info.kinds:
            topic, msg_type, known = info.name, info.msg_type, True
            named = ros_type(attr_type)
            if named is not None and named != msg_type:
                raise ApiError(400, f"attribute {attr!r} of {robot.name!r} has type {attr_type!r} but topic "
                                    f"{topic} carries {python_type(msg_type)}")
        elif "publisher" in self.whitelist.topic_kinds(robot.name, relative) or (
                info is not None and robot.source == "rcm" and "publisher" in info.kinds):
            msg_type = ros_type(attr_type)
            if msg_type is None:
                raise ApiError(400, f"attribute {attr!r} of {robot.name!r} has type {attr_type!r}, "
                                    f"not a message type like std_msgs.msg.String")
            topic, known = f"{robot.namespace}/{relative}", False
        else:
            return None
        if self.sender.is_own(robot.name, attr, value):
            return None
        with self._lock:
            if robot.last_command.get(attr) == value:
                return None
        if isinstance(value, dict):
            data = {k: v for k, v in value.items() if k != "firosstamp"}
        else:
            raise ApiError(400, f"value of {robot.name}.{attr} must be a JSON object with the message fields")
        try:
            msg = dict_to_message(data, load_message_class(msg_type))
        except ConversionError as exc:
            raise ApiError(400, f"{robot.name}.{attr}: {exc}") from None
        return robot, attr, topic, msg_type, msg, known, value

    # --- reading ----------------------------------------------------------------------------------------------
    def list_robots(self):
        with self._lock:
            robots = [(r.name, list(r.topics.values())) for r in self.robots.values()]
        result = []
        for name, topics in sorted(robots):
            entries = []
            for info in sorted(topics, key=lambda i: i.relative):
                try:
                    shape = structure(info.msg_type)
                except ConversionError:
                    shape = {}
                for kind in sorted(info.kinds):
                    entries.append({"name": info.relative, "type": python_type(info.msg_type),
                                    "structure": shape, "pubsub": kind})
            result.append({"name": name, "topics": entries})
        return result

    def read_robot(self, name):
        with self._lock:
            known = name in self.robots
        try:
            with self.read_client.lock:
                entity = self.read_client.get_entity(name)
        except BrokerUnavailable as exc:
            raise ApiError(503, f"the context broker is unavailable: {exc}") from None
        except BrokerError as exc:
            raise ApiError(502, f"the context broker refused the query: {exc}") from None
        if entity is None:
            raise ApiError(404, f"robot {name!r} has no entity in the context broker"
                                + ("" if known else " and is not connected"))
        return {"id": name, "type": self.settings.context_type, "connected": known, "attributes": entity}

    # --- whitelist --------------------------------------------------------------------------------------------
    def whitelist_write(self, data):
        try:
            self.whitelist.write(data)
        except WhitelistError as exc:
            raise ApiError(400, str(exc)) from None
        self._after_whitelist_change()

    def whitelist_remove(self, data):
        try:
            self.whitelist.remove(data)
        except WhitelistError as exc:
            raise ApiError(400, str(exc)) from None
        self._after_whitelist_change()

    def whitelist_restore(self):
        try:
            self.whitelist.restore()
        except ConfigError as exc:
            raise ApiError(400, f"whitelist not restored: {exc}") from None
        self._after_whitelist_change()

    def _after_whitelist_change(self):
        """Newly allowed robots and topics are picked up at once; robots already connected keep their topics."""
        with self._membership:
            try:
                self._scan(None)
            except OSError as exc:
                log.warning("cannot read the ROS graph after a whitelist change: %s", exc)
            with self._lock:
                robots = list(self.robots.values())
            for robot in robots:
                self._update_subscription(robot)

