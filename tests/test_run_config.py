"""A run folder's config.yaml is written and read through one struct (issue 41): what ``drivebench run`` writes,
``drivebench run --config`` reads back as the same episode and the same brain launches."""

from __future__ import annotations

from pathlib import Path

import msgspec
import yaml

from orchestrator.cli.run import run_from_config
from orchestrator.matrix.plan import BrainEntry
from orchestrator.stack.launcher import BrainLaunch
from orchestrator.stack.run_folder import LaunchedBrain, RunConfig
from protocol.messages import CameraSpec, EpisodeSpec


def test_config_yaml_reads_back_as_the_episode_and_brains_it_was_written_from(tmp_path):
    spec = EpisodeSpec(circuit="simple", laps=2, seed=7, camera=CameraSpec(width_px=64, height_px=48))
    launches = [
        BrainLaunch("explicit", options=("speed_mps=2.5",), host=("--warm-up-frames", "1")),
        BrainLaunch("explicit", name="shadow-1"),
    ]
    config = RunConfig(run_id="ab12", episode=spec, brains=[LaunchedBrain.of(launch) for launch in launches])
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False))

    episode, brains = run_from_config(path)

    assert episode == spec
    assert [(b.brain, b.bus_name, b.options, b.host) for b in brains] == [
        (b.brain, b.bus_name, b.options, b.host) for b in launches
    ]


def test_a_matrix_brain_entry_reads_back_from_what_results_store():
    entry = BrainEntry(
        label="tiny-s1",
        brain="neural",
        weights=Path("/w/tiny-s1.ckpt"),
        options=(("speed_mps", 2.0),),
        group="tiny",
        training_seed=1,
    )
    assert BrainEntry.from_dict(entry.to_dict()) == entry
    assert BrainEntry.from_dict(BrainEntry(label="e", brain="explicit").to_dict()) == BrainEntry(
        label="e", brain="explicit"
    )
