"""rcmp_log_guard: a peer's strings are cut before they are logged, and the lines a peer can cause are rate-limited
(a fake clock; a real logger with a handler that keeps the lines)."""

import logging

import pytest

from rcm_platform.rcmp_log_guard import LOGGED_TEXT, Budget, BudgetFilter, shown


class Lines(logging.Handler):
    def __init__(self):
        super().__init__()
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


@pytest.fixture
def logger():
    logger = logging.getLogger(f"test.log_guard.{id(object())}")
    logger.propagate = False
    logger.setLevel(logging.DEBUG)
    handler = Lines()
    logger.addHandler(handler)
    logger.lines = handler.lines
    return logger


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


def test_a_long_string_is_cut_and_says_how_long_it_was():
    text = shown("/" + "a" * 16000)
    assert len(text) < LOGGED_TEXT + 40
    assert text.startswith("'/aaa") and text.endswith("... (16001 characters)")
    assert shown("/nothing") == "'/nothing'"


def test_control_characters_cannot_forge_a_log_line():
    text = shown("x\n2024-01-01 00:00:00 INFO rcm_platform: admin logged in\x1b[2J")
    assert "\n" not in text and "\x1b" not in text
    assert "\\n" in text and "\\x1b" in text


def test_bytes_and_other_values_are_bounded_without_being_rendered_whole():
    assert shown(b"\xff" * 5000, 50).endswith("... (5000 characters)")
    huge = {"name": "n" * 1000000, "nodes": list(range(100000))}
    text = shown(huge)
    assert len(text) <= LOGGED_TEXT + 3
    assert "nnnn" in text and "..." in text
    assert shown(None) == "None" and shown(3.5) == "3.5"


def test_a_budget_writes_its_burst_then_counts_the_rest_with_the_next_window(logger):
    clock = Clock()
    budget = Budget(logger, "warnings about strangers", clock=clock, burst=3, period=10.0)
    written = [budget.warning("stranger %d", n) for n in range(10)]
    assert written == [True] * 3 + [False] * 7
    assert logger.lines == ["stranger 0", "stranger 1", "stranger 2"]
    clock.now += 10.0
    budget.warning("stranger again")
    assert logger.lines[3:] == ["7 more warnings about strangers were left out of the log in the last 10 s",
                                "stranger again"]
    assert budget.left_out_total == 7


def test_a_flood_that_goes_on_gets_ever_longer_windows_and_a_quiet_window_resets_them(logger):
    clock = Clock()
    budget = Budget(logger, "lines", clock=clock, burst=2, period=10.0, longest=40.0)
    lengths = []
    for _ in range(6):            # a flood: far more than the burst in every window
        for _ in range(50):
            budget.info("flood")
        lengths.append(budget._length)
        clock.now += budget._length
    assert lengths == [10.0, 20.0, 40.0, 40.0, 40.0, 40.0]
    assert logger.lines.count("flood") == 12             # two per window, whatever the flood's size
    clock.now += 100.0                                    # quiet: the usual window again
    budget.info("calm")
    assert budget._length == 10.0
    assert logger.lines[-1] == "calm"


def test_flush_writes_the_count_of_a_flood_that_stopped(logger):
    budget = Budget(logger, "lines", clock=Clock(), burst=1)
    for _ in range(5):
        budget.warning("x")
    budget.flush()
    assert logger.lines == ["x", "4 more lines were left out of the log in the last 10 s"]
    budget.flush()
    assert len(logger.lines) == 2


def test_the_filter_limits_a_logger_but_lets_errors_through(logger):
    clock = Clock()
    logger.addFilter(BudgetFilter(Budget(logger, "lines of Twisted's own log", clock=clock, burst=2)))
    for n in range(20):
        logger.info("Timing out client: %d", n)
    logger.error("Unhandled error in Deferred")
    clock.now += 10.0
    logger.info("later")
    assert logger.lines == ["Timing out client: 0", "Timing out client: 1", "Unhandled error in Deferred",
                            "18 more lines of Twisted's own log were left out of the log in the last 10 s", "later"]
