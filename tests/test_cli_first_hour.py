"""The CLI as a newcomer meets it: help with no arguments, --version, shell completion, did-you-mean, errors that
name the option typed, --json on the list and inspect commands, every mistake of a matrix file at once, run --config,
and the README's runnable commands run as written."""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from needs import require

ROOT = Path(__file__).resolve().parent.parent
LEGACY_RECORDING = ROOT / "tests" / "fixtures" / "legacy-run-topics.mcap"


def drivebench(*args: str, timeout: float = 120, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", *args], capture_output=True, text=True, timeout=timeout, cwd=cwd
    )


def one_error_line(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2, result
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    return lines[0]


def test_drivebench_alone_prints_the_help_with_every_command():
    result = drivebench()
    assert result.returncode == 0, result.stderr
    for command in ("run", "matrix", "brains", "circuits", "completion", "examples:"):
        assert command in result.stdout
    assert result.stderr == ""


def test_version_is_the_installed_distributions():
    from importlib import metadata

    result = drivebench("--version")
    assert (result.returncode, result.stdout.strip()) == (0, f"drivebench {metadata.version('drivebench')}")


def test_bash_completion_is_valid_bash_that_knows_the_commands_and_options():
    script = drivebench("completion", "bash").stdout
    assert "matrix" in script and "--circuit" in script and "--max-sim-seconds" in script
    bash = shutil.which("bash")
    assert bash is not None
    checked = subprocess.run([bash, "-n"], input=script, capture_output=True, text=True)
    assert checked.returncode == 0, checked.stderr
    zsh = drivebench("completion", "zsh").stdout
    assert zsh.startswith("#compdef drivebench") and "--brain-timeout" in zsh


def bash_completions(script: str, words: list[str], *, cwd: Path) -> list[str]:
    """What bash completes for the last of ``words`` (the command line so far), through the generated script's own
    completion function, in a real bash."""
    bash = shutil.which("bash")
    assert bash is not None
    line = " ".join(shlex.quote(word) for word in words)
    program = (
        f"{script}\nCOMP_WORDS=({line}); COMP_CWORD={len(words) - 1}\n"
        "_shtab_drivebench\nprintf '%s\\n' \"${COMPREPLY[@]}\"\n"
    )
    done = subprocess.run([bash, "-c", program], capture_output=True, text=True, cwd=cwd, timeout=30)
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


def test_bash_completion_completes_circuit_and_brain_names(tmp_path):
    script = drivebench("completion", "bash").stdout
    (tmp_path / "my_bm_brain.py").write_text("class Brain: ...\n")
    assert bash_completions(script, ["drivebench", "run", "--circuit", "mont"], cwd=tmp_path) == [
        "montmelo",
        "montreal",
    ]
    assert bash_completions(script, ["drivebench", "circuits", "show", "nur"], cwd=tmp_path) == ["nurburgring"]
    assert bash_completions(script, ["drivebench", "run", "--brain", "pilot"], cwd=tmp_path) == [
        "pilotnet",
        "pilotnet_x3",
    ]
    assert bash_completions(script, ["drivebench", "brains", "check", "my_bm"], cwd=tmp_path) == ["my_bm_brain.py"]
    assert "explicit" in bash_completions(script, ["drivebench", "swap", "ex"], cwd=tmp_path)
    assert "explicit" in bash_completions(script, ["drivebench", "run", "--shadow", "ex"], cwd=tmp_path)
    zsh = drivebench("completion", "zsh").stdout
    assert "(extended_simple many_curves monaco montmelo" in zsh and "pilotnet pilotnet_x3" in zsh


@pytest.mark.parametrize(
    ("args", "starts", "suggests"),
    [
        (["run", "--circuit", "simpel"], "--circuit simpel: unknown circuit 'simpel'", "did you mean 'simple'?"),
        (["run", "--brain", "explicti"], "--brain explicti: unknown brain 'explicti'", "did you mean 'explicit'?"),
        (["run", "--noise", "salt_peper=0.2"], "--noise salt_peper=0.2: unknown noise model", "'salt_pepper'?"),
        (["run", "--variation", "lien=red"], "--variation lien=red: unknown variation 'lien'", "'line'?"),
        (["run", "--variation", "camera=lefft"], "--variation camera=lefft: unknown camera preset", "'left'?"),
        (["run", "--variation", "line=whte"], "--variation line=whte: line must be one of", "'white'?"),
        (["run", "--variation", "look=gazbo"], "--variation look=gazbo: unknown look 'gazbo'", "'gazebo'?"),
        (["run", "--variation", "direction=revers"], "--variation direction=revers: direction must be", "'reverse'?"),
        (
            [
                "run",
                "--brain",
                "behavior_metrics",
                "--brain-option",
                "file=examples/behavior_metrics/brain_f1_follow_line.py",
                "--brain-option",
                "config={ImageTranform: rainy}",
            ],
            "Behavior Metrics brain 'examples/behavior_metrics/brain_f1_follow_line.py': ",
            "unknown ImageTranform 'rainy' (Behavior Metrics knows '', 'rain', 'night', 'shadow', 'snow', 'fog', "
            "'sunflare', 'daytime', 'affine'); did you mean 'rain'?",
        ),
        (["run", "--camera", "0x0"], "--camera 0x0: width_px must be within 8..4096, got 0", ""),
        (["run", "--laps", "0"], "--laps 0: laps must be >= 1, got 0", ""),
    ],
)
def test_a_bad_option_is_one_line_that_names_it_as_typed_and_suggests_the_closest_name(args, starts, suggests):
    line = one_error_line(drivebench(*args))
    assert line.startswith(f"drivebench: error: {starts}"), line
    assert line.endswith(suggests), line


@pytest.mark.parametrize(
    ("args", "error", "suggests"),
    [
        (["rnu"], "argument COMMAND: invalid choice: 'rnu'", "; did you mean 'run'?"),
        (["brains", "chek", "explicit"], "invalid choice: 'chek'", "; did you mean 'check'?"),
        (["run", "--circut", "simple"], "unrecognized arguments: --circut simple", "; did you mean '--circuit'?"),
        (["matrix", "m.yaml", "--smkoe"], "unrecognized arguments: --smkoe", "; did you mean '--smoke'?"),
    ],
)
def test_a_misspelled_command_or_option_gets_the_closest_name(args, error, suggests):
    result = drivebench(*args)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    last = result.stderr.strip().splitlines()[-1]  # argparse's usage, then its one error line
    assert error in last and last.endswith(suggests), last


def test_a_misspelled_class_of_a_module_path_brain_gets_the_closest_name(tmp_path):
    (tmp_path / "my_driver.py").write_text("class MyDriver:\n    pass\n")
    line = one_error_line(drivebench("run", "--brain", "my_driver:MyDrivr", cwd=tmp_path))
    assert "module 'my_driver' has no 'MyDrivr'; did you mean 'MyDriver'?" in line, line


def test_no_suggestion_when_nothing_is_close():
    line = one_error_line(drivebench("run", "--circuit", "atlantis"))
    assert "did you mean" not in line


def test_every_schema_mistake_of_a_matrix_file_is_reported_at_once(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text(
        "name: m\nbrains: [explicit]\ncircuits: [simple]\nlimit: {laps: 1}\nrepetitions: many\n"
        "camera: {width_px: 0, heigth_px: 9}\n"
    )
    result = drivebench("matrix", str(path), "--plan")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert lines[0] == (
        f"drivebench: error: {path}:4: unknown key 'limit' in the matrix (allowed: circuits, variations, worlds, "
        "perturbations, repetitions, limits, exclude, include, draw, name, brains, shadows, camera, seed, realtime, "
        "renderer, parts); did you mean 'limits'?"
    )
    assert lines[1:3] == [
        f"{path}:5: repetitions must be an integer, got 'many'",
        f"{path}:6: camera.width_px must be an integer >= 8, got 0",
    ]
    assert lines[3].startswith(f"{path}:6: unknown key 'heigth_px' in camera") and "'height_px'?" in lines[3]


def test_every_mistake_in_a_matrix_files_values_is_reported_at_once_before_anything_starts(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text(
        "name: m\nbrains: [explicit, pilotnett]\ncamera: 320by240\nparts:\n  generalisation:\n"
        "    circuits: [simple, montmelo, montmelp]\n  noise:\n    circuits: [simple]\n"
    )
    result = drivebench("matrix", str(path), "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 3, lines
    assert lines[0].startswith(f"drivebench: error: {path}:2: unknown brain 'pilotnett'")
    assert lines[1].startswith(f"{path}:3: camera must look like 320x240")
    assert lines[2].startswith(f"{path}:6: unknown circuit 'montmelp'")
    for line, suggestion in ((lines[0], "'pilotnet'"), (lines[2], "'montmelo'")):
        assert line.endswith(f"did you mean {suggestion}?"), line
    assert [child.name for child in tmp_path.iterdir()] == ["m.yaml"]  # no output folder: nothing started


def test_list_and_inspect_commands_print_json():
    circuits = json.loads(drivebench("circuits", "list", "--json").stdout)
    simple = next(c for c in circuits if c["name"] == "simple")
    assert 400 < simple["length_m"] < 500 and simple["road_width_m"] == 3.0
    brains = json.loads(drivebench("brains", "list", "--json").stdout)
    explicit = {"name": "explicit", "origin": "built-in", "target": "brains.explicit.brain:ExplicitBrain"}
    assert {**explicit, "needs": None, "extra": None} in brains
    assert {"needs": "torch", "extra": "ml"}.items() <= next(b for b in brains if b["name"] == "pilotnet").items()
    plan_text = drivebench("matrix", "experiments/generalization.yaml", "--plan", cwd=ROOT).stdout.splitlines()
    plan = json.loads(drivebench("matrix", "experiments/generalization.yaml", "--plan", "--json", cwd=ROOT).stdout)
    assert len(plan) == len(plan_text) - 1 == 16
    assert [episode["key"] for episode in plan] == [line.split()[1] for line in plan_text[1:]]
    assert plan[0]["spec"]["circuit"] == "simple" and plan[0]["spec"]["seed"] == 7
    info = json.loads(drivebench("recorder", "info", str(LEGACY_RECORDING), "--json").stdout)
    assert info["messages"] == sum(channel["messages"] for channel in info["channels"]) > 0


def test_brains_list_has_a_header_row_and_says_which_brains_need_torch():
    lines = drivebench("brains", "list").stdout.splitlines()
    assert lines[0].split()[:3] == ["name", "from", "needs"]
    rows = {line.split()[0]: line.split() for line in lines[1:]}
    assert rows["explicit"][2] == "-"
    for network in ("pilotnet", "deepest_lstm_tiny_pilotnet", "memdccp", "neural"):
        assert rows[network][2:4] == ["torch", "(ml)"], rows[network]


def test_brains_list_in_the_demos_environment_says_what_to_install():
    """The demo's .venv has no torch (the interpreter is told so, as in the in-process torch test)."""
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "from orchestrator.cli import main\n"
        "sys.exit(main(['brains', 'list']))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "torch is not installed here: pip install 'drivebench[ml]'" in result.stderr.splitlines()


def test_brains_check_shows_no_third_party_banner():
    result = drivebench("brains", "check", "explicit", "--memory-steps", "5")
    assert result.returncode == 0, result.stderr
    assert "pybullet" not in result.stderr.lower() and "pybullet" not in result.stdout.lower()
    assert "PASS  act" in result.stdout


def test_run_help_groups_its_options_and_ends_with_examples():
    text = drivebench("run", "--help").stdout
    for group in ("world:", "brain:", "episode:", "output:", "attach:"):
        assert f"\n{group}\n" in text, group
    groups = text[text.index("\nworld:\n") :]  # past the usage line
    assert groups.index("--circuit") < groups.index("\nbrain:\n") < groups.index("--shadow")
    assert "examples:" in text and "drivebench run --config" in text


@pytest.mark.slow
@pytest.mark.integration
def test_a_run_folders_config_runs_the_same_episode_again(tmp_path):
    first = drivebench(
        "run",
        "--circuit",
        "nurburgring",
        "--noise",
        "gaussian=8",
        "--seed",
        "3",
        "--max-sim-seconds",
        "6",
        "--json",
        "--out",
        str(tmp_path / "first"),
        timeout=180,
    )
    assert first.returncode == 0, first.stderr
    again = drivebench(
        "run", "--config", str(tmp_path / "first" / "config.yaml"), "--json", "--out", str(tmp_path / "again")
    )
    assert again.returncode == 0, again.stderr
    before, after = json.loads(first.stdout), json.loads(again.stdout)
    assert after["spec"] == before["spec"] and before["spec"]["circuit"] == "nurburgring"
    for metric in ("progress_m", "cross_track_mean_m", "cross_track_max_m"):
        assert after["metrics"][metric] == before["metrics"][metric], metric
    assert before["header"]["run_id"] != after["header"]["run_id"]


def test_a_bad_config_file_is_one_line(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("episode: {circuit: simple}\n")
    line = one_error_line(drivebench("run", "--config", str(path)))
    assert line == f"drivebench: error: --config {path}:1: the run config is missing 'brains'"


def test_a_config_that_is_not_a_file_says_what_it_is(tmp_path):
    """A folder or a device is not "no such file": say what the path is, and point a run folder at its config."""
    run_folder = tmp_path / "run"
    run_folder.mkdir()
    (run_folder / "config.yaml").write_text("episode: {}\nbrains: [{brain: explicit}]\n")
    assert one_error_line(drivebench("run", "--config", str(run_folder))) == (
        f"drivebench: error: --config {run_folder}: a folder, not a file (did you mean {run_folder / 'config.yaml'}?)"
    )
    assert one_error_line(drivebench("run", "--config", str(tmp_path))) == (
        f"drivebench: error: --config {tmp_path}: a folder, not a file"
    )
    assert one_error_line(drivebench("run", "--config", "/dev/null")) == (
        "drivebench: error: --config /dev/null: a device, not a file"
    )
    missing = tmp_path / "nothing.yaml"
    assert one_error_line(drivebench("run", "--config", str(missing))) == (
        f"drivebench: error: --config {missing}: no such file"
    )


def test_a_config_file_reports_every_mistake_at_once_with_its_line(tmp_path):
    path = tmp_path / "config.yaml"
    path.write_text("run_id: abc\nepisode:\n  circuit: nowhere\n  laps: 2\nbrains:\n  - {brain: explict}\n")
    result = drivebench("run", "--config", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 2, result.stderr
    assert lines[0].startswith(f"drivebench: error: --config {path}:3: unknown circuit 'nowhere'")
    assert lines[1].startswith(f"--config {path}:6: ") and "explict" in lines[1]
    path.write_text("episode: {circuit: simple}\nbrains:\n  - {brain: explicit, colour: red}\n")
    line = one_error_line(drivebench("run", "--config", str(path)))
    assert line == (
        f"drivebench: error: --config {path}:3: unknown key 'colour' in brains[0] (allowed: brain, name, options, host)"
    )


def test_a_config_file_refuses_every_unknown_key_and_range_at_its_own_line_all_at_once(tmp_path):
    """A misspelt key is a mistake at every level (msgspec ignores unknown keys of an episode spec), and a value out
    of range is reported at its line, not at the episode's; every mistake of the file in one answer."""
    path = tmp_path / "config.yaml"
    path.write_text(
        "run_id: abc\n"  # 1
        "episode:\n"  # 2
        "  circuit: simple\n"  # 3
        "  lpas: 5\n"  # 4
        "  sead: 7\n"  # 5
        "  laps: -3\n"  # 6
        "  camera:\n"  # 7
        "    widht_px: 640\n"  # 8
        "    height_px: 2\n"  # 9
        "  realtme: true\n"  # 10
        "brians: []\n"  # 11
        "brains:\n"  # 12
        "  - {brain: explicit}\n"  # 13
    )
    result = drivebench("run", "--config", str(path), timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().removeprefix("drivebench: error: ").splitlines()
    expected = [
        (4, "unknown key 'lpas' in episode"),
        (5, "unknown key 'sead' in episode"),
        (6, "episode.laps must be >= 1, got -3"),
        (8, "unknown key 'widht_px' in episode.camera"),
        (9, "episode.camera.height_px must be within 8..4096, got 2"),
        (10, "unknown key 'realtme' in episode"),
        (11, "unknown key 'brians' in the run config"),
    ]
    assert len(lines) == len(expected), result.stderr
    for line, (number, message) in zip(lines, expected, strict=True):
        assert line.startswith(f"--config {path}:{number}: {message}"), (line, number, message)
    assert "did you mean 'laps'" in lines[0] and "did you mean 'brains'" in lines[-1]


@pytest.mark.parametrize(
    "flags",
    [
        ["--max-sim-seconds", "3", "--seed", "5", "--circuit", "montmelo", "--brain", "constant"],
        ["--seed", "0"],  # the default's value, typed: the file may say another
        ["--variation", "line=white"],
    ],
)
def test_config_with_the_options_it_replaces_is_refused_in_one_line(tmp_path, flags):
    """``run --config X`` drives the file's episode and brains: an option of the world, brain or episode groups beside
    it would be ignored, so it is refused, naming each option typed, before anything starts."""
    path = tmp_path / "config.yaml"
    path.write_text("episode: {circuit: simple, seed: 7}\nbrains:\n  - {brain: explicit}\n")
    line = one_error_line(drivebench("run", "--config", str(path), *flags, "--out", str(tmp_path / "run")))
    typed = [flag for flag in flags if flag.startswith("--")]
    assert line.startswith(f"drivebench: error: --config {path} runs the file as it is: {', '.join(typed)}"), line
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("flags", "words"),
    [
        (["--start-m", "100", "--variation", "start_m=200"], "--start-m 100 and --variation start_m=200 disagree"),
        (
            ["--direction", "reverse", "--variation", "line=white,direction=forward"],
            "--direction reverse and --variation line=white,direction=forward disagree",
        ),
    ],
)
def test_an_option_and_a_variation_that_disagree_are_one_line(tmp_path, flags, words):
    """Two ways of saying the start or the direction that say different things: refused, not the last one winning."""
    line = one_error_line(drivebench("run", *flags, "--out", str(tmp_path / "run")))
    assert line.startswith(f"drivebench: error: {words}"), line
    assert not (tmp_path / "run").exists()


RUNNABLE = re.compile(r"<!-- runnable -->\n```bash\n(.*?)```", re.S)


def readme_runnable_commands() -> list[str]:
    commands = []
    for block in RUNNABLE.findall((ROOT / "README.md").read_text()):
        commands += [line.split("#", 1)[0].strip() for line in block.splitlines() if line.split("#", 1)[0].strip()]
    return commands


def test_the_readme_marks_commands_as_runnable():
    commands = readme_runnable_commands()
    assert len(commands) >= 4 and all(command.startswith("drivebench ") for command in commands), commands


@pytest.mark.slow
def test_the_readmes_runnable_commands_run_as_written():
    for command in readme_runnable_commands():
        result = drivebench(*shlex.split(command)[1:], cwd=ROOT)
        assert result.returncode == 0, f"{command}: {result.stderr}"
        assert result.stdout.strip(), command


def _docs_hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "scripts" / "docs_hooks.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_docs_cli_reference_is_every_command_of_the_parser():
    require("mkdocs")  # the docs extra, which scripts/setup.sh installs
    reference = _docs_hooks().cli_reference()
    for heading in (
        "## drivebench run",
        "## drivebench matrix",
        "## drivebench recorder info",
        "## drivebench completion",
    ):
        assert f"\n{heading}\n" in reference, heading
    assert "--max-sim-seconds" in reference and "--record-images" in reference
    messages = _docs_hooks().messages_reference(ROOT / "docs" / "protocol")
    assert "## Command" in messages and "| `speed_mps` |" in messages


@pytest.mark.slow
def test_the_readmes_own_brain_meets_the_brain_contract(tmp_path):
    """The README's brain, written to the file it names, checked as the README says (from its folder)."""
    block = re.search(r"```python\n(# (\w+)\.py, in the folder.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert block is not None, "the README's own-brain example is gone"
    (tmp_path / f"{block.group(2)}.py").write_text(block.group(1))
    classes = re.findall(r"^class (\w+)", block.group(1), re.M)
    result = drivebench("brains", "check", f"{block.group(2)}:{classes[0]}", "--memory-steps", "5", cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "meets the brain contract" in result.stderr


def test_the_readmes_torch_example_in_the_demos_environment_names_what_to_install():
    """scripts/demo.sh's lean set has no torch: the README's example that needs it says which extra to install, in
    one line, exit 2 (the user's set-up, not a stack that could not run). The interpreter is told torch is absent,
    as it is in that set; the refusal comes before any process starts, so the children need not be told."""
    readme = (ROOT / "README.md").read_text()
    line = next(line for line in readme.splitlines() if line.startswith("drivebench run") and "(needs torch)" in line)
    argv = shlex.split(line.partition("#")[0])[1:] + ["--max-sim-seconds", "1"]
    code = f"import sys; sys.modules['torch'] = None\nfrom orchestrator.cli import main\nsys.exit(main({argv!r}))\n"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert result.stderr.strip() == (
        "drivebench: this needs torch, which is not installed: pip install 'drivebench[ml]' "
        "(or bash scripts/setup.sh, which installs every extra)"
    )


def test_every_page_in_the_site_nav_shows_in_the_nav():
    """With the theme's navigation.indexes, a README.md or index.md listed inside a section becomes that section's
    own page and drops out of its list (the Foxglove layouts page did); only the home page may be one."""
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"]

    def pages(items: list) -> list[str]:
        found = []
        for item in items:
            for value in item.values():
                found += pages(value) if isinstance(value, list) else [value]
        return found

    hidden = [page for page in pages(nav) if Path(page).name in ("README.md", "index.md") and page != "index.md"]
    assert hidden == []


def test_the_guides_output_folders_are_ignored_by_git():
    """The training guide writes its dataset under data/: a user following it should not see it as untracked."""
    ignored = subprocess.run(
        ["git", "check-ignore", "-q", "data/tiny/episode_0.mcap"], cwd=ROOT, capture_output=True, check=False
    )
    assert ignored.returncode == 0
