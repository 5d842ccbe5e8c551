"""A ROS peer for FIROS tests, run as a child: publishes messages given as JSON at a rate and prints every
message it receives on the topics it subscribes to as one line `RECV <topic> <json>` (flushed).

    /usr/bin/python3 -m tests.support.firos_talker --rate 5 \
        --pub /bot/twist geometry_msgs/Twist '{"linear": {"x": 1.5}}' --sub /bot/cmd geometry_msgs/Twist

``--pub-file TOPIC TYPE PATH`` takes the message's JSON from a file (messages too big for a command line);
``--stamp TOPIC FIELD`` writes a new value (the count of messages published so far) into a float field of that
topic's message before each publish, so that every message is distinct.
"""

import argparse
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "firos", "scripts"))

import rospy  # noqa: E402

from include.ros_conversion import dict_to_message, load_message_class, message_to_dict  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--rate", type=float, default=5.0)
    parser.add_argument("--pub", nargs=3, action="append", default=[], metavar=("TOPIC", "TYPE", "JSON"))
    parser.add_argument("--pub-file", nargs=3, action="append", default=[], metavar=("TOPIC", "TYPE", "PATH"))
    parser.add_argument("--stamp", nargs=2, action="append", default=[], metavar=("TOPIC", "FIELD"))
    parser.add_argument("--sub", nargs=2, action="append", default=[], metavar=("TOPIC", "TYPE"))
    args = parser.parse_args(rospy.myargv(sys.argv if argv is None else argv)[1:])
    rospy.init_node("firos_talker", anonymous=True)
    pubs = []
    for topic, type_name, path in args.pub_file:
        with open(path) as f:
            args.pub.append([topic, type_name, f.read()])
    stamped = dict(args.stamp)
    for topic, type_name, value in args.pub:
        cls = load_message_class(type_name)
        pubs.append((topic, rospy.Publisher(topic, cls, queue_size=10), dict_to_message(json.loads(value), cls)))
    for topic, type_name in args.sub:
        def show(msg, topic=topic):
            print("RECV", topic, json.dumps(message_to_dict(msg), sort_keys=True), flush=True)
        rospy.Subscriber(topic, load_message_class(type_name), show)
    print("READY", flush=True)
    rate = rospy.Rate(args.rate)
    count = 0
    while not rospy.is_shutdown():
        count += 1
        for topic, pub, msg in pubs:
            if topic in stamped:
                setattr(msg, stamped[topic], float(count))
            pub.publish(msg)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == "__main__":
    main()
