"""Names with letters beyond ASCII (a brain label ``élève``): accepted where names are checked, and carried end to
end (real processes, real Zenoh keys, a real MCAP recording read back)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from protocol import keys
from protocol.mapping import topics
from recorder.reading import read_messages, recording_info

MATRIX = "name: unicode\nbrains: [{name: explicit, label: élève}]\ncircuits: [simple]\n"
SHORT = "limits: {laps: 1, max_sim_seconds: 2}\ncamera: 96x72\n"


def drivebench(*argv: str | Path, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *map(str, argv)], capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.parametrize("name", ["élève", "Ωmega_2", "número.3-b"])
def test_unicode_letters_make_names_and_stable_topics(name):
    assert keys.check_name(name, what="brain label") == name
    key = keys.command("r1", name)
    assert topics.topic_of_key(key) == f"/brain/{name}/cmd" and topics.is_stable_topic(f"/brain/{name}/cmd")


@pytest.mark.parametrize("name", ["a b", "a/b", "a*", "é$", "x\n", ""])
def test_what_a_key_chunk_cannot_hold_is_still_refused(name):
    with pytest.raises(ValueError, match="may only contain letters"):
        keys.check_name(name, what="brain label")


def test_a_matrix_plans_a_unicode_label(tmp_path):
    (tmp_path / "m.yaml").write_text(MATRIX)
    result = drivebench("matrix", tmp_path / "m.yaml", "--plan")
    assert result.returncode == 0, result.stderr
    assert "élève/simple" in result.stdout


@pytest.mark.integration
def test_a_brain_labelled_eleve_drives_and_is_recorded(tmp_path):
    (tmp_path / "m.yaml").write_text(MATRIX + SHORT)
    result = drivebench("matrix", tmp_path / "m.yaml", "-o", tmp_path / "out", "--no-report", "--record")
    assert result.returncode == 0, result.stderr
    [episode] = sorted((tmp_path / "out" / "episodes").iterdir())
    score = json.loads((episode / "score.json").read_text())
    assert score["brain"] == "élève" and score["metrics"]["steps"] == 40  # 2 s at 20 Hz: every step answered
    [recording] = sorted(episode.glob("*.mcap"))
    channels = {c.topic: c.messages for c in recording_info(recording).channels}
    assert channels["/brain/élève/cmd"] >= 40
    commands = [r.message for r in read_messages(recording) if r.key.endswith("/brain/élève/cmd")]
    assert len(commands) == channels["/brain/élève/cmd"] and {c.brain for c in commands} == {"élève"}
