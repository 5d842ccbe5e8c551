"""ROS topic handling for FIROS: the rospy Subscribers that feed the sender and the Publishers that carry broker
commands into ROS, per robot, plus the message "structure" shown by `GET /robots`.

Owns every rospy Subscriber/Publisher FIROS makes for robots. Subscribers take messages as rospy delivers them
undeserialized (`rospy.AnyMsg`): the callback only hands the bytes to the sender (no deserialization, no conversion,
no I/O), so a message the sender skips (a newer one came, a rate limit, too big for the broker) costs nothing, and
its size is known before anything is converted. A Publisher created for a topic that nobody uses yet is latched, so
that a subscriber arriving a moment later (`rostopic echo`) still gets the command; for a topic with known
subscribers, the first publish waits (briefly) until they are connected, since rospy drops messages published before
that.
"""

import logging
import threading
import time

import rosgraph
import rospy

from include.ngsi_encoding import message_type_to_attribute_type
from include.ros_conversion import SerializedMessage, load_message_class

log = logging.getLogger("firos.topics")

PRIMITIVES = {"bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32",
              "float64", "string", "time", "duration", "byte", "char"}


def structure(msg_type, depth=0):
    """{field: type or nested structure} of a message type ("pkg/Type"); arrays shown as "type[]"."""
    cls = load_message_class(msg_type)
    result = {}
    for name, slot_type in zip(cls.__slots__, cls._slot_types):
        base = slot_type.split("[", 1)[0]
        suffix = slot_type[len(base):]
        if base in PRIMITIVES or depth > 8:
            result[name] = slot_type
            continue
        nested = "std_msgs/Header" if base == "Header" else base
        inner = structure(nested, depth + 1)
        result[name] = [inner] if suffix else inner
    return result


def wait_for_subscribers(publisher, topic, timeout=1.0, master_uri=None, own_node=None):
    """Wait until ``publisher`` is connected to every subscriber the master lists for ``topic`` (or timeout)."""
    own_node = own_node or rospy.get_name()
    try:
        _, subs, _ = rosgraph.Master(own_node, master_uri=master_uri).getSystemState()
        expected = len([n for t, nodes in subs if t == topic for n in nodes if n != own_node])
    except Exception:  # the master is gone: nothing to wait for
        return
    deadline = time.monotonic() + timeout
    while publisher.get_num_connections() < expected and time.monotonic() < deadline:
        time.sleep(0.01)  # polling rospy's connection count; rospy offers no event for it


class TopicHandler:
    """The rospy endpoints FIROS keeps for each robot."""

    def __init__(self, sender):
        self.sender = sender
        self._lock = threading.Lock()
        self._subscribers = {}   # robot -> {topic: (rospy.Subscriber, msg_type)}
        self._publishers = {}    # topic -> (robot, rospy.Publisher, msg_type, fresh)

    def subscribe(self, robot, info):
        """Forward messages of ``info`` (a TopicInfo) to the broker as attribute ``info.attribute``."""
        with self._lock:
            current = self._subscribers.get(robot, {}).get(info.name)
            if current is not None and current[1] == info.msg_type:
                return False
        if current is not None:
            self.unsubscribe(robot, info.name)       # the topic changed type: subscribe with the new one
        cls = load_message_class(info.msg_type)
        attr, atype = info.attribute, message_type_to_attribute_type(info.msg_type)
        offer = self.sender.offer

        def callback(raw):
            if raw._connection_header.get("md5sum") not in (cls._md5sum, "*"):
                return                               # another type now: discovery subscribes again
            offer(robot, attr, atype, SerializedMessage(cls, raw._buff))

        sub = rospy.Subscriber(info.name, rospy.AnyMsg, callback, queue_size=10)
        with self._lock:
            self._subscribers.setdefault(robot, {})[info.name] = (sub, info.msg_type)
        log.info("forwarding %s (%s) to the broker as %s.%s", info.name, info.msg_type, robot, attr)
        return True

    def publisher(self, robot, topic, msg_type, known_subscribers):
        """The Publisher FIROS uses for ``topic`` (created on first use)."""
        with self._lock:
            entry = self._publishers.get(topic)
            if entry is not None and entry[2] == msg_type:
                return entry[1]
        cls = load_message_class(msg_type)
        pub = rospy.Publisher(topic, cls, queue_size=10, latch=not known_subscribers)
        with self._lock:
            old = self._publishers.get(topic)
            self._publishers[topic] = (robot, pub, msg_type, True)
        if old is not None:
            old[1].unregister()
        log.info("publishing broker commands of %s on %s (%s)", robot, topic, msg_type)
        return pub

    def publish(self, robot, topic, msg_type, msg, known_subscribers):
        pub = self.publisher(robot, topic, msg_type, known_subscribers)
        with self._lock:
            entry = self._publishers.get(topic)
            fresh = entry is not None and entry[3]
            if fresh:
                self._publishers[topic] = entry[:3] + (False,)
        if fresh and known_subscribers:
            wait_for_subscribers(pub, topic)
        pub.publish(msg)

    def unsubscribe(self, robot, topic):
        """Stop forwarding ``topic`` of ``robot`` (no-op when FIROS does not subscribe to it)."""
        with self._lock:
            entry = self._subscribers.get(robot, {}).pop(topic, None)
        if entry is not None:
            entry[0].unregister()
            log.info("no longer forwarding %s of %s", topic, robot)

    def drop_publisher(self, topic):
        """Remove FIROS's Publisher of ``topic`` (a later command creates it again, with the type it has then)."""
        with self._lock:
            entry = self._publishers.pop(topic, None)
        if entry is not None:
            entry[1].unregister()

    def drop_robot(self, robot):
        with self._lock:
            subs = self._subscribers.pop(robot, {})
            pubs = [t for t, entry in self._publishers.items() if entry[0] == robot]
            pub_objs = [self._publishers.pop(t)[1] for t in pubs]
        for sub, _ in subs.values():
            sub.unregister()
        for pub in pub_objs:
            pub.unregister()
