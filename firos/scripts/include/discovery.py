"""Robots from the ROS graph: which robots exist and which of their topics the whitelist maps.

A robot is the first namespace of a topic (`/turtle1/pose` → robot `turtle1`, topic `pose`); message types come
from the master (`getTopicTypes`). FIROS's own endpoints do not count, so a topic only FIROS subscribes to is not a
sign that the robot listens. Owns the graph reading (rosgraph, no rospy) and which kinds of a topic are mapped
(`mapped_kinds`: what the whitelist lists, except that images and point clouds, `LARGE_MESSAGE_TYPES`, are mapped
only where an entry names them plainly) with the limits the whitelist sets for it; the naming rules (topic →
attribute, message type → attribute type) are `ngsi_encoding`'s. A topic whose name or type breaks them is left
out.
"""

import logging
from dataclasses import dataclass, field
from typing import Optional

import rosgraph

from include.ngsi_encoding import NgsiEncodingError, attribute_type_to_message_type, relative_topic_to_attribute

log = logging.getLogger("firos.discovery")

IGNORED_TOPICS = ("/rosout", "/rosout_agg")
IGNORED_NAMESPACES = ("firos", "rcm")
ROS_TO_BROKER_KIND = {"publisher": "subscriber", "subscriber": "publisher"}
# Types whose messages are big (camera frames, point clouds): mapped only when a whitelist entry names the topic
# plainly, never through a pattern such as ".*".
LARGE_MESSAGE_TYPES = ("sensor_msgs/Image", "sensor_msgs/CompressedImage", "sensor_msgs/PointCloud2",
                       "sensor_msgs/PointCloud")


@dataclass
class TopicInfo:
    """One mapped topic of a robot. ``kinds`` ⊆ {"publisher", "subscriber"} (the broker's point of view)."""
    name: str                  # full ROS name, "/turtle1/cmd_vel"
    relative: str              # relative to the robot namespace, "cmd_vel"
    msg_type: str              # "geometry_msgs/Twist"
    kinds: set = field(default_factory=set)
    max_rate: Optional[float] = None    # messages per second sent to the broker at most (whitelist limit)
    max_size: Optional[int] = None      # bytes one value may take in a request (whitelist limit)

    @property
    def attribute(self):
        return relative_topic_to_attribute(self.relative)

    @property
    def limits(self):
        return self.max_rate, self.max_size


def mapped_kinds(whitelist, robot, relative, msg_type, listed=None):
    """The kinds of a robot's topic the whitelist maps (``listed``: those it lists, when already known); a topic
    of a large type only under the kinds whose entries name it plainly."""
    kinds = whitelist.topic_kinds(robot, relative) if listed is None else set(listed)
    if kinds and msg_type in LARGE_MESSAGE_TYPES:
        kinds &= whitelist.names_plainly(robot, relative)
    return kinds


def topic_info(whitelist, robot, name, relative, msg_type, kinds):
    """A TopicInfo with the limits the whitelist sets for it."""
    return TopicInfo(name, relative, msg_type, set(kinds), *whitelist.topic_limits(robot, relative))


def _valid(relative, msg_type):
    """True when the topic name and message type follow the naming rules (FIROS cannot map them otherwise)."""
    try:
        relative_topic_to_attribute(relative)
        attribute_type_to_message_type(msg_type)
        return True
    except NgsiEncodingError as exc:
        log.debug("topic %s left out: %s", relative, exc)
        return False


def split_topic(topic):
    """("turtle1", "pose") for "/turtle1/pose"; None for topics without a robot namespace."""
    parts = topic.strip("/").split("/", 1)
    if len(parts) < 2 or not parts[0] or not parts[1]:
        return None
    return parts[0], parts[1]


class GraphReader:
    """Reads the ROS master's view of topics, leaving out ``own_node``'s endpoints."""

    def __init__(self, own_node="/firos", master_uri=None):
        self.own_node = own_node
        self.master = rosgraph.Master(own_node + "_discovery", master_uri=master_uri)

    def topics(self):
        """{topic: (msg_type, has_publishers, has_subscribers)} for topics with some endpoint besides FIROS."""
        pubs, subs, _ = self.master.getSystemState()
        types = dict(self.master.getTopicTypes())
        publishers = {t: [n for n in nodes if n != self.own_node] for t, nodes in pubs}
        subscribers = {t: [n for n in nodes if n != self.own_node] for t, nodes in subs}
        result = {}
        for topic in set(publishers) | set(subscribers):
            if topic in IGNORED_TOPICS or topic not in types:
                continue
            has_pub, has_sub = bool(publishers.get(topic)), bool(subscribers.get(topic))
            if has_pub or has_sub:
                result[topic] = (types[topic], has_pub, has_sub)
        return result


def robots_from_graph(graph_topics, whitelist, only=None):
    """{robot: {relative topic: TopicInfo}} of whitelisted robots and topics found in ``graph_topics``.

    A topic someone publishes is a "subscriber" topic when the whitelist lists it so (FIROS forwards it to the
    broker); a topic listed as "publisher" becomes one whoever else uses it (FIROS publishes broker commands).
    """
    robots = {}
    for topic, (msg_type, has_pub, _has_sub) in graph_topics.items():
        split = split_topic(topic)
        if split is None:
            continue
        robot, relative = split
        if robot in IGNORED_NAMESPACES or (only is not None and robot != only):
            continue
        if not whitelist.robot_allowed(robot):
            continue
        kinds = mapped_kinds(whitelist, robot, relative, msg_type)
        if not has_pub:
            kinds.discard("subscriber")
        if kinds and _valid(relative, msg_type):
            robots.setdefault(robot, {})[relative] = topic_info(whitelist, robot, topic, relative, msg_type, kinds)
    return robots


def robot_from_rcm(robot, info, whitelist):
    """{relative topic: TopicInfo} from rcm_driver's firos_info answer for ``robot`` (the whole service space).

    ``info`` is {"topics": [{"name", "msg", "type": "publisher"|"subscriber"}]}; a topic may be listed twice.
    rcm_driver's "type" is the ROS point of view (rcm/README.md): a topic some node publishes is one FIROS
    forwards to the broker ("subscriber" from the broker's point of view), and the other way round.
    Topic names are made relative to the robot's namespace when they are under it. When some whitelist entry
    matches the robot, it filters the topics as usual; otherwise every topic rcm_driver reported is mapped, but
    images and point clouds never (they need an entry naming them).
    """
    topics = {}
    filtered = whitelist.robot_allowed(robot)
    for entry in info.get("topics", []) if isinstance(info, dict) else []:
        if not isinstance(entry, dict):
            continue
        name, msg, kind = entry.get("name"), entry.get("msg"), entry.get("type")
        if not isinstance(name, str) or not isinstance(msg, str) or kind not in ("publisher", "subscriber"):
            continue
        full = "/" + name.strip("/")
        if full in IGNORED_TOPICS or full.split("/")[1] in IGNORED_NAMESPACES:
            continue
        relative = full.strip("/")
        if relative.startswith(robot + "/"):
            relative = relative[len(robot) + 1:]
        kind = ROS_TO_BROKER_KIND[kind]
        if not _valid(relative, msg):
            continue
        msg_type = attribute_type_to_message_type(msg)
        listed = whitelist.topic_kinds(robot, relative) if filtered else {kind}
        if kind not in mapped_kinds(whitelist, robot, relative, msg_type, listed):
            continue
        info_entry = topics.setdefault(relative, topic_info(whitelist, robot, full, relative, msg_type, ()))
        info_entry.kinds.add(kind)
    return topics
