"""A run folder's config.yaml is written and read through one struct (issue 41): what ``drivebench run`` writes,
``drivebench run --config`` reads back as the same episode and the same brain launches."""

from __future__ import annotations

from pathlib import Path

import msgspec
import yaml

from orchestrator.cli.run import run_from_config
from orchestrator.matrix.plan import BrainEntry
from orchestrator.stack.launcher import BrainLaunch
from orchestrator.stack.run_folder import LaunchedBrain, RunConfig, write_run_config
from protocol.messages import CameraSpec, EpisodeSpec


def test_config_yaml_reads_back_as_the_episode_and_brains_it_was_written_from(tmp_path):
    spec = EpisodeSpec(circuit="simple", laps=2, seed=7, camera=CameraSpec(width_px=64, height_px=48))
    launches = [
        BrainLaunch("explicit", options=("speed_mps=2.5",), host=("--warm-up-frames", "1")),
        BrainLaunch("explicit", name="shadow-1"),
    ]
    config = RunConfig(run_id="ab12", episode=spec, brains=[LaunchedBrain.of(launch) for launch in launches])
    path = write_run_config(tmp_path, config)
    assert set(yaml.safe_load(path.read_text())) == {"run_id", "episode", "brains"}  # as before: no attach keys

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


def test_an_attached_runs_config_yaml_is_the_same_struct(tmp_path):
    """``drivebench run --attach`` wrote its config.yaml from a dict of its own; it is a RunConfig now, read back whole
    (it names the router it joined and launched no brain)."""
    spec = EpisodeSpec(circuit="simple", active_brain="remote", camera=CameraSpec(width_px=64, height_px=48))
    config = RunConfig(run_id="cd34", router="tcp/10.0.0.5:7447", attached=True, episode=spec)
    path = write_run_config(tmp_path, config)
    read = msgspec.convert(yaml.safe_load(path.read_text()), RunConfig)
    assert read == config and read.brains == []
