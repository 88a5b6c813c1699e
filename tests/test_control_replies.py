"""Run control replies are typed: processes decide on ``ControlReply.code`` (and ``state``), never on ``detail``.

The source tree is read for any decision on a message's ``detail`` text (rewording a reply once silently broke
nothing only because nobody reworded it); real processes answer with the codes the launcher decides on.
"""

from __future__ import annotations

import ast
import threading
from pathlib import Path

import pytest

from orchestrator.stack.launcher import BrainLaunch
from protocol import codec, keys
from protocol.bus import ANSWER_TIMEOUT_S
from protocol.episode_spec import EpisodeSpec
from protocol.messages import ControlReply, ControlRequest, ReplyCode, ServerState

ROOT = Path(__file__).resolve().parent.parent
# Text checks are fine in tests (they check what people read); everywhere else the code decides.
SKIPPED_FOLDERS = {"tests", ".venv", "build", "dist", ".git"}
TEXT_METHODS = {"startswith", "endswith", "find", "index", "count", "lower", "upper", "casefold", "split", "strip"}


def is_detail(node: ast.AST) -> bool:
    """``<anything>.detail``: the human text of a control reply (and of an episode's end)."""
    return isinstance(node, ast.Attribute) and node.attr == "detail"


def wording_matches(path: Path, *, root: Path = ROOT) -> list[str]:
    """Each place in ``path`` that compares, searches or reshapes a ``.detail`` text, as ``file:line``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Compare) and any(is_detail(side) for side in [node.left, *node.comparators]):
            found.append(node)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr in TEXT_METHODS and is_detail(node.func.value):
                found.append(node)
        elif isinstance(node, ast.Match) and is_detail(node.subject):
            found.append(node)
    return [f"{path.relative_to(root)}:{node.lineno}" for node in found]


def source_files() -> list[Path]:
    return [path for path in sorted(ROOT.rglob("*.py")) if not SKIPPED_FOLDERS & set(path.relative_to(ROOT).parts[:-1])]


def test_no_reply_is_matched_by_its_wording():
    files = source_files()
    assert any(path.name == "launcher.py" for path in files)  # the walk reaches the packages
    matches = [match for path in files for match in wording_matches(path)]
    assert not matches, f"decide on ControlReply.code, not on detail text: {matches}"


def test_the_check_sees_a_match_on_wording(tmp_path):
    """The check itself can fail: the launcher's former retry condition is found."""
    sample = tmp_path / "sample.py"
    sample.write_text('retry = "is not alive" in reply.detail or reply.detail.startswith("busy")\n')
    assert wording_matches(sample, root=tmp_path) == ["sample.py:1", "sample.py:1"]


def request(stack, key: str, control: ControlRequest) -> ControlReply:
    payload = stack.bus.request(key, codec.encode(control), timeout_s=ANSWER_TIMEOUT_S)
    assert payload is not None, f"nobody answered on {key}"
    return codec.decode(payload, ControlReply)


@pytest.mark.integration
def test_refusals_carry_their_code_and_a_late_brain_is_waited_for(make_stack):
    stack = make_stack(BrainLaunch("explicit"))
    sim = keys.sim_control(stack.run_id)
    late = EpisodeSpec(active_brain="late", max_sim_seconds=2.0)

    refused = request(stack, sim, ControlRequest(action="start", spec=late))
    assert (refused.ok, refused.code, refused.state) == (False, ReplyCode.NOT_ALIVE, ServerState.IDLE)
    assert "'late' is not alive" in refused.detail  # the detail still tells a person which brain
    host = request(stack, keys.brain_control(stack.run_id, "explicit"), ControlRequest(action="dance"))
    assert (host.ok, host.code, host.state) == (False, ReplyCode.UNKNOWN_ACTION, ServerState.SERVING)

    # The launcher retries a not_alive refusal while the brain's token is on its way, and decides on the code.
    appears = threading.Timer(1.0, stack.bus.declare_alive, args=(keys.alive(stack.run_id, "brain", "late"),))
    appears.start()
    try:
        started = stack._start(late)
    finally:
        appears.join()
    assert (started.ok, started.code, started.state) == (True, ReplyCode.OK, ServerState.STARTING)
    busy = request(stack, sim, ControlRequest(action="start", spec=late))
    assert (busy.ok, busy.code) == (False, ReplyCode.BUSY)
    assert request(stack, sim, ControlRequest(action="stop")).ok
