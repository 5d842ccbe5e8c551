"""FIROS's `include/log_guard.py`: a peer's strings capped and escaped for the log, and the budget of the lines a peer
can cause (the same rule as the agent's `rcmp_log_guard`, with a lock: FIROS's HTTP workers are threads)."""

import logging
import threading

from include.log_guard import BURST, Budget, shown


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


class Lines:
    """The messages a budget wrote, from the firos_log fixture (caplog on FIROS's logger)."""

    def __init__(self, caplog):
        self.caplog = caplog

    def __getitem__(self, index):
        return [r.getMessage() for r in self.caplog.records if r.name == "firos.test_log_guard"][index]

    def __len__(self):
        return len(self[:])


def _budget(caplog, **options):
    clock = Clock()
    return Budget(logging.getLogger("firos.test_log_guard"), "lines about tests", clock=clock, **options), clock, \
        Lines(caplog)


def test_shown_caps_and_escapes_what_a_peer_sent():
    assert shown("/robots") == "'/robots'"
    long = "/" + "x" * 16000
    text = shown(long)
    assert len(text) < 260 and text.endswith("... (16001 characters)")
    assert "\n" not in shown("a\nforged line") and "\\n" in shown("a\nforged line")
    assert shown(b"\x00\xff" * 300).endswith("... (600 characters)")
    big = {"k%d" % i: "v" * 1000 for i in range(1000)}
    assert len(shown(big)) < 260
    assert shown("x" * 50, limit=10) == "'xxxxxxxxxx'... (50 characters)"


def test_a_flood_writes_its_burst_then_fewer_and_fewer_lines_and_counts_the_rest(firos_log):
    budget, clock, lines = _budget(firos_log)
    for _ in range(100):
        budget.warning("refused %s", "x")
    assert len(lines) == BURST and budget.left_out == 90
    clock.now += 10                                 # the next window: the count comes first, the window doubles
    budget.warning("refused again")
    assert lines[BURST:] == ["90 more lines about tests were left out of the log in the last 10 s", "refused again"]
    for _ in range(50):
        budget.warning("more")
    clock.now += 10                                 # still inside the 20 s window: nothing new is written
    assert not budget.warning("more") and len(lines) == BURST + 2 + BURST - 1
    clock.now += 10
    budget.warning("after 20 s")
    assert lines[-2] == "42 more lines about tests were left out of the log in the last 20 s"
    clock.now += 200                                # a quiet spell: back to the short window
    budget.flush()
    budget.info("quiet")
    assert budget._window == 10.0 and lines[-1] == "quiet"
    assert budget.left_out_total == 90 + 42


def test_threads_share_one_budget(firos_log):
    budget, clock, lines = _budget(firos_log, burst=25)
    workers = [threading.Thread(target=lambda: [budget.warning("w") for _ in range(200)]) for _ in range(8)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    assert len(lines) == 25 and budget.left_out == 8 * 200 - 25
