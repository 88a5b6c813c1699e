"""Stack failures are typed (issue 41): one FailureKind, its role members following the process graph, and no
decision made by reading a message's words."""

from __future__ import annotations

import pytest

from orchestrator.stack.failures import Failure, FailureKind
from protocol.deploy import graph
from protocol.episode_spec import CameraSpec, EpisodeSpec, FieldError


@pytest.mark.parametrize("role", [row for row in graph.ROLES if row.module], ids=lambda row: row.name)
def test_every_role_that_runs_a_process_has_its_own_failure_kind(role):
    kind = FailureKind.died(role.token_role)
    assert kind is not FailureKind.ERROR, f"add {role.token_role.upper()}_DIED to FailureKind (a role of the graph)"
    assert kind == f"{role.token_role}_died"


def test_a_role_the_graph_does_not_have_is_an_error_not_a_guess():
    assert FailureKind.died("lawnmower") is FailureKind.ERROR


def test_a_failure_reads_as_its_kind_then_its_detail():
    failure = Failure(FailureKind.BRAIN_DIED, "brain 'x' exited with code -9; its last log line: a: b")
    assert str(failure) == "brain_died: brain 'x' exited with code -9; its last log line: a: b"
    # Results store kind and detail apart (tests/test_results_schema.py): nothing turns this text back into a record.
    assert not hasattr(Failure, "parse")


@pytest.mark.parametrize(
    ("fields", "field"),
    [
        ({"laps": 0}, "laps"),
        ({"brain_timeout_s": -1.0}, "brain_timeout_s"),
        ({"direction": "sideways"}, "direction"),
        ({"renderer": "crayon"}, "renderer"),
    ],
)
def test_a_spec_out_of_bounds_names_its_field_in_the_error_not_only_in_the_words(fields, field):
    with pytest.raises(FieldError) as error:
        EpisodeSpec(circuit="simple", camera=CameraSpec(width_px=64, height_px=48), **fields)
    assert error.value.field == field
