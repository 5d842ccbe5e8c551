"""A small ROS node for tests, run as a child process: it echoes a topic, publishes a message, or calls a service.

Tests start it with ``/usr/bin/python3 -m tests.support.ros_probe MODE ...`` so that rospy lives in a child (a
pytest process can hold only one rospy node, bound to one ROS master). It writes one JSON object per line on
stdout, flushed, so a test reads its output through ``ProcessGroup.output``:

- ``echo TOPIC PKG/Type``: prints ``{"ready": true}`` once subscribed (registered with the master), then each
  message as a JSON object of its fields.
- ``pub TOPIC PKG/Type JSON``: publishes one message (fields from JSON) on a latched topic, prints
  ``{"published": true}`` and keeps the topic advertised until stopped.
- ``call SERVICE PKG/Srv JSON``: waits for the service, calls it with the request fields from JSON, prints the
  response fields and exits 0 (or prints ``{"error": ...}`` and exits 1).

ROS arguments (``__name:=firos``) are passed through to rospy; the default node name is ``probe_<pid>``.
SIGINT and SIGTERM end it at once, without rospy's orderly (and slow) shutdown.
Only flat messages (fields of primitive types) are supported: that is all the tests need.
"""

import json
import os
import signal
import sys

import roslib.message
import rospy


def _fields(msg):
    return {slot: getattr(msg, slot) for slot in msg.__slots__}


def _echo(topic, type_name):
    msg_class = roslib.message.get_message_class(type_name)
    rospy.Subscriber(topic, msg_class, lambda msg: _emit(_fields(msg)), queue_size=100)
    _emit({"ready": True})
    rospy.spin()
    return 0


def _pub(topic, type_name, fields_json):
    msg_class = roslib.message.get_message_class(type_name)
    publisher = rospy.Publisher(topic, msg_class, queue_size=10, latch=True)
    publisher.publish(msg_class(**json.loads(fields_json)))
    _emit({"published": True})
    rospy.spin()
    return 0


def _call(service, type_name, fields_json):
    srv_class = roslib.message.get_service_class(type_name)
    try:
        rospy.wait_for_service(service, timeout=15.0)
        response = rospy.ServiceProxy(service, srv_class)(**json.loads(fields_json))
    except (rospy.ROSException, rospy.ServiceException) as exc:
        _emit({"error": str(exc)})
        return 1
    _emit(_fields(response))
    return 0


def _emit(obj):
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


MODES = {"echo": (_echo, 2), "pub": (_pub, 3), "call": (_call, 3)}


def main(argv):
    args = rospy.myargv(argv)[1:]
    if not args or args[0] not in MODES or len(args) - 1 != MODES[args[0]][1]:
        print("usage: ros_probe echo TOPIC TYPE | pub TOPIC TYPE JSON | call SERVICE TYPE JSON", file=sys.stderr)
        return 2
    rospy.init_node(f"probe_{os.getpid()}", argv=argv, disable_signals=True)
    # a probe is stopped by its test: leave at once (rospy's orderly shutdown takes about a second per node)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: os._exit(0))
    function, _ = MODES[args[0]]
    return function(*args[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv))
