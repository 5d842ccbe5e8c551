"""Heartbeats with a fake clock: beats every interval, a peer silent for misses*interval is gone, once."""

from twisted.internet import defer, task
from twisted.trial import unittest

from rcm_platform.rcmp_wd import Watchdog


class Peer:
    """A fake peer: records beats; answers them (moves last_heard) only while ``answering``."""

    def __init__(self, clock):
        self.clock = clock
        self.heard = clock.seconds()
        self.beats = []
        self.answering = True

    def beat(self):
        self.beats.append(self.clock.seconds())
        if self.answering:
            self.heard = self.clock.seconds()
            return defer.succeed({})
        return defer.fail(TimeoutError("no answer"))


class WatchdogTests(unittest.TestCase):

    def setUp(self):
        self.clock = task.Clock()
        self.peer = Peer(self.clock)
        self.gone = []
        self.dog = Watchdog(self.clock, interval=2.0, misses=3, send_beat=self.peer.beat,
                            last_heard=lambda: self.peer.heard, on_gone=self.gone.append, name="test peer")

    def test_beats_every_interval_while_answered(self):
        self.dog.start()
        self.clock.pump([2.0] * 10)
        self.assertEqual(self.peer.beats, [2.0 * n for n in range(1, 11)])
        self.assertEqual(self.gone, [])
        self.assertTrue(self.dog.running)

    def test_no_beat_before_the_first_interval(self):
        self.dog.start()
        self.clock.advance(1.9)
        self.assertEqual(self.peer.beats, [])

    def test_silent_peer_is_gone_after_misses_times_interval(self):
        self.dog.start()
        self.clock.advance(2.0)                      # answered at t=2
        self.peer.answering = False
        self.clock.advance(2.0)                      # t=4: silent 2 s
        self.clock.advance(2.0)                      # t=6: silent 4 s
        self.assertEqual(self.gone, [])
        self.clock.advance(2.0)                      # t=8: silent 6 s = 3 * 2 s
        self.assertEqual(self.gone, [6.0])
        self.assertFalse(self.dog.running)

    def test_gone_is_reported_once_and_beats_stop(self):
        self.dog.start()
        self.peer.answering = False
        self.clock.pump([2.0] * 10)
        self.assertEqual(len(self.gone), 1)
        self.assertEqual(self.peer.beats, [2.0, 4.0])  # no beat sent at the tick that declares it gone

    def test_any_frame_from_the_peer_keeps_it_alive(self):
        self.dog.start()
        self.peer.answering = False
        for _ in range(10):
            self.clock.advance(2.0)
            self.peer.heard = self.clock.seconds() - 1.0   # the peer's own beats arrive between ours
        self.assertEqual(self.gone, [])

    def test_stopped_watchdog_neither_beats_nor_declares(self):
        self.dog.start()
        self.dog.stop()
        self.peer.answering = False
        self.clock.pump([2.0] * 10)
        self.assertEqual((self.peer.beats, self.gone), ([], []))

    def test_restart_after_stop(self):
        self.dog.start()
        self.dog.stop()
        self.dog.start()
        self.clock.advance(2.0)
        self.assertEqual(self.peer.beats, [2.0])

    def test_bad_settings_are_rejected(self):
        with self.assertRaises(ValueError):
            Watchdog(self.clock, 0, 3, self.peer.beat, lambda: 0, self.gone.append)
        with self.assertRaises(ValueError):
            Watchdog(self.clock, 1.0, 0, self.peer.beat, lambda: 0, self.gone.append)

    def test_limit(self):
        self.assertEqual(self.dog.limit, 6.0)

    def test_a_late_check_does_not_judge_then_the_next_one_does(self):
        self.dog.start()
        self.peer.answering = False
        self.clock.advance(10.0)                     # this agent was stalled for 10 s: frames may be unread
        self.assertEqual(self.gone, [])
        self.assertEqual(len(self.peer.beats), 1)    # it still beats
        self.clock.advance(2.0)                      # an on-time check after the stall judges
        self.assertEqual(len(self.gone), 1)

    def test_frames_read_after_a_stall_keep_the_peer(self):
        self.dog.start()
        self.peer.answering = False
        self.clock.advance(10.0)
        self.peer.heard = self.clock.seconds()       # the reactor read the peer's waiting frames
        self.clock.advance(2.0)
        self.assertEqual(self.gone, [])


class MissedBeatTests(unittest.TestCase):
    """``on_miss``: a check that finds the peer silent for more than one and a half intervals, before it is gone."""

    def setUp(self):
        self.clock = task.Clock()
        self.peer = Peer(self.clock)
        self.gone, self.missed = [], []
        self.dog = Watchdog(self.clock, interval=2.0, misses=3, send_beat=self.peer.beat,
                            last_heard=lambda: self.peer.heard, on_gone=self.gone.append, name="test peer",
                            on_miss=lambda: self.missed.append(self.clock.seconds()))

    def test_an_answering_peer_misses_nothing(self):
        self.dog.start()
        self.clock.pump([2.0] * 10)
        self.assertEqual(self.missed, [])

    def test_a_beat_unanswered_by_the_next_check_is_a_miss_and_the_limit_is_not(self):
        self.dog.start()
        self.clock.advance(2.0)                 # the beat of 2.0 answered at once
        self.peer.answering = False
        self.clock.pump([2.0] * 3)              # 4.0: beat; 6.0: the beat of 4.0 missed; 8.0: silent 6 s, gone
        self.assertEqual(self.missed, [6.0])
        self.assertEqual(self.gone, [6.0])

    def test_a_peer_heard_once_between_two_checks_misses_nothing(self):
        self.dog.start()
        self.peer.answering = False
        for _ in range(5):
            self.clock.advance(1.9)
            self.peer.heard = self.clock.seconds()   # its own beats, just before each of our checks
            self.clock.advance(0.1)
        self.assertEqual((self.missed, self.gone), ([], []))

    def test_a_peer_beating_by_itself_near_our_checks_misses_nothing(self):
        self.dog.start()
        self.peer.answering = False
        for n in range(10):                     # its beats land just after, then just before our checks
            offset = 0.05 if n % 2 else 1.95
            self.clock.advance(offset)
            self.peer.heard = self.clock.seconds()
            self.clock.advance(2.0 - offset)
        self.assertEqual((self.missed, self.gone), ([], []))

    def test_a_late_check_is_not_a_miss(self):
        self.dog.start()
        self.clock.advance(2.0)
        self.peer.answering = False
        self.clock.advance(3.5)                 # this agent was stalled: the check runs 1.5 s late
        self.assertEqual(self.missed, [])
