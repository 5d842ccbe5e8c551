"""A real ROS master (Debian's ``rosmaster --core``, optionally with ``rosout``) on a free port, for tests."""


import rosgraph

from .polling import wait_until
from .ports import free_port
from .processes import ProcessGroup, ros_env


class RosMaster:
    """One ROS master owned by a test. ``uri`` is its ROS_MASTER_URI; ``env()`` an environment for nodes."""

    def __init__(self, procs: ProcessGroup, host="127.0.0.1", with_rosout=False):
        self.procs = procs
        self.host = host
        self.port = free_port(host)
        self.uri = f"http://{host}:{self.port}/"
        self.with_rosout = with_rosout
        self.process = None

    def env(self, extra=None):
        env = ros_env(extra, master_uri=self.uri)
        env["ROS_IP"] = self.host
        return env

    def start(self, timeout=20.0):
        self.process = self.procs.start(
            ["/usr/bin/rosmaster", "--core", "-p", str(self.port)],
            env=self.env(), name=f"rosmaster-{self.port}")
        master = self.api()
        wait_until(lambda: master.is_online(), timeout=timeout, message=f"ROS master on {self.uri}")
        if self.with_rosout:
            self.procs.start(["/usr/bin/rosrun", "rosout", "rosout"], env=self.env(), name="rosout")
            wait_until(lambda: "/rosout" in self.nodes(), timeout=timeout, message="/rosout to register")
        return self

    def api(self, caller_id="/robotics_test"):
        return rosgraph.Master(caller_id, master_uri=self.uri)

    def system_state(self):
        return self.api().getSystemState()

    def nodes(self):
        pubs, subs, srvs = self.system_state()
        names = set()
        for _, members in pubs + subs + srvs:
            names.update(members)
        return names

    def topic_types(self):
        return dict(self.api().getTopicTypes())

    def publishers(self, topic):
        pubs, _, _ = self.system_state()
        return next((members for name, members in pubs if name == topic), [])

    def services(self):
        _, _, srvs = self.system_state()
        return {name for name, _ in srvs}
