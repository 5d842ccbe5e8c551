"""The FIROS domain: which robots are connected, and what connecting, disconnecting and a broker notification do.

Owns the robot table and the rules of CONTRACTS §3 that tie the other modules together: connecting a robot creates
its entity (with `descriptions`), subscribes to its subscriber topics and keeps a broker subscription for its
publisher attributes; disconnecting undoes all of it; a notification whose `COMMAND` lists publisher topics of a
connected robot is published on them, FIROS's own updates excepted, and FIROS then writes `COMMAND` back to the empty
list (the command is taken), so that whatever the broker re-sends without a new update commands nothing. A command
goes only to a topic of the robot's ROS graph, with the graph's type, or to one whose type the whitelist declares;
never with a type the caller chose. Commands are counted (`commands`: published, or why not). A whitelist
edit takes effect on the robots already mapped: topics no longer allowed are dropped, newly allowed ones mapped, and
the limits it sets passed on to the sender. Robots explicitly disconnected are not brought back by graph discovery
until they are connected again. Errors a client can cause raise `ApiError`.
"""

import collections
import logging
import re
import threading
from dataclasses import dataclass, field

from include import discovery
from include.config import ConfigError
from include.discovery import TopicInfo
from include.log_guard import Budget, shown
from include.ngsi_client import COMMAND, DESCRIPTIONS, BrokerError, BrokerUnavailable, NotificationError
from include.ngsi_encoding import NgsiEncodingError, attribute_to_relative_topic, check_robot_name, \
    attribute_type_to_message_type, message_type_to_attribute_type, relative_topic_to_attribute, \
    split_firosstamp
from include.ros_conversion import ConversionError, dict_to_message, load_message_class
from include.topics import structure
from include.whitelist import WhitelistError, pattern_of

log = logging.getLogger("firos.bridge")

# why a commanded attribute was not published: no topic the whitelist lets the broker command (FIROS's own
# attributes, listed in COMMAND by its updates, included), a whitelisted topic absent from the ROS graph whose type
# nothing declares, FIROS's own update coming back, an entity that is no connected robot, a command refused (400)
COMMAND_SKIPS = ("not_whitelisted", "not_in_graph", "own_update", "unknown_robot", "refused")

_LITERAL_TOPIC = re.compile(r"[A-Za-z0-9_/]+")


def _message_type(attr_type):
    """"pkg/Type" for an attribute type naming a message type, else None."""
    try:
        return attribute_type_to_message_type(attr_type)
    except NgsiEncodingError:
        return None


def _robot_name(name):
    """ApiError 400 (nothing kept, the name shortened in the answer) for a name no robot can have."""
    try:
        return check_robot_name(name)
    except NgsiEncodingError as exc:
        raise ApiError(400, str(exc)) from None


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
    rcm_info: dict = field(default_factory=dict)  # rcm_driver's firos_info answer (RCM robots)


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
        self.commands = collections.Counter({outcome: 0 for outcome in ("published",) + COMMAND_SKIPS})
        self.notes = Budget(log, "lines about commands not published")

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
        if name is not None:
            _robot_name(name)
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
        """Connect an RCM robot whose topics (the whole service space) come from rcm_driver's firos_info;
        ApiError 400 for a name no robot can have."""
        _robot_name(name)
        info = info if isinstance(info, dict) else {}
        topics = discovery.robot_from_rcm(name, info, self.whitelist)
        with self._membership:
            with self._lock:
                self.disabled.discard(name)
            self._connect(name, "", "rcm", topics, force=True, rcm_info=info)

    def _connect(self, name, namespace, source, topics, force=False, rcm_info=None):
        """Create or extend a robot; True when something changed."""
        with self._lock:
            robot = self.robots.get(name)
            new = robot is None
            if new:
                robot = self.robots[name] = Robot(name, namespace, source)
            if rcm_info is not None:
                robot.rcm_info = rcm_info
        if new:
            static = {}
            if name in self.descriptions:
                static[DESCRIPTIONS] = ("DescriptionData", self.descriptions[name])
            self.sender.create(name, static)
            log.info("robot %s connected (%s)", name, source)
        changed = self._set_topics(robot, topics, replace=rcm_info is not None) or new
        if not (changed or force):
            return False
        self._update_subscription(robot)
        return True

    def _set_topics(self, robot, topics, replace):
        """Make ``topics`` the robot's mapped topics (``replace``) or add them (discovery: kinds only grow);
        drop what is no longer mapped, (re)subscribe what is new or changed type. True when anything changed."""
        with self._lock:
            old = dict(robot.topics)
            new = {} if replace else dict(old)
            for relative, info in topics.items():
                before = None if replace else old.get(relative)
                if before is not None and before.msg_type == info.msg_type:
                    info = TopicInfo(info.name, relative, info.msg_type, before.kinds | info.kinds, *info.limits)
                new[relative] = info
            robot.topics = new
        changed = False
        for relative, info in old.items():
            now = new.get(relative)
            same_type = now is not None and now.msg_type == info.msg_type
            if now is None or now.kinds != info.kinds or not same_type:
                changed = True
            if "subscriber" in info.kinds and not (same_type and "subscriber" in now.kinds):
                self.topics.unsubscribe(robot.name, info.name)
                self.sender.forget(robot.name, info.attribute)
                log.info("%s of %s no longer forwarded to the broker", info.name, robot.name)
            if "publisher" in info.kinds and not (same_type and "publisher" in now.kinds):
                self.topics.drop_publisher(info.name)
        changed = changed or any(relative not in old for relative in new)
        for info in list(new.values()):
            if "subscriber" in info.kinds:
                self.sender.set_limits(robot.name, info.attribute, *info.limits)
                try:
                    self.topics.subscribe(robot.name, info)
                except ConversionError as exc:
                    log.error("cannot forward %s: %s", info.name, exc)
        return changed

    def _update_subscription(self, robot):
        """The broker subscription watches the robot's command attributes: its publisher topics in the graph and
        those whose type the whitelist declares; any attribute while a publisher pattern matches no topic yet."""
        attrs, wildcard = set(), False
        for info in robot.topics.values():
            if "publisher" in info.kinds:
                attrs.add(info.attribute)
        for topic in self.whitelist.declared_types(robot.name):
            try:
                attrs.add(relative_topic_to_attribute(topic))
            except NgsiEncodingError:
                continue
        for rx, entry in self._whitelist_entries(robot.name):
            for pattern in map(pattern_of, entry.get("publisher", [])):
                if not _LITERAL_TOPIC.fullmatch(pattern) and not any(re.fullmatch(pattern, rel)
                                                                     for rel in robot.topics):
                    wildcard = True
        if attrs and self.read_client.watches_command:
            # a broker that notifies only real changes and cannot be forced (v1 Orion): a repeated command
            # changes COMMAND from [] back to [p1]; v2 repeats use forcedUpdate, NGSI-LD notifies every update
            attrs.add(COMMAND)
        if attrs or wildcard:
            self.subscriptions.set(robot.name, [] if wildcard else sorted(attrs))
        else:
            self.subscriptions.remove(robot.name)

    def _whitelist_entries(self, name):
        return [(rx, entry) for rx, entry in self.whitelist.snapshot().items() if re.fullmatch(rx, name)]

    def disconnect(self, name):
        """Remove the robot: its entity, its subscription, its topics; discovery leaves it alone afterwards.
        ApiError 400 for a name that cannot be a robot's, 404 if it is not connected; either way nothing about
        the name is kept."""
        _robot_name(name)
        with self._membership:
            if not self._drop(name):
                raise ApiError(404, f"robot {name!r} is not connected")
            with self._lock:
                self.disabled.add(name)
        log.info("robot %s disconnected", name)

    def _drop(self, name):
        """Forget a robot: its ROS endpoints, its subscription, its entity. False when it was not connected."""
        with self._lock:
            robot = self.robots.pop(name, None)
        if robot is None:
            return False
        self.topics.drop_robot(name)
        self.subscriptions.remove(name)
        self.sender.delete(name)
        return True

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
        """Publish the commanded attributes of a notification (v1, v2 or NGSI-LD, as configured); returns
        {robot: [attributes published]}. Every notification naming a publisher attribute in COMMAND is
        published, a repeated command included; FIROS then writes COMMAND back to [] (see the module doc).
        Each commanded attribute is counted in ``commands``: published, or why not (``COMMAND_SKIPS``)."""
        jobs, skipped = [], []
        try:
            try:
                entities = self.read_client.parse_notification(body)
            except NotificationError as exc:
                raise ApiError(400, str(exc)) from None
            for eid, _etype, attrs in entities:
                name = self.read_client.robot_of(eid)
                with self._lock:
                    robot = self.robots.get(name) if name is not None else None
                command = attrs.get(COMMAND, (None, []))[1]
                if robot is None:
                    skipped += ["unknown_robot"] * (len(command) if isinstance(command, list) else 0)
                    continue
                if command is None or command == "":
                    command = []
                if isinstance(command, str):
                    command = [command]
                if not isinstance(command, list) or not all(isinstance(c, str) for c in command):
                    raise ApiError(400, f"COMMAND of {eid!r} must be a list of attribute names")
                for attr in command:
                    if attr not in attrs or attr == COMMAND:
                        continue
                    job, why_not = self._command_job(robot, attr, attrs[attr])
                    if job is not None:
                        jobs.append(job)
                    else:
                        skipped.append(why_not)
        except ApiError:
            self._count(["refused"])
            raise
        published = {}
        for robot, attr, topic, msg_type, msg, known in jobs:   # all converted: now publish
            self.topics.publish(robot.name, topic, msg_type, msg, known)
            published.setdefault(robot.name, []).append(attr)
        for name in published:
            self.sender.command_taken(name)
        self._count(skipped + ["published"] * len(jobs))
        return published

    def _count(self, outcomes):
        with self._lock:
            self.commands.update(outcomes)

    def _command_job(self, robot, attr, typed_value):
        """(the job publishing a commanded attribute, None), or (None, why it is not published: a word of
        COMMAND_SKIPS); ApiError 400 for a command that cannot be published (another type, a bad value).

        A command is published on a topic of the robot's ROS graph with that topic's type, or on a topic absent from
        the graph whose type a whitelist entry declares, with that type; never with a type the caller chose
        (docs/DECISIONS.md, "FIROS commands only topics in the graph")."""
        attr_type, value = typed_value
        try:
            relative = attribute_to_relative_topic(attr)
        except NgsiEncodingError:
            return None, "not_whitelisted"                  # not a name FIROS maps: never a topic
        info = robot.topics.get(relative)
        if info is not None and "publisher" in info.kinds:
            topic, msg_type, known = info.name, info.msg_type, True
        else:
            if "publisher" not in self.whitelist.topic_kinds(robot.name, relative):
                return None, "not_whitelisted"
            topic, known = f"{robot.namespace}/{relative}", False
            msg_type = self.whitelist.declared_type(robot.name, relative)
            if msg_type is None:
                self.notes.info("a command of %s for %s not published: %s is not in the ROS graph (FIROS commands "
                                "the topics nodes use, with their type, and those whose type the whitelist "
                                "declares)", robot.name, shown(attr), shown(topic))
                return None, "not_in_graph"
        named = _message_type(attr_type) if attr_type is not None else None
        if named is not None and named != msg_type:
            raise ApiError(400, f"attribute {attr!r} of {robot.name!r} has type {attr_type!r} but topic "
                                f"{topic} carries {message_type_to_attribute_type(msg_type)}")
        if self.sender.is_own(robot.name, attr, value):
            return None, "own_update"
        try:
            data, _ = split_firosstamp(value)
        except NgsiEncodingError:
            raise ApiError(400, f"value of {robot.name}.{attr} must be a JSON object with the message fields") \
                from None
        try:
            msg = dict_to_message(data, load_message_class(msg_type))
        except ConversionError as exc:
            raise ApiError(400, f"{robot.name}.{attr}: {exc}") from None
        return (robot, attr, topic, msg_type, msg, known), None

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
                    entries.append({"name": info.relative, "type": message_type_to_attribute_type(info.msg_type),
                                    "structure": shape, "pubsub": kind})
            result.append({"name": name, "topics": entries})
        return result

    def read_robot(self, name):
        _robot_name(name)
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
        """The edit takes effect at once on the robots already mapped: topics the whitelist no longer allows are
        dropped (no more updates, their ROS endpoints removed), a robot it no longer allows at all is
        disconnected (discovery brings it back when allowed again), newly allowed robots and topics are mapped,
        and the broker subscriptions follow."""
        with self._membership:
            with self._lock:
                robots = list(self.robots.values())
            for robot in robots:
                if robot.source == "rcm":
                    self._set_topics(robot, discovery.robot_from_rcm(robot.name, robot.rcm_info, self.whitelist),
                                     replace=True)
                elif not self.whitelist.robot_allowed(robot.name):
                    self._drop(robot.name)
                    log.info("robot %s disconnected: the whitelist no longer names it", robot.name)
                else:
                    allowed = {}
                    for relative, info in robot.topics.items():
                        kinds = info.kinds & discovery.mapped_kinds(self.whitelist, robot.name, relative,
                                                                    info.msg_type)
                        if kinds:
                            allowed[relative] = discovery.topic_info(self.whitelist, robot.name, info.name,
                                                                     relative, info.msg_type, kinds)
                    self._set_topics(robot, allowed, replace=True)
            try:
                self._scan(None)
            except OSError as exc:
                log.warning("cannot read the ROS graph after a whitelist change: %s", exc)
            with self._lock:
                robots = list(self.robots.values())
            for robot in robots:
                self._update_subscription(robot)
