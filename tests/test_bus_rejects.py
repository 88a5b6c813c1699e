"""Bad input on the bus: counted per subscription or queryable, logged rate-limited, every drop in the lines."""

from __future__ import annotations

import logging
import re
import time

from protocol.bus import RejectCounter


def counted(lines: list[str]) -> int:
    return sum(1 if "dropped bad " in line else int(re.search(r"dropped (\d+) more", line)[1]) for line in lines)


def test_bad_input_is_logged_first_in_full_then_at_most_once_an_interval_then_at_flush(caplog):
    rejects = RejectCounter(interval_s=0.3)
    caplog.set_level(logging.WARNING, logger="drivebench.bus")
    started = time.monotonic()
    sent = 0
    while time.monotonic() - started < 1.0:  # about three intervals of junk under one wildcard
        rejects.reject(f"run/r/brain/junk{sent}/cmd", ValueError("not a valid Command"), source="run/r/brain/*/cmd")
        sent += 1
        time.sleep(0.001)
    rejects.reject("run/r/sim/control", ValueError("not a valid ControlRequest"), what="request")
    elapsed_s = time.monotonic() - started
    during = [r.getMessage() for r in caplog.records]
    rejects.flush()
    lines = [r.getMessage() for r in caplog.records]

    assert lines[0].startswith("dropped bad message on run/r/brain/junk0/cmd: not a valid Command (more on ")
    control = [line for line in lines if "run/r/sim/control" in line]
    assert len(control) == 1 and control[0].startswith("dropped bad request on run/r/sim/control: not a valid Contr")
    wildcard = [line for line in lines if "run/r/brain/*/cmd" in line]
    assert 2 <= len(wildcard) <= 2 + elapsed_s / 0.3, wildcard  # the first, one per interval, the rest at flush
    assert counted(wildcard) == sent > 100  # every drop is in a line
    summary = r"dropped \d+ more bad message\(s\) on run/r/brain/\*/cmd since [\d:]+ \(the last on run/r/brain/junk"
    assert re.match(summary, wildcard[1]), wildcard[1]
    assert len(lines) > len(during)  # flush logged what the interval had not yet
    assert rejects.counts == {"run/r/brain/*/cmd": sent, "run/r/sim/control": 1}  # bounded: by source, not by key
    rejects.flush()
    assert len(caplog.records) == len(lines)  # nothing new: nothing logged twice
