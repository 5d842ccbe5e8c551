"""The agent process's own resources: the soft open-file limit raised to the hard one (and the agent port's default
cap following it), and the garbage collector's freezes (what survived is frozen; what became cyclic garbage while
frozen is freed at the next thaw), on this process's real limits and real collector."""

import gc
import logging
import resource
import weakref

import pytest
from twisted.internet import task

from rcm_platform import rcmp_inter_communication as ic
from rcm_platform import rcmp_resources


@pytest.fixture
def nofile():
    before = resource.getrlimit(resource.RLIMIT_NOFILE)
    yield before
    resource.setrlimit(resource.RLIMIT_NOFILE, before)


def test_the_soft_open_file_limit_goes_up_to_the_hard_one(nofile, caplog):
    _, hard = nofile
    ceiling = rcmp_resources.NOFILE_CEILING if hard == resource.RLIM_INFINITY else min(hard, 65536)
    if ceiling <= 256:
        pytest.skip(f"the hard open-file limit here ({hard}) leaves no room to lower the soft one")
    resource.setrlimit(resource.RLIMIT_NOFILE, (256, hard))
    assert ic.default_max_connections() == 64            # a quarter of 256
    with caplog.at_level(logging.INFO, logger="rcmp.resources"):
        assert rcmp_resources.raise_open_files() == (256, ceiling)
    assert resource.getrlimit(resource.RLIMIT_NOFILE) == (ceiling, hard)
    assert f"open-file limit raised from 256 to {ceiling}" in caplog.text
    assert ic.default_max_connections() == ceiling // 4  # the agent port's cap follows the limit
    assert rcmp_resources.raise_open_files() == (ceiling, ceiling)   # already there: nothing to do


def test_the_cap_never_falls_below_64(nofile):
    resource.setrlimit(resource.RLIMIT_NOFILE, (100, nofile[1]))
    assert ic.default_max_connections() == 64


class Cycle:
    def __init__(self):
        self.me = self


@pytest.fixture
def freezer():
    clock = task.Clock()
    freezer = rcmp_resources.GcFreezer(clock, freeze_every=30.0, thaw_every=120.0)
    freezer.start()
    yield clock, freezer
    freezer.stop()


def test_what_survived_is_frozen_and_a_thaw_frees_what_died_meanwhile(freezer):
    clock, freezer = freezer
    held = Cycle()
    gone_young = Cycle()
    young = weakref.ref(gone_young)
    del gone_young                                       # cyclic garbage before the freeze: collected, not frozen
    clock.advance(30.0)
    assert freezer.freezes == 1
    assert young() is None
    assert gc.get_freeze_count() > 0
    frozen = weakref.ref(held)
    del held                                             # garbage now, but frozen: a full collection skips it
    gc.collect()
    assert frozen() is not None
    clock.pump([30.0] * 3)                               # 120 s: thawed and collected, then frozen again
    assert freezer.thaws == 1
    assert frozen() is None
    assert gc.get_freeze_count() > 0


def test_stopping_thaws_everything(freezer):
    clock, freezer = freezer
    clock.advance(30.0)
    assert gc.get_freeze_count() > 0
    freezer.stop()
    assert gc.get_freeze_count() == 0
