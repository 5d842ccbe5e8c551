#!/usr/bin/env python3
"""Test node: publishes std_msgs/String on the topic given by ~topic (default "chatter") at ~rate Hz."""

import rospy
from std_msgs.msg import String


def main():
    rospy.init_node("talker")
    topic = rospy.get_param("~topic", "chatter")
    rate = rospy.Rate(float(rospy.get_param("~rate", 2.0)))
    pub = rospy.Publisher(topic, String, queue_size=10)
    while not rospy.is_shutdown():
        pub.publish(String(data=f"hello from {rospy.get_name()}"))
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == "__main__":
    main()
