"""The challenge's page in a real browser (headless Chromium over the DevTools protocol) against a real
``drivebench board serve``: a person uploads two brains through the page's form, watches the second one's state
change on its page without reloading it, and reads the leaderboard ranking both by IQM progress with intervals."""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from pathlib import Path

import needs
import pytest
from support.cdp import Browser
from support.waits import wait_for
from test_board import GOOD_BRAIN, LOADED_S, Server, board, brain_file  # noqa: F401  (board: the fixture)

pytestmark = [pytest.mark.slow, pytest.mark.integration]

SLOW_BRAIN = GOOD_BRAIN.replace("speed_mps=3.0", "speed_mps=1.0")  # a third of the way in the same time
PAGE_GRACE_S = 20  # the page polls each second; a loaded machine may take some more to answer and redraw
LIFECYCLE = ["queued", "checking", "running", "scored"]
# Set once a page has loaded: still there later means the page was never reloaded in between.
PROBE = "window.__sameDocument"
STATE = (
    "JSON.stringify([" + PROBE + " === true, (document.getElementById('state') || {}).textContent || null,"
    " ((document.getElementById('state') || {}).dataset || {}).final || null])"
)


@pytest.fixture
def browser(tmp_path):
    from test_browser import browser_check

    chromium = browser_check().chromium()
    if chromium is None:
        needs.missing("no chromium on PATH (Debian: apt-get install chromium)")  # a failure in CI, not a skip
    with Browser.start(chromium, profile=tmp_path / "chromium") as started:
        yield started


def upload(browser: Browser, url: str, path: Path, *, name: str) -> str:
    """Fill in and send the page's upload form; the id of the submission page it lands on."""
    browser.navigate(url + "/")
    browser.evaluate(f"document.querySelector('#upload input[name=name]').value = {json.dumps(name)}")
    browser.choose_file("#upload input[type=file]", path)
    browser.evaluate("document.querySelector('#upload button[type=submit]').click()")
    landed = wait_for(
        lambda: re.fullmatch(rf"{re.escape(url)}/submissions/(\w+)", _current(browser, "location.href") or ""),
        timeout_s=60,
        what=f"the upload of {path.name} to land on its page",
    )
    wait_for(lambda: _current(browser, "document.readyState") == "complete", timeout_s=60, what="its page to load")
    return landed.group(1)


def _current(browser: Browser, expression: str) -> object:
    """``expression`` in the page, or None while the page is between documents (no context to run it in)."""
    try:
        return browser.evaluate(expression)
    except AssertionError:
        return None


def watch_states(browser: Browser, *, server_final: Callable[[], bool], timeout_s: float) -> list[tuple[bool, str]]:
    """The submission page's shown state each time it changes, until it is final, with whether the page was still
    the document the test loaded (True) or had reloaded itself (False). The test never reloads it; once the server
    says the submission is final, the page has PAGE_GRACE_S to show it."""
    browser.evaluate(f"{PROBE} = true")
    seen: list[tuple[bool, str]] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server_final():
            deadline = min(deadline, time.monotonic() + PAGE_GRACE_S)
        shown = _current(browser, STATE)
        if shown is not None:
            same, state, final = json.loads(str(shown))
            if state and (not seen or seen[-1] != (same, state)):
                seen.append((same, state))
            if final == "true":
                return seen
        time.sleep(0.2)  # a poll, not a wait before an assertion: the page's own poll is 1 s
    raise AssertionError(f"the page did not show the final state; it showed, in turn: {seen}")


@pytest.mark.timeout(3 * LOADED_S)  # two evaluations, one after the other, on a loaded machine
def test_an_upload_through_the_form_shows_its_state_live_and_ranks_by_iqm(board, browser, tmp_path):  # noqa: F811
    fast = upload(browser, board.url, brain_file(tmp_path, "fast.py", GOOD_BRAIN), name="fast-pilot")
    # One worker: the second waits in the queue behind the first, so its page starts at queued.
    slow = upload(browser, board.url, brain_file(tmp_path, "slow.py", SLOW_BRAIN), name="slow-pilot")
    seen = watch_states(browser, server_final=lambda: board.state(slow)["final"], timeout_s=2 * LOADED_S)
    live = [state for same, state in seen if same]
    assert len(set(live)) >= 2 and live[0] == "queued", seen  # it changed in place, at least once
    assert [state for _, state in seen] == sorted({s for _, s in seen}, key=LIFECYCLE.index), seen
    assert seen[-1][1] == "scored", seen
    assert _current(browser, "!!document.getElementById('hidden-scores')"), "the scored page shows no scores"

    browser.navigate(board.url + "/")
    rows = browser.evaluate(
        "Array.from(document.querySelectorAll('#leaderboard tr.entry')).map("
        "r => [r.dataset.id].concat(Array.from(r.cells).map(c => c.textContent.trim())))"
    )
    ranking = json.loads(board.get("/api/leaderboard"))
    assert [row[0] for row in rows] == [fast, slow] == [entry["id"] for entry in ranking], (rows, ranking)
    estimates = [entry["progress_iqm"]["estimate"] for entry in ranking]
    assert estimates[0] > estimates[1], ranking
    for row, entry in zip(rows, ranking):
        iqm = entry["progress_iqm"]
        assert row[3] == f"{iqm['estimate']:.2f} [{iqm['low']:.2f}, {iqm['high']:.2f}]", row
        assert re.fullmatch(r"\d+ / 2\s+\[\d\.\d\d, \d\.\d\d\]", row[4]), row


@pytest.mark.timeout(3 * LOADED_S)
def test_a_submissions_page_follows_it_across_a_server_restart(board, browser, tmp_path):  # noqa: F811
    """The server stops while a submission's page is open: the page says the server is not answering, keeps asking,
    and follows the restarted server's queue to the final state, with nobody reloading it."""
    submission = upload(browser, board.url, brain_file(tmp_path, "good.py", GOOD_BRAIN), name="patient")
    board.stop()
    wait_for(
        lambda: _current(browser, "!document.getElementById('server-away').hidden"),
        timeout_s=60,
        what="the page to say the server is not answering",
    )
    again = Server(board.data, board.conditions)
    again.port, again.url = board.port, board.url  # the same address: the page's own
    again.start()
    try:
        seen = watch_states(browser, server_final=lambda: again.state(submission)["final"], timeout_s=2 * LOADED_S)
    finally:
        again.stop()
    assert seen[-1] == (False, "scored"), seen  # reloaded by the page itself once final
    assert _current(
        browser, "document.getElementById('server-away') === null || document.getElementById('server-away').hidden"
    )
