"""Matrix files: expansion, labels, keys, seeds, exclude / include, and one-line errors at the right line."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
import yaml

from orchestrator.matrix.load import BrainEntry, Matrix, MatrixError, load_matrix, parse_matrix, part_of
from protocol.episode_spec import Gaussian, Occlusion, SaltPepper

EXAMPLE = """\
name: generalization
brains: [explicit, {name: constant, label: slow, options: {speed_mps: 1.5}}]
circuits: [simple, montmelo, montreal]
variations: {line: [red, white, none], road: [grey, white], walls: [on, off]}
perturbations: [none, {salt_pepper: 0.2}, {camera: left}, "gaussian=10", {salt_pepper: 0.2, camera: left}]
repetitions: 3
limits: {laps: 2, max_sim_seconds: 120, brain_timeout_s: 5}
camera: 160x120
seed: 7
realtime: false
shadows: [{name: constant, options: {speed_mps: 2}}]
"""

MINIMAL = "brains: [explicit]\ncircuits: [simple]\n"


def parse(text: str, **options) -> Matrix:
    return parse_matrix(textwrap.dedent(text), **options)


# -- expansion ---------------------------------------------------------------------------------------------------


def test_example_expands_to_the_full_product_in_order():
    matrix = parse(EXAMPLE)
    assert matrix.name == "generalization"
    assert matrix.variation_keys == ("line", "road", "walls")
    assert len(matrix.episodes) == 2 * 3 * (3 * 2 * 2) * 5 * 3
    assert [episode.index for episode in matrix.episodes] == list(range(len(matrix.episodes)))
    first = [episode.key for episode in matrix.episodes[:7]]
    assert first == [
        "explicit/simple/line=red,road=grey,walls=on/none/r0",
        "explicit/simple/line=red,road=grey,walls=on/none/r1",
        "explicit/simple/line=red,road=grey,walls=on/none/r2",
        "explicit/simple/line=red,road=grey,walls=on/salt_pepper=0.2/r0",
        "explicit/simple/line=red,road=grey,walls=on/salt_pepper=0.2/r1",
        "explicit/simple/line=red,road=grey,walls=on/salt_pepper=0.2/r2",
        "explicit/simple/line=red,road=grey,walls=on/camera=left/r0",
    ]
    assert matrix.episodes[-1].key == "slow/montreal/line=none,road=white,walls=off/salt_pepper=0.2+camera=left/r2"
    assert len({episode.key for episode in matrix.episodes}) == len(matrix.episodes)


def test_axes_vary_brain_slowest_then_circuit_variation_perturbation_repetition():
    episodes = parse(EXAMPLE).episodes
    per_brain = len(episodes) // 2
    assert {episode.brain.label for episode in episodes[:per_brain]} == {"explicit"}
    assert [episode.circuit for episode in episodes[: per_brain : per_brain // 3]] == ["simple", "montmelo", "montreal"]
    assert [episode.variation for episode in episodes[: 5 * 3 * 2 : 5 * 3]] == [
        "line=red,road=grey,walls=on",
        "line=red,road=grey,walls=off",
    ]
    assert [episode.perturbation for episode in episodes[:15:3]] == [
        "none",
        "salt_pepper=0.2",
        "camera=left",
        "gaussian=10",
        "salt_pepper=0.2+camera=left",
    ]


def test_episode_specs_carry_limits_camera_seed_world_noise_and_label():
    episodes = {episode.key: episode for episode in parse(EXAMPLE).episodes}
    episode = episodes["slow/montmelo/line=white,road=white,walls=off/salt_pepper=0.2+camera=left/r1"]
    spec = episode.spec
    assert (spec.circuit, spec.laps, spec.max_sim_seconds, spec.brain_timeout_s) == ("montmelo", 2, 120.0, 5.0)
    assert (spec.camera.width_px, spec.camera.height_px) == (160, 120)
    assert spec.camera.lateral_offset_m == pytest.approx(0.20)
    assert (spec.world.line, spec.world.road, spec.world.walls) == ("white", "white", False)
    assert spec.noise == [SaltPepper(probability=0.2)]
    assert spec.active_brain == "slow" and spec.realtime is False
    assert (episode.brain.brain, episode.repetition, spec.seed) == ("constant", 1, 8)


def test_every_brain_sees_the_same_seed_in_a_repetition():
    episodes = parse(EXAMPLE).episodes
    for repetition in range(3):
        seeds = {episode.spec.seed for episode in episodes if episode.repetition == repetition}
        assert seeds == {7 + repetition}


def test_defaults_of_a_minimal_matrix():
    matrix = parse(MINIMAL, source="runs/smoke.yaml")
    assert matrix.name == "smoke" and matrix.source == "runs/smoke.yaml" and matrix.text == MINIMAL
    assert matrix.variation_keys == () and matrix.shadows == ()
    (episode,) = matrix.episodes
    assert episode.key == "explicit/simple/default/none/r0"
    assert (episode.variation, episode.perturbation, episode.repetition) == ("default", "none", 0)
    assert episode.spec.seed == 0 and episode.spec.noise == [] and episode.spec.realtime is False
    assert episode.spec.world.walls is True and episode.spec.camera.lateral_offset_m == 0.0


def test_single_items_stand_for_lists_and_random_circuits_are_accepted():
    matrix = parse("brains: explicit\ncircuits: random:42\nvariations: {walls: off}\nperturbations: gaussian=5\n")
    assert [episode.key for episode in matrix.episodes] == ["explicit/random:42/walls=off/gaussian=5/r0"]


def test_same_text_gives_same_keys_and_specs():
    first, second = parse(EXAMPLE), parse(EXAMPLE)
    assert [episode.key for episode in first.episodes] == [episode.key for episode in second.episodes]
    assert [episode.spec for episode in first.episodes] == [episode.spec for episode in second.episodes]


# -- labels --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("written", "label"),
    [
        ("none", "none"),
        ("null", "none"),
        ("{salt_pepper: 0.2}", "salt_pepper=0.2"),
        ('"salt_pepper=0.2"', "salt_pepper=0.2"),
        ("gaussian=10", "gaussian=10"),
        ("{gaussian: 10}", "gaussian=10"),
        ("{salt_pepper: 0.2, camera: left}", "salt_pepper=0.2+camera=left"),
        ('"salt_pepper=0.2+camera=left"', "salt_pepper=0.2+camera=left"),
        ("{occlusion: {patches: 2, size_fraction: 0.3}}", "occlusion:patches=2,size_fraction=0.3"),
        ('"occlusion:patches=2,size_fraction=0.3"', "occlusion:patches=2,size_fraction=0.3"),
        ("{camera_offset_m: 0.1, delay: 2}", "camera_offset_m=0.1+delay=2"),
        ("brightness=+0.2", "brightness=0.2"),
    ],
)
def test_perturbation_labels(written, label):
    (episode,) = parse(f"{MINIMAL}perturbations: [{written}]\n").episodes
    assert episode.perturbation == label
    assert episode.key == f"explicit/simple/default/{label}/r0"


def test_noise_stages_apply_in_written_order():
    text = f"{MINIMAL}perturbations: [{{gaussian: 10, occlusion: {{patches: 3}}, salt_pepper: 0.4}}]\n"
    (episode,) = parse(text).episodes
    assert episode.spec.noise == [Gaussian(sigma=10), Occlusion(patches=3), SaltPepper(probability=0.4)]


def test_variation_labels_keep_written_key_order_and_print_booleans_as_on_off():
    text = f"{MINIMAL}variations: {{walls: [off, true], camera_yaw_rad: [0.1], lighting: [no_sun]}}\n"
    labels = [episode.variation for episode in parse(text).episodes]
    assert labels == ["walls=off,camera_yaw_rad=0.1,lighting=no_sun", "walls=on,camera_yaw_rad=0.1,lighting=no_sun"]
    assert parse(text).episodes[0].spec.camera.yaw_rad == pytest.approx(0.1)


def test_brain_label_defaults():
    (explicit, constant) = parse(EXAMPLE).brains
    assert explicit == BrainEntry(label="explicit", brain="explicit")
    assert constant == BrainEntry(label="slow", brain="constant", options=(("speed_mps", 1.5),))
    (shadow,) = parse(EXAMPLE).shadows
    assert shadow.label == "constant" and shadow.options == (("speed_mps", 2),)


# -- weights and launch options --------------------------------------------------------------------------------------


@pytest.fixture
def weights_matrix(tmp_path) -> Path:
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "memdccp_v1.ckpt").write_bytes(b"not really a checkpoint")
    path = tmp_path / "experiments" / "m.yaml"
    path.parent.mkdir()
    path.write_text(
        "brains: [{name: memdccp, weights: ../runs/memdccp_v1.ckpt, options: {threads: 1, scale: 1.0e-7,"
        " mode: 'on'}}]\ncircuits: [simple]\n"
    )
    return path


def test_weights_resolve_from_the_matrix_folder_whatever_the_working_folder(weights_matrix, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path / "runs")
    matrix = load_matrix(weights_matrix)
    (brain,) = matrix.brains
    assert brain.weights == (tmp_path / "runs" / "memdccp_v1.ckpt").resolve()
    assert brain.label == "memdccp-memdccp_v1" == matrix.episodes[0].spec.active_brain
    assert matrix.name == "m" and matrix.source == str(weights_matrix)


def test_launch_options_and_to_dict_round_trip(weights_matrix):
    (brain,) = load_matrix(weights_matrix).brains
    options = brain.launch_options()
    assert options[-1] == f"weights={json.dumps(str(brain.weights))}"
    read_back = {text.partition("=")[0]: yaml.safe_load(text.partition("=")[2]) for text in options}
    assert read_back == {"threads": 1, "scale": 1e-7, "mode": "on", "weights": str(brain.weights)}
    assert json.loads(json.dumps(brain.to_dict())) == {
        "label": "memdccp-memdccp_v1",
        "brain": "memdccp",
        "weights": str(brain.weights),
        "options": {"threads": 1, "scale": 1e-7, "mode": "on"},
    }


# -- exclude and include -------------------------------------------------------------------------------------------


def test_exclude_drops_combinations_matching_all_keys():
    text = EXAMPLE + textwrap.dedent("""\
        exclude:
          - {brain: explicit, line: none}
          - {circuit: montreal, perturbation: {camera: left}}
          - {walls: off, perturbation: "salt_pepper=0.2+camera=left", repetition: 2}
        """)
    episodes = parse(text).episodes
    keys = {episode.key for episode in episodes}
    assert not any(key.startswith("explicit/") and "line=none" in key for key in keys)
    assert not any("/montreal/" in key and "/camera=left/" in key for key in keys)
    assert not any("walls=off" in key and key.endswith("/salt_pepper=0.2+camera=left/r2") for key in keys)
    assert "slow/simple/line=none,road=grey,walls=on/none/r0" in keys
    assert "explicit/montreal/line=red,road=grey,walls=on/salt_pepper=0.2+camera=left/r0" in keys
    full = 2 * 3 * 12 * 5 * 3
    first = 1 * 3 * 4 * 5 * 3
    second = 2 * 1 * 12 * 1 * 3 - 1 * 1 * 4 * 1 * 3
    third = 2 * 3 * 6 * 1 * 1 - 1 * 3 * 2 * 1 * 1  # less those the first exclude took already
    assert len(episodes) == full - first - second - third


def test_include_adds_combinations_over_repetitions_at_the_end_without_duplicates():
    text = EXAMPLE + textwrap.dedent("""\
        exclude: [{brain: explicit, line: none}]
        include:
          - {brain: explicit, circuit: monaco}
          - {brain: slow, circuit: simple, walls: on, line: red, road: grey}
          - {brain: explicit, circuit: simple, road: grey, line: none, walls: off, perturbation: {gaussian: 10}}
          - {brain: explicit, circuit: simple, lighting: no_sun, line: white, perturbation: "delay=2"}
        """)
    matrix = parse(text)
    excluded = 2 * 3 * 12 * 5 * 3 - 1 * 3 * 4 * 5 * 3
    added = [episode.key for episode in matrix.episodes[excluded:]]
    assert added == [
        "explicit/monaco/default/none/r0",
        "explicit/monaco/default/none/r1",
        "explicit/monaco/default/none/r2",
        # the second include is already in the product: not repeated
        "explicit/simple/line=none,road=grey,walls=off/gaussian=10/r0",
        "explicit/simple/line=none,road=grey,walls=off/gaussian=10/r1",
        "explicit/simple/line=none,road=grey,walls=off/gaussian=10/r2",
        "explicit/simple/line=white,lighting=no_sun/delay=2/r0",
        "explicit/simple/line=white,lighting=no_sun/delay=2/r1",
        "explicit/simple/line=white,lighting=no_sun/delay=2/r2",
    ]
    monaco = matrix.episodes[excluded]
    assert monaco.spec.world.line == "red" and monaco.spec.noise == [] and monaco.spec.seed == 7
    last = matrix.episodes[-1].spec
    assert (last.world.line, last.world.lighting, last.world.walls, last.seed) == ("white", "no_sun", True, 9)


def test_worlds_list_the_worlds_one_by_one_and_exclude_names_their_values():
    matrix = parse(
        MINIMAL
        + textwrap.dedent("""\
        worlds:
          - {line: red, road: grey, walls: on}
          - {line: none, walls: off}
          - {line: red, direction: reverse}
        exclude: [{line: none}]
    """)
    )
    assert [episode.variation for episode in matrix.episodes] == [
        "line=red,road=grey,walls=on",
        "line=red,direction=reverse",
    ]
    assert matrix.variation_keys == ("line", "road", "walls", "direction")
    assert [episode.spec.direction for episode in matrix.episodes] == ["forward", "reverse"]


def test_start_m_is_a_route_variation_like_direction():
    matrix = parse(
        textwrap.dedent("""\
        brains: [explicit]
        circuits: [simple, montreal]
        variations: {start_m: [0, 120.5], direction: [forward, reverse]}
        include: [{brain: explicit, circuit: montreal, start_m: 1000}]
    """)
    )
    assert matrix.variation_keys == ("start_m", "direction")
    starts = [(episode.circuit, episode.spec.start_m, episode.spec.direction) for episode in matrix.episodes]
    assert starts == [
        (circuit, start_m, direction)
        for circuit in ("simple", "montreal")
        for start_m in (0.0, 120.5)
        for direction in ("forward", "reverse")
    ] + [("montreal", 1000.0, "forward")]  # montreal is 1433 m long
    assert matrix.episodes[2].key == "explicit/simple/start_m=120.5,direction=forward/none/r0"


def test_parts_expand_in_order_over_the_same_brains_with_their_own_axes():
    matrix = parse("""\
        brains: [explicit, {name: constant, label: slow}]
        circuits: [simple]
        limits: {laps: 1, max_sim_seconds: 100}
        seed: 4
        parts:
          laps: {circuits: [montmelo], repetitions: 2}
          worlds: {worlds: [{line: white}, {direction: reverse}], limits: {max_sim_seconds: 50}}
          noise: {perturbations: [{salt_pepper: 0.4}]}
    """)
    assert matrix.parts == ("laps", "worlds", "noise")
    keys = [episode.key for episode in matrix.episodes]
    assert keys == [
        "laps:explicit/montmelo/default/none/r0",
        "laps:explicit/montmelo/default/none/r1",
        "laps:slow/montmelo/default/none/r0",
        "laps:slow/montmelo/default/none/r1",
        "worlds:explicit/simple/line=white/none/r0",
        "worlds:explicit/simple/direction=reverse/none/r0",
        "worlds:slow/simple/line=white/none/r0",
        "worlds:slow/simple/direction=reverse/none/r0",
        "noise:explicit/simple/default/salt_pepper=0.4/r0",
        "noise:slow/simple/default/salt_pepper=0.4/r0",
    ]
    assert [episode.index for episode in matrix.episodes] == list(range(10))
    assert [part_of(key) for key in keys] == ["laps"] * 4 + ["worlds"] * 4 + ["noise"] * 2
    assert [episode.part for episode in matrix.episodes] == [part_of(key) for key in keys]
    assert {episode.spec.max_sim_seconds for episode in matrix.episodes if episode.part == "worlds"} == {50}
    assert {episode.spec.max_sim_seconds for episode in matrix.episodes if episode.part != "worlds"} == {100}
    assert {episode.spec.seed for episode in matrix.episodes} == {4, 5}
    assert part_of("explicit/simple/default/occlusion:patches=2/r0") == ""


# -- errors --------------------------------------------------------------------------------------------------------


ERRORS = [
    # (matrix text, line, words the message must contain)
    ("brains: [explicit\ncircuits: [simple]\n", 2, ["invalid YAML"]),
    ("- explicit\n- simple\n", 1, ["top level must be a mapping", "brains"]),
    (MINIMAL + "repetitons: 2\n", 3, ["'repetitons'", "allowed", "repetitions"]),
    (MINIMAL + "brains: [constant]\n", 3, ["duplicate key 'brains'", "line 1"]),
    (MINIMAL + "limits: {laps: 1, laps: 2}\n", 3, ["duplicate key 'laps'"]),
    ("circuits: [simple]\n", 1, ["missing 'brains'"]),
    ("brains: [explicit]\n", 1, ["missing 'circuits'"]),
    ("brains: []\ncircuits: [simple]\n", 1, ["brains", "empty"]),
    ("brains: [explicit]\ncircuits:\n", 2, ["circuits", "empty"]),
    ("brains:\n  - explicit\n  - warpdrive\ncircuits: [simple]\n", 3, ["'warpdrive'", "known:", "explicit"]),
    ("brains: [{label: x}]\ncircuits: [simple]\n", 1, ["brains[0] is missing 'name'"]),
    ("brains: [{name: explicit, weight: a.ckpt}]\ncircuits: [simple]\n", 1, ["'weight'", "weights"]),
    (
        "brains: [explicit]\ncircuits:\n  - simple\n  - nowhere\n",
        4,
        ["'nowhere'", "montmelo", "drivebench circuits list"],
    ),
    ("brains: [explicit]\ncircuits: [simple, simple]\n", 2, ["'simple'", "twice"]),
    (MINIMAL + "variations:\n  colour: [red]\n", 4, ["'colour'", "allowed", "line"]),
    (MINIMAL + "variations:\n  line: [red, blue]\n", 4, ["'blue'", "red, white, none"]),
    (MINIMAL + "variations:\n  walls: [on, maybe]\n", 4, ["'maybe'", "on or off"]),
    (MINIMAL + "variations:\n  camera: [left, upside]\n", 4, ["'upside'", "rotate_down"]),
    (MINIMAL + "variations:\n  line: []\n", 4, ["line", "empty"]),
    (MINIMAL + "perturbations:\n  - none\n  - {hail: 0.1}\n", 5, ["'hail'", "salt_pepper", "camera"]),
    (MINIMAL + "perturbations:\n  - salt_pepper=2\n", 4, ["salt_pepper", "0..1"]),
    (MINIMAL + "perturbations:\n  - {occlusion: {patches: 2, colour: red}}\n", 4, ["occlusion", "colour"]),
    (MINIMAL + "perturbations:\n  - {camera: upside}\n", 4, ["'upside'", "known"]),
    (MINIMAL + "perturbations:\n  - line=white\n", 4, ["'line'", "noise models"]),
    (MINIMAL + "perturbations:\n  - 3\n", 4, ["perturbation", "3"]),
    (MINIMAL + "perturbations:\n  - gaussian=10\n  - {gaussian: 10}\n", 5, ["'gaussian=10'", "twice", "line 4"]),
    (MINIMAL + "limits:\n  laps: 0\n", 4, ["laps", ">= 1", "0"]),
    (MINIMAL + "limits:\n  laps: 1.5\n", 4, ["limits.laps must be an integer, got 1.5"]),
    (MINIMAL + "limits:\n  max_sim_seconds: -3\n", 4, ["max_sim_seconds", "-3"]),
    (MINIMAL + "limits:\n  lap: 1\n", 4, ["'lap'", "laps"]),
    (MINIMAL + "limits: 3\n", 3, ["limits", "mapping"]),
    (MINIMAL + "camera: 320by240\n", 3, ["camera", "320by240", "320x240"]),
    (MINIMAL + "camera: 4x240\n", 3, ["width_px must be within 8..4096, got 4"]),
    (MINIMAL + "camera:\n  width_px: 320\n  height_px: tall\n", 5, ["camera.height_px", "integer", "'tall'"]),
    (MINIMAL + "camera:\n  depth_px: 3\n", 4, ["'depth_px'", "width_px"]),
    (MINIMAL + "seed: -1\n", 3, ["seed", ">= 0", "-1"]),
    (MINIMAL + "seed: seven\n", 3, ["seed", "'seven'"]),
    (MINIMAL + "repetitions: 0\n", 3, ["repetitions", ">= 1", "0"]),
    (MINIMAL + "repetitions: 1000000\n", 3, ["1000000", "at most"]),
    (MINIMAL + "realtime: maybe\n", 3, ["realtime must be true or false, got 'maybe'"]),
    (MINIMAL + "name: [a]\n", 3, ["name must be text, got a list"]),
    (MINIMAL + 'name: "x/../../../escaped"\n', 3, ["matrix name 'x/../../../escaped'", "letters, digits"]),
    ("brains:\n  - {name: memdccp, weights: missing.ckpt}\ncircuits: [simple]\n", 2, ["'missing.ckpt'", "not found"]),
    ("brains:\n  - explicit\n  - explicit\ncircuits: [simple]\n", 3, ["duplicate brain label 'explicit'", "line 2"]),
    (MINIMAL + "shadows:\n  - explicit\n", 4, ["duplicate brain label 'explicit'", "line 1"]),
    ("brains: [{name: explicit, label: my brain}]\ncircuits: [simple]\n", 1, ["'my brain'", "letters, digits"]),
    ("brains: [{name: explicit, options: {weights: a}}]\ncircuits: [simple]\n", 1, ["weights"]),
    ("brains: [{name: explicit, options: [1]}]\ncircuits: [simple]\n", 1, ["options", "mapping"]),
    (MINIMAL + "exclude:\n  - {colour: red}\n", 4, ["'colour'", "brain, circuit, repetition, perturbation"]),
    (MINIMAL + "exclude:\n  - {line: red}\n", 4, ["'line'", "not a variation axis"]),
    (MINIMAL + "variations: {camera_yaw_rad: [.nan]}\n", 3, ["camera_yaw_rad", "finite", "nan"]),
    (MINIMAL + "seed: 1\x07\n", 3, ["invalid YAML", "#x0007"]),
    (MINIMAL + "exclude:\n  - {circuit: montmelo}\n", 4, ["'montmelo'", "known: simple"]),
    (MINIMAL + "exclude:\n  - {brain: explicit, repetition: 3}\n", 4, ["repetition", "'3'", "known: 0"]),
    (MINIMAL + "variations: {line: [red]}\nworlds: [{line: red}]\n", 4, ["variations", "worlds", "not both"]),
    (MINIMAL + "worlds:\n  - {line: red}\n  - {fog: 1}\n", 5, ["'fog'", "allowed"]),
    (MINIMAL + "worlds:\n  - {line: red}\n  - {line: red}\n", 5, ["'line=red'", "twice", "line 4"]),
    (MINIMAL + "worlds:\n  - {direction: backwards}\n", 4, ["'backwards'", "forward, reverse"]),
    (MINIMAL + "variations:\n  start_m: [0, -5]\n", 4, ["bad start_m value -5", ">= 0"]),
    (MINIMAL + "worlds:\n  - {start_m: far}\n", 4, ["start_m must be a number, got 'far'"]),
    (
        "brains: [explicit]\ncircuits: [montreal, simple]\nvariations:\n  start_m:\n    - 100\n    - 500\n",
        6,
        ["start_m must be >= 0 and below 442.836 m, the length of circuit 'simple', got 500"],
    ),
    (
        MINIMAL + "include:\n  - {brain: explicit, circuit: simple, start_m: 443}\n",
        4,
        ["below 442.836 m, the length of circuit 'simple', got 443"],
    ),
    ("brains: [explicit]\nparts:\n  a: {repetitions: 2}\n", 3, ["part 'a' has no circuits"]),
    (MINIMAL + "parts:\n  a: {seed: 2}\n", 4, ["'seed'", "allowed", "circuits"]),
    (MINIMAL + "parts:\n  a b: {circuits: [simple]}\n", 4, ["'a b'", "letters, digits"]),
    (MINIMAL + "parts: {}\n", 3, ["parts is empty"]),
    (MINIMAL + "parts:\n  a:\n    exclude: [{brain: explicit}]\n", 5, ["part 'a' expands to no episodes"]),
    (MINIMAL + "exclude:\n  - {perturbation: gaussian=3}\n", 4, ["'gaussian=3'", "known: none"]),
    (MINIMAL + "exclude:\n  - {}\n", 4, ["empty exclude"]),
    (MINIMAL + "exclude:\n  - {brain: explicit}\n", 3, ["no episodes", "excluded"]),
    (MINIMAL + "include:\n  - {brain: explicit}\n", 4, ["include", "brain and circuit"]),
    (MINIMAL + "include:\n  - {brain: constant, circuit: simple}\n", 4, ["'constant'", "labels: explicit"]),
    (MINIMAL + "include:\n  - {brain: explicit, circuit: nowhere}\n", 4, ["'nowhere'", "drivebench circuits list"]),
    (MINIMAL + "include:\n  - {brain: explicit, circuit: simple, repetition: 1}\n", 4, ["'repetition'"]),
    (MINIMAL + "include:\n  - {brain: explicit, circuit: simple, line: blue}\n", 4, ["'blue'"]),
    (MINIMAL + "seed: !!python/object:os.system ls\n", 3, ["cannot read"]),
]


@pytest.mark.parametrize(("text", "line", "words"), ERRORS, ids=[f"{i}" for i in range(len(ERRORS))])
def test_mistakes_name_the_line_and_the_value(text, line, words):
    with pytest.raises(MatrixError) as caught:
        parse_matrix(text, source="m.yaml")
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"m.yaml:{line}: "), message
    assert caught.value.line == line
    for word in words:
        assert word in message, message


def test_missing_file_is_named(tmp_path):
    with pytest.raises(MatrixError, match="nothing.yaml: cannot read the matrix file"):
        load_matrix(tmp_path / "nothing.yaml")


def test_matrix_error_is_a_value_error():
    assert issubclass(MatrixError, ValueError)


SEVERAL_MISTAKES = """\
brains: [explicit, warpdrive]
camera: 320by240
parts:
  generalisation:
    circuits: [simple, montmelo, montmelp]
    variations: {line: [red, blue]}
  noise:
    circuits: [simple]
    perturbations: [none, {hail: 0.1}]
"""


def test_every_independent_mistake_is_reported_at_once_in_line_order():
    with pytest.raises(MatrixError) as caught:
        parse_matrix(SEVERAL_MISTAKES, source="m.yaml")
    lines = str(caught.value).splitlines()
    # (line, words): camera is read for each part and reported once
    expected = [
        (1, ["unknown brain 'warpdrive'"]),
        (2, ["camera must look like 320x240", "'320by240'"]),
        (5, ["unknown circuit 'montmelp'", "did you mean 'montmelo'?"]),
        (6, ["bad line value 'blue'"]),
        (9, ["unknown perturbation 'hail'"]),
    ]
    assert len(lines) == len(expected), lines
    for text, (line, words) in zip(lines, expected):
        assert text.startswith(f"m.yaml:{line}: "), text
        assert all(word in text for word in words), text
    assert (caught.value.line, caught.value.message) == (1, lines[0].removeprefix("m.yaml:1: "))


FOLLOW_ONS = [
    # (matrix text, the lines of its mistakes): each wrong value could also fail a check that depends on it
    (MINIMAL + "exclude: [{brain: explicit}]\nvariations: {colour: [red]}\n", [4]),  # not "no episodes left"
    ("brains: [explicit]\ncircuits: [simple, nowhere]\nexclude: [{circuit: nowhere}]\nrepetitions: 2\n", [2]),
    ("brains: [explicit, nobody]\ncircuits: [simple, nowhere]\nexclude: [{brain: nobody}]\n", [1, 2]),
    (MINIMAL + "worlds:\n  - {line: red, walls: maybe}\n  - {line: red}\n  - {fog: 1}\n", [4, 6]),
    (MINIMAL + "variations: {colour: [red, red], line: [blue]}\n", [3, 3]),  # not "red listed twice"
    (MINIMAL + "perturbations: [{hail: 1}, none, {hail: 1}]\n", [3]),
    ("brains: [explicit]\ndraw: {count: 3, circuits: [nowhere, simple]}\nparts: {a: {}, b: {}}\n", [2]),
]


@pytest.mark.parametrize(("text", "lines"), FOLLOW_ONS, ids=[f"{i}" for i in range(len(FOLLOW_ONS))])
def test_a_wrong_value_is_reported_without_the_mistakes_that_follow_from_it(text, lines):
    with pytest.raises(MatrixError) as caught:
        parse_matrix(text, source="m.yaml")
    reported = str(caught.value).splitlines()
    assert [int(line.split(":")[1]) for line in reported] == lines, reported


def test_past_ten_mistakes_the_rest_are_counted():
    text = "brains: [explicit]\ncircuits:\n" + "".join(f"  - nowhere{index}\n" for index in range(14))
    with pytest.raises(MatrixError) as caught:
        parse_matrix(text, source="m.yaml")
    lines = str(caught.value).splitlines()
    assert [line.split(":")[1] for line in lines[:10]] == [str(line) for line in range(3, 13)]
    assert lines[10:] == ["m.yaml: ... and 4 more mistakes"]


# -- resume against stored results -----------------------------------------------------------------------------------


def _stored(matrix: Matrix, *, keys: set[str] | None = None) -> list:
    from orchestrator.matrix.results import EpisodeResult

    return [
        EpisodeResult.of(episode, status="done", run_id=f"r{episode.index}", started_at=0.0, ended_at=1.0)
        for episode in matrix.episodes
        if keys is None or episode.key in keys
    ]


def test_resume_keeps_finished_episodes_at_their_index_and_new_ones_take_the_free_ones():
    from orchestrator.matrix.resume import fit_to_results

    before = parse_matrix(EXAMPLE)
    grown = parse_matrix(EXAMPLE.replace("repetitions: 3", "repetitions: 4"))
    done = _stored(before, keys={episode.key for episode in before.episodes[:50]})
    resumed = fit_to_results(grown, done, shadows=None, planned_before=[e.key for e in before.episodes], where="out")
    indices = {episode.key: episode.index for episode in resumed.matrix.episodes}
    assert all(indices[result.key] == result.index for result in done)  # their folders stay theirs
    assert sorted(indices.values()) == list(range(len(grown.episodes)))  # every index once
    assert [e.key for e in resumed.matrix.episodes] == [e.key for e in grown.episodes]  # expansion order kept
    assert (resumed.kept, resumed.added) == (50, len(grown.episodes) - len(before.episodes))
    assert resumed.note() == f"the matrix file adds episodes: 50 finished episode(s) kept, {resumed.added} new"
    same = fit_to_results(before, done, shadows=None, planned_before=[e.key for e in before.episodes], where="out")
    assert same.matrix == before and same.note() is None


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (("max_sim_seconds: 120", "max_sim_seconds: 60"), "max_sim_seconds 120.0 -> 60.0"),
        (("seed: 7", "seed: 8"), "seed 7 -> 8"),
        (("camera: 160x120", "camera: 320x240"), "camera.width_px 160 -> 320"),
        (("circuits: [simple, montmelo, montreal]", "circuits: [simple, montmelo]"), "circuits removed: montreal"),
        (("label: slow, options: {speed_mps: 1.5}", "label: slow, options: {speed_mps: 2}"), "brain 'slow' options"),
        (("shadows: [{name: constant, options: {speed_mps: 2}}]", "shadows: []\n"), "shadows [constant] -> []"),
    ],
)
def test_resume_refuses_a_matrix_that_changed_what_the_results_ran_naming_the_change(change, words):
    from orchestrator.matrix.resume import MatrixChangedError, fit_to_results

    before = parse_matrix(EXAMPLE)
    shadows = [shadow.to_dict() for shadow in before.shadows]
    changed = parse_matrix(EXAMPLE.replace(*change).replace("shadows: []\n", ""))
    with pytest.raises(MatrixChangedError) as caught:
        fit_to_results(changed, _stored(before), shadows=shadows, planned_before=None, where="runs/x")
    message = str(caught.value)
    assert message.startswith("runs/x: the matrix file changed since these results (") and words in message, message
    assert "\n" not in message
