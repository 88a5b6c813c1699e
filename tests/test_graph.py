"""The process graph (protocol/deploy/graph.py) against everything that used to spell it out by hand.

The generated files (compose.yaml, compose.secure.yaml, deploy/secure/router.yaml, the process table of
docs/architecture.md) must be what the graph gives; scripts/make-certs.sh must make a certificate for every identity
in it; and a real stack must put only keys that some row publishes and that row's access rules allow.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from orchestrator import compose_files
from orchestrator.stack.launcher import BrainLaunch
from protocol import keys
from protocol.bus import Inbox
from protocol.deploy import graph, security
from protocol.episode_spec import CameraSpec, EpisodeSpec
from protocol.messages import AnyRunMessage

ROOT = Path(__file__).resolve().parent.parent


def test_the_generated_files_are_what_the_graph_gives():
    assert compose_files.stale_files() == [], "run: python -m orchestrator.compose_files --write"


def test_the_check_names_a_stale_file_and_write_mends_it(tmp_path):
    for path in compose_files.generated_files().keys():
        (tmp_path / path.relative_to(ROOT)).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path.relative_to(ROOT)).write_text(path.read_text())
    compose = tmp_path / "compose.yaml"
    compose.write_text(compose.read_text().replace('"services.scorer"', '"services.referee"'))
    (stale,) = compose_files.stale_files(tmp_path)
    assert stale.startswith("compose.yaml differs from the process graph") and "services.referee" in stale
    readme = tmp_path / "docs" / "architecture.md"
    readme.write_text(readme.read_text().replace(compose_files.README_END, ""))
    with pytest.raises(ValueError, match="docs/architecture.md has no generated process table"):
        compose_files.stale_files(tmp_path)


def test_make_certs_makes_a_certificate_for_every_identity_of_the_graph():
    script = (ROOT / "scripts" / "make-certs.sh").read_text()
    names = set(re.search(r"^for name in ([^;]+); do cert", script, flags=re.M).group(1).split())
    identities = {row.identity for row in graph.ROLES if row.identity and row.name != "router"}
    assert names == identities | {graph.OBSERVER_IDENTITY}


def test_every_role_has_a_runnable_module_and_every_health_role_a_token_or_an_http_check():
    import importlib.util

    for row in graph.ROLES:
        assert not row.module or importlib.util.find_spec(row.module) is not None, row.name
        assert row.bus_mode in ("peer", "client", "router"), row.name
    assert set(graph.health_roles()) == {
        "router",
        "simulator",
        "noise",
        "brain",
        "scorer",
        "driver",
        "recorder",
        "viz",
        "ros2_bridge",
        "board",
    }
    for name in graph.health_roles():
        row = graph.role("orchestrator" if name == "driver" else name)
        assert row.token is not None or row.name == "router" or row.http_health, name
    with pytest.raises(KeyError, match="no process role 'referee'"):
        graph.role("referee")


@pytest.mark.parametrize(
    "expression, key, matches",
    [
        ("drivebench/run/*/sim/pose", "drivebench/run/r1/sim/pose", True),
        ("drivebench/run/*/sim/pose", "drivebench/run/r1/sim/camera", False),
        ("drivebench/run/*/**", "drivebench/run/r1/brain/b/cmd", True),
        ("drivebench/run/*/**", "drivebench/run/r1", False),
        ("drivebench/run/*/brain/*/cmd", "drivebench/run/r1/brain/b/control", False),
    ],
)
def test_key_matching(expression, key, matches):
    assert graph.key_matches(expression, key) is matches


def _put_allowed(role: str, key: str) -> bool:
    return any(
        flow == "ingress" and "put" in messages and any(graph.key_matches(e, key) for e in expressions)
        for flow, messages, expressions in security.ROLES[role]
    )


def test_every_key_a_stack_puts_is_published_by_one_row_that_its_access_rules_allow(make_stack):
    stack = make_stack(BrainLaunch("explicit"))
    inbox = Inbox()
    stack.bus.subscribe(keys.run_all(stack.run_id), AnyRunMessage, inbox=inbox)
    stack.run_episode(EpisodeSpec(max_sim_seconds=1.0, camera=CameraSpec(width_px=64, height_px=48)))
    # The stack returns once its own subscription has the score; this one may get it a moment later.
    seen, score_key = set(), keys.score(stack.run_id)
    while score_key not in seen and (item := inbox.recv(timeout_s=30.0)) is not None:
        seen |= {item.key, *(other.key for other in inbox.drain())}
    for key in seen:
        (owner,) = graph.publishers_of(key)  # exactly one row publishes each key
        assert _put_allowed(owner.name, key), f"{owner.name} puts {key}, which its access rules do not allow"
        assert _put_allowed("replay", key), key
    # Every key the driving rows say they publish was on the bus: the rows are not wider than what runs.
    templates = {t for row in graph.ROLES if row.local_stack or row.name == "brain" for t in row.publishes}
    assert {t for t in templates if any(graph.key_matches(graph.wildcard(t), key) for key in seen)} == templates
