"""rcmp_command: validation of names, params and service logics, and the read cache (real SQLite in a temp dir,
twisted.trial)."""

import os
import tempfile

from twisted.trial import unittest

from rcm_platform.rcmp_command import BadRequest, ReadCache, split_params, validate_name, validate_service_logic
from rcm_platform.rcmp_robotics_data import RoboticsData


class DataTestCase(unittest.TestCase):
    def setUp(self):
        self.dir = tempfile.mkdtemp()
        self.data = RoboticsData(os.path.join(self.dir, "robotics_data.db"))
        self.addCleanup(self.data.close)


class ValidationTests(unittest.TestCase):
    def test_names(self):
        for good in ("r", "robot1", "Robot_01", "a" * 64):
            self.assertEqual(validate_name(good, "pi_name"), good)
        for bad in ("", "a" * 65, "1r", "_r", "r-1", "r/1", "r 1", "r;1", "$(x)", "r\u00f6", 5, None, ["r"]):
            self.assertRaises(BadRequest, validate_name, bad, "pi_name")

    def test_params_split_like_a_shell_without_one(self):
        self.assertEqual(split_params("-a 'b c' \"d e\" f\\ g $(rm) ;ls"), ["-a", "b c", "d e", "f g", "$(rm)", ";ls"])
        self.assertEqual(split_params(""), [])
        for bad in ("'open", 'x "y', "trail\\", "nul\x00"):
            self.assertRaises(BadRequest, split_params, bad)

    def test_service_logic_normalised(self):
        name, nodes, launchers, side = validate_service_logic({
            "slg_name": "s", "sn_list": [{"sn_package": "p", "sn_type": "t", "sn_name": "n", "sn_side": "R"}]})
        self.assertEqual((name, launchers, side), ("s", [], "S"))
        self.assertEqual(nodes, [{"sn_package": "p", "sn_type": "t", "sn_name": "n", "sn_params": "",
                                  "sn_side": "R"}])
        with self.assertRaisesRegex(BadRequest, r"sn_list\[0\]\.sn_side"):
            validate_service_logic({"slg_name": "s", "sn_list": [
                {"sn_package": "p", "sn_type": "t", "sn_name": "n", "sn_side": "Q"}]})


class ReadCacheTests(DataTestCase):
    def test_read_cache_is_bounded(self):
        cache = ReadCache(self.data, max_entries=3)
        for i in range(5):
            cache.put(i, self.data.generation, [i])
        self.assertLessEqual(len(cache._entries), 3)
