"""rcmp_ext_connector: the RDAPI resource driven with Twisted's DummyRequest (as Twisted's own web tests do), on real
SQLite."""

import json

from twisted.internet import defer
from twisted.web.test.requesthelper import DummyRequest

from rcm_platform.rcmp_ext_connector import Rdapi
from rcm_platform.rcmp_platform_command import PlatformCommands
from rcm_platform.rcmp_service_command import ServiceCommands
from tests.unit.rcm_platform.test_rcmp_command import DataTestCase


class ResourceTests(DataTestCase):
    def setUp(self):
        super().setUp()
        self.resource = Rdapi(PlatformCommands(self.data), ServiceCommands(self.data))

    @defer.inlineCallbacks
    def render(self, method, path, body=None, args=None):
        request = DummyRequest(path.strip("/").split("/"))
        request.method = method.encode()
        request.path = path.encode()
        request.args = args or {}
        request.too_large = False
        request.max_body = 65536
        if body is not None:
            from io import BytesIO
            request.content = BytesIO(body)
            request.requestHeaders.setRawHeaders(b"content-type", [b"application/json"])
        result = self.resource.render(request)
        if isinstance(result, bytes):
            request.write(result)
            request.finish()
        elif not request.finished:
            yield request.notifyFinish()
        return request.responseCode or 200, b"".join(request.written), request

    @defer.inlineCallbacks
    def test_ok_and_error_answers(self):
        code, body, _ = yield self.render("GET", "/platform_instance/read")
        self.assertEqual((code, json.loads(body)), (200, {"result": "OK", "reason": []}))
        code, body, _ = yield self.render("POST", "/service_logic/provisioning", b'{"slg_name": "s"}')
        self.assertEqual(code, 200)
        code, body, _ = yield self.render("POST", "/service_logic/provisioning", b'{"slg_name": "s"}')
        self.assertEqual((code, json.loads(body)["result"]), (409, "ERROR"))
        code, body, request = yield self.render("GET", "/service_logic/provisioning")
        self.assertEqual(code, 405)
        self.assertEqual(request.responseHeaders.getRawHeaders(b"allow")[-1], b"POST, OPTIONS")
        code, body, _ = yield self.render("GET", "/service_logic/read", args={b"slg_name": [b"s"]})
        self.assertEqual(json.loads(body)["reason"], {"ss_side": "S", "sn_list": [], "sl_list": []})

    @defer.inlineCallbacks
    def test_unexpected_error_is_500_and_logged(self):
        class Broken:
            def read(self):
                return defer.fail(RuntimeError("boom"))
        self.resource = Rdapi(Broken(), ServiceCommands(self.data))
        code, body, _ = yield self.render("GET", "/platform_instance/read")
        self.assertEqual(code, 500)
        self.assertIn("rcmp.log", json.loads(body)["reason"])
        self.flushLoggedErrors(RuntimeError)

    @defer.inlineCallbacks
    def test_answers_are_strict_json_and_peer_strings_are_cut(self):
        class Spaces:
            def describe(self, ss_name):     # a space whose live state carries numbers JSON cannot
                return {"r_nodes": [{"sn_name": "n", "state": "running", "load": float("nan")}],
                        "inbound_port": None, "ratio": float("inf")}
        self.resource = Rdapi(PlatformCommands(self.data), ServiceCommands(self.data, spaces=Spaces()))
        code, body, _ = yield self.render("GET", "/service_space/read", args={b"ss_name": [b"robot1"]})

        def refuse(constant):
            raise ValueError(constant)
        answer = json.loads(body, parse_constant=refuse)
        self.assertEqual(code, 200)
        self.assertEqual((answer["reason"]["r_nodes"][0]["load"], answer["reason"]["ratio"]), ("NaN", "Infinity"))
        code, body, _ = yield self.render("GET", "/" + "a" * 16000)
        self.assertEqual(code, 404)
        self.assertLess(len(body), 400)
        code, body, _ = yield self.render("GET", "/platform_instance/read", args={b"k" * 15000: [b"1"]})
        self.assertEqual(code, 400)
        self.assertLess(len(body), 400)
