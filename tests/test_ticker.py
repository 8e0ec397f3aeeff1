"""Saying how a long step goes (issue 36: a first run trained its model for a minute in silence): the ticker's
lines and estimates on a clock of the test's own, its thread's lines in real time, and the command line's
progress rewriting one line on a terminal."""

from __future__ import annotations

import io
import time

import pytest

from supramodal.node.cli.arguments import StderrProgress
from supramodal.node.runtime.ticker import Ticker


def test_the_ticker_says_the_stage_the_time_so_far_and_the_time_left_by_the_networks_pace():
    now = [100.0]
    said: list[str] = []
    t = Ticker(said.append, "the model", networks=4, period=3600, clock=lambda: now[0])
    with t:
        assert said == ["the model: training (4 networks: its calibration's fold networks, which it deploys); later "
                        "runs read it from the model cache"]                                  # at once, before any work
        now[0] += 2.0
        t.stage("features, texture 1/8")
        assert t.line() == "the model: features, texture 1/8; 2 s so far"          # no network begun: no estimate
        t.stage("network 1 of 4, epoch 1 of 10", 0.1)                            # the network starts at 102 s
        now[0] += 3.0
        t.stage("network 1 of 4, epoch 4 of 10", 0.4)
        # 3 s for 0.4 of a network: 7.5 s per network, 3.6 networks left
        assert t.line() == "the model: network 1 of 4, epoch 4 of 10; 5 s so far, about 27 s left"
        now[0] += 4.5
        t.network_done()                                                         # 7.5 s for the first
        t.stage("network 2 of 4")
        now[0] += 1.0
        assert t.line() == "the model: network 2 of 4; 10 s so far, about 22 s left"   # 7.5 s x 3 networks left
        now[0] += 2.5
        t.network_done()                                   # two networks in 11 s (from 102 s): 5.5 s each
        assert t.line() == "the model: network 2 of 4; 13 s so far, about 11 s left"


def test_the_ticker_s_thread_says_a_line_every_period_until_the_step_ends():
    said: list[str] = []
    t = Ticker(said.append, "x", networks=2, period=0.05)
    t.stage("working")                     # before the thread starts: every tick says it
    with t:
        deadline = time.monotonic() + 10.0
        while len(said) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
    n = len(said)
    assert n >= 4 and all(line.startswith("x: working; ") for line in said[1:4])
    time.sleep(0.2)
    assert len(said) == n                                                        # none after the step ended
    with pytest.raises(KeyboardInterrupt):
        with Ticker(said.append, "y", networks=2, period=3600):
            raise KeyboardInterrupt
    assert said[-1].startswith("y: stopped after ")     # a plain line ends a rewritten one before the error


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("terminal", [True, False])
def test_transient_lines_rewrite_one_line_on_a_terminal_and_are_plain_lines_elsewhere(terminal):
    out = _Terminal() if terminal else io.StringIO()
    say = StderrProgress(out)
    say("start")
    say.transient("1 s so far")
    say.transient("2 s so far")
    say("done")
    if terminal:
        assert out.getvalue() == ("supramodal: start\n\r\x1b[Ksupramodal: 1 s so far\r\x1b[Ksupramodal: 2 s so far"
                                  "\r\x1b[Ksupramodal: done\n")
    else:
        assert out.getvalue() == "supramodal: start\nsupramodal: 1 s so far\nsupramodal: 2 s so far\nsupramodal: done\n"
