"""FIROS's ROS control interface: `firos/connect` and `firos/disconnect` (std_msgs/String, a robot name; an empty
name on connect means every whitelisted robot), RCM's `/rcm/robot_event` (robotics_msgs/Robot_Event, with the
robot's topics asked of `/rcm/firos_info`) and the `/firos/cb_event` (robotics_msgs/CB_Event) announcements.

Owns those endpoints and two worker threads: callbacks only queue the request, one worker does the (blocking)
service call and the connecting, so no ROS callback waits on the broker or on rcm_driver; the other publishes the
CB_Events (waiting for rcm_driver's connection first), so the sender thread that reports an entity never waits.
"""

import json
import logging
import queue
import threading

import rospy
from robotics_msgs.msg import CB_Event, Robot_Event
from robotics_msgs.srv import FIROS_Info
from std_msgs.msg import String

from include.bridge import ApiError
from include.log_guard import Budget, shown
from include.ngsi_encoding import NgsiEncodingError, check_robot_name
from include.topics import wait_for_subscribers

log = logging.getLogger("firos.rcm")

CB_EVENT_TOPIC = "/firos/cb_event"
FIROS_INFO_SERVICE = "/rcm/firos_info"


class RosControl:
    def __init__(self, firos, service_timeout=5.0):
        self.firos = firos
        self.service_timeout = service_timeout
        self._queue = queue.Queue()
        self._events = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="firos-control", daemon=True)
        self._event_thread = threading.Thread(target=self._run_events, name="firos-cb-events", daemon=True)
        self.cb_pub = None
        self._subs = []
        self.notes = Budget(log, "lines about ROS requests refused")   # any ROS peer may publish on these topics

    def start(self):
        self.cb_pub = rospy.Publisher(CB_EVENT_TOPIC, CB_Event, queue_size=20)
        self._subs = [
            rospy.Subscriber("firos/connect", String, lambda m: self._queue.put(("connect", m.data.strip()))),
            rospy.Subscriber("firos/disconnect", String, lambda m: self._queue.put(("disconnect", m.data.strip()))),
            rospy.Subscriber("/rcm/robot_event", Robot_Event, self._robot_event),
        ]
        self._thread.start()
        self._event_thread.start()

    def stop(self):
        """Stop taking requests; CB_Events still queued (and those of the shutdown) are published by
        ``finish_events``."""
        self._queue.put(None)
        self._thread.join(5.0)
        for sub in self._subs:
            sub.unregister()

    def _robot_event(self, event):
        if event.instance_status == Robot_Event.CONNECTED:
            self._queue.put(("rcm_connect", event.instance_name))
        elif event.instance_status == Robot_Event.DISCONNECTED:
            self._queue.put(("disconnect", event.instance_name))
        else:
            self.notes.warning("ignoring Robot_Event for %s with unknown status %d", shown(event.instance_name),
                               event.instance_status)

    # entity events, called by the bridge
    def created(self, name):
        self._publish_cb(name, CB_Event.CREATED)

    def removed(self, name):
        self._publish_cb(name, CB_Event.REMOVED)

    def _publish_cb(self, name, status):
        if self.cb_pub is not None:
            self._events.put((name, status))

    def finish_events(self, timeout=3.0):
        """Publish what is queued, then stop the CB_Event thread."""
        self._events.put(None)
        self._event_thread.join(timeout)

    def _run_events(self):
        while True:
            event = self._events.get()
            if event is None:
                return
            name, status = event
            try:
                wait_for_subscribers(self.cb_pub, CB_EVENT_TOPIC, timeout=2.0)
                self.cb_pub.publish(CB_Event(entity_name=name, entity_status=status))
                log.info("CB_Event %s %s published", name, "CREATED" if status == CB_Event.CREATED else "REMOVED")
            except Exception:  # rospy shutting down: nothing more can be announced
                log.exception("cannot publish CB_Event for %s", name)

    def _run(self):
        while True:
            job = self._queue.get()
            if job is None:
                return
            kind, name = job
            try:
                if kind == "connect":
                    self.firos.connect(name or None)
                elif kind == "disconnect":
                    if name:
                        self.firos.disconnect(name)
                else:
                    self._rcm_connect(name)
            except ApiError as exc:
                self.notes.warning("%s %s: %s", kind, shown(name), shown(exc.reason))
            except Exception:  # one bad request must not stop the control thread
                log.exception("%s %s failed", kind, shown(name))

    def _rcm_connect(self, name):
        try:
            check_robot_name(name)        # before the name goes into a service call or the log
        except NgsiEncodingError as exc:
            raise ApiError(400, str(exc)) from None
        try:
            rospy.wait_for_service(FIROS_INFO_SERVICE, timeout=self.service_timeout)
            answer = rospy.ServiceProxy(FIROS_INFO_SERVICE, FIROS_Info)(instance_name=name)
            info = json.loads(answer.json_format or "{}")
        except (rospy.ROSException, rospy.ServiceException, ValueError) as exc:
            log.error("cannot learn the topics of %s from %s: %s; connecting it without topics",
                      name, FIROS_INFO_SERVICE, exc)
            info = {}
        entry = info.get(name, {}) if isinstance(info, dict) else {}
        self.firos.connect_rcm(name, entry)
