"""rcmp_ext_connector's listener limits: slow and idle clients, connection caps with 503, in-process with small
limits and real sockets driven from threads."""

import http.client
import json
import os
import socket
import tempfile

from twisted.internet import defer, threads
from twisted.trial import unittest as trial

from rcm_platform.rcmp_ext_connector import make_site, rdapi_service
from rcm_platform.rcmp_platform_command import PlatformCommands
from rcm_platform.rcmp_robotics_data import RoboticsData
from rcm_platform.rcmp_service_command import ServiceCommands
from tests.support.polling import until_deferred


# -- slow and idle clients, in-process with small limits ----------------------------------------------------------

class SlowClientTests(trial.TestCase):
    """The RDAPI's listener with small caps and a short request deadline, driven by real sockets in threads."""

    def setUp(self):
        from twisted.internet import reactor
        self.data = RoboticsData(os.path.join(tempfile.mkdtemp(), "robotics_data.db"))
        self.addCleanup(self.data.close)
        self.site = make_site(PlatformCommands(self.data), ServiceCommands(self.data), max_connections=3,
                              max_per_address=2, idle_timeout=30, request_deadline=0.5, connection_lifetime=1.0)
        self.listener = rdapi_service(self.site, 0, "127.0.0.1", reactor=reactor)
        self.listener.startService()
        self.addCleanup(self.listener.stopService)
        self.port = self.listener.port.getHost().port

    def _trickle(self, source="127.0.0.1", total=40):
        """Send a request line a byte every 0.05 s (``total`` bytes, 2 s); return (bytes sent, what came back)."""
        sent, answer = 0, b""
        with socket.create_connection(("127.0.0.1", self.port), timeout=5, source_address=(source, 0)) as sock:
            line = b"GET /platform_instance/read HTTP/1.1\r\nX-Pad: " + b"a" * total
            try:
                for byte in line[:total]:
                    sock.sendall(bytes([byte]))
                    sent += 1
                    sock.settimeout(0.05)
                    try:
                        chunk = sock.recv(4096)
                        if not chunk:
                            break
                        answer += chunk
                    except socket.timeout:
                        pass
            except OSError:
                pass
        return sent, answer

    def _idle_until_closed(self, source="127.0.0.1"):
        with socket.create_connection(("127.0.0.1", self.port), timeout=10, source_address=(source, 0)) as sock:
            try:
                return sock.recv(4096)
            except OSError:
                return b""

    def _get(self, source):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10, source_address=(source, 0))
        try:
            conn.request("GET", "/platform_instance/read")
            resp = conn.getresponse()
            return resp.status, resp.read()
        finally:
            conn.close()

    @defer.inlineCallbacks
    def test_a_trickling_client_is_dropped_and_an_idle_one_closed(self):
        sent, answer = yield threads.deferToThread(self._trickle)
        self.assertLess(sent, 40, "the server let a request trickle on past its deadline")
        self.assertNotIn(b"200 OK", answer)
        closed = yield threads.deferToThread(self._idle_until_closed)
        self.assertEqual(closed, b"")
        self.assertGreaterEqual(self.site.slow_dropped, 2)
        status, _ = yield threads.deferToThread(self._get, "127.0.0.1")
        self.assertEqual(status, 200)

    @defer.inlineCallbacks
    def test_caps_answer_503_and_free_up(self):

        def scenario():
            held = [socket.create_connection(("127.0.0.1", self.port), timeout=5) for _ in range(2)]
            try:
                per_address = self._get("127.0.0.1")            # a third from 127.0.0.1: over its cap
                other = self._get("127.0.0.3")                  # another address: served (3 of 3)
                held.append(socket.create_connection(("127.0.0.1", self.port), timeout=5,
                                                      source_address=("127.0.0.4", 0)))
                total = self._get("127.0.0.5")                  # a fourth in all: over the total cap
            finally:
                for sock in held:
                    sock.close()
            return per_address, other, total
        per_address, other, total = yield threads.deferToThread(scenario)
        self.assertEqual(per_address[0], 503)
        self.assertIn(b"127.0.0.1", per_address[1])
        self.assertEqual(other[0], 200)
        self.assertEqual(total[0], 503)
        self.assertEqual(json.loads(total[1])["result"], "ERROR")
        self.assertEqual(self.site.refused, 2)
        # the held connections are closed: the counts go back down and everyone is served again
        yield until_deferred(lambda: not self.site.open_channels, timeout=10, message="the connections to close")
        status, _ = yield threads.deferToThread(self._get, "127.0.0.1")
        self.assertEqual(status, 200)

    @defer.inlineCallbacks
    def test_a_keep_alive_connection_trickling_requests_is_closed_at_its_lifetime(self):
        """One small request every 0.1 s on one connection (each within every deadline) used to keep a slot for
        ever: after ``connection_lifetime`` the answer says ``Connection: close`` and the connection ends; every
        request sent was answered in full."""

        def trickle():
            conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=10)
            answers = []
            try:
                conn.connect()
                sock = conn.sock
                for _ in range(100):
                    try:
                        conn.request("GET", "/platform_instance/read")
                        resp = conn.getresponse()
                    except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError):
                        # the server closed the idle connection as this request was on its way (HTTP's
                        # keep-alive race: a client sends it again on a new connection); nothing was half-answered
                        return answers, True
                    answers.append((resp.status, resp.getheader("Connection"), json.loads(resp.read())["result"]))
                    if resp.will_close:
                        break
                    sock.settimeout(0.1)
                    try:                    # wait a little between requests, and see the server close meanwhile
                        if sock.recv(1, socket.MSG_PEEK) == b"":
                            break
                    except socket.timeout:
                        pass
                    sock.settimeout(10)
                closed = sock.recv(1) == b"" if conn.sock is not None else True
            finally:
                conn.close()
            return answers, closed
        answers, closed = yield threads.deferToThread(trickle)
        self.assertTrue(closed)
        self.assertLess(len(answers), 100, "the connection was kept past its lifetime")
        self.assertTrue(all(status == 200 and result == "OK" for status, _, result in answers))
        self.assertGreaterEqual(self.site.expired, 1)
        yield until_deferred(lambda: not self.site.open_channels, timeout=10, message="the connection to close")
