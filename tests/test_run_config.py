"""A run folder's config.yaml is written and read through one struct (issue 41): what ``drivebench run`` writes,
``drivebench run --config`` reads back as the same episode and the same brain launches."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import msgspec
import yaml

from orchestrator.cli.run import run_from_config
from orchestrator.matrix.executor import read_episode_config, write_episode_config
from orchestrator.matrix.load import parse_matrix
from orchestrator.matrix.plan import BrainEntry, EpisodeConfig
from orchestrator.stack.launcher import BrainLaunch
from orchestrator.stack.run_folder import LaunchedBrain, RunConfig, write_run_config
from protocol.episode_spec import CameraSpec, EpisodeSpec


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


# What main wrote for this episode before EpisodeConfig (an ad-hoc dict dumped by the executor): the struct writes the
# same bytes, so episode folders of earlier matrices and of this one read alike.
EPISODE_CONFIG_SAMPLE = """\
run_id: m0001-abcdef
matrix: sample
key: slow/simple/default/salt_pepper=0.4/r0
episode:
  circuit: simple
  laps: 1
  max_sim_seconds: 3.0
  step_s: 0.05
  seed: 7
  realtime: false
  camera: {width_px: 96, height_px: 72, hfov_rad: 1.57, forward_m: 0.45, lateral_offset_m: 0.0,
    height_m: 0.1, pitch_down_rad: 0.0, yaw_rad: 0.0, near_m: 0.1, far_m: 15.0}
  active_brain: slow
  brain_timeout_s: 10.0
  world: {line: red, road: grey, walls: true, lighting: sun, look: flat}
  noise:
  - {model: salt_pepper, probability: 0.4}
  direction: forward
  renderer: auto
  start_m: 0.0
brains:
- label: slow
  brain: constant
  weights: null
  options: {speed_mps: 1.5, scale: 1.0e-07}
- label: constant
  brain: constant
  weights: null
  options: {speed_mps: 2}
- label: neural-s3
  brain: neural
  weights: /w/ckpt.pt
  options: {k: 1}
  group: neural
  training_seed: 3
"""


def test_a_matrix_episodes_config_yaml_is_written_and_read_through_one_struct(tmp_path):
    """A matrix episode's config.yaml was an ad-hoc dict (issue 41): it is an EpisodeConfig now, written with the
    same bytes as before and read back as the same episode and brains (a training run's group and seed included)."""
    matrix = parse_matrix("""\
name: sample
brains: [explicit, {name: constant, label: slow, options: {speed_mps: 1.5, scale: 1.0e-7}}]
shadows: [{name: constant, options: {speed_mps: 2}}]
circuits: [simple]
seed: 7
limits: {laps: 1, max_sim_seconds: 3}
camera: 96x72
perturbations: [none, {salt_pepper: 0.4}]
""")
    trained = BrainEntry(
        label="neural-s3", brain="neural", weights=Path("/w/ckpt.pt"), options=(("k", 1),), group="neural",
        training_seed=3,
    )  # fmt: skip
    matrix = dataclasses.replace(matrix, shadows=(*matrix.shadows, trained))
    episode = matrix.episodes[-1]
    config = EpisodeConfig.of(episode, matrix=matrix, run_id="m0001-abcdef")
    path = write_episode_config(tmp_path, config)
    assert path.read_text() == EPISODE_CONFIG_SAMPLE
    again = read_episode_config(path)
    assert again == config
    assert again.episode == episode.spec
    assert [record.entry() for record in again.brains] == [episode.brain, *matrix.shadows]
