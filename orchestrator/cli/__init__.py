"""The ``drivebench`` command: one module per subcommand, one error table for all of them.

    drivebench run [--circuit simple] [--brain explicit] [--laps 1] [--camera 320x240] [--record F.mcap] [--json] ...
    drivebench swap BRAIN [--weights CKPT] [--name NAME] [--run RUN_ID] [--router EP] [--keep-old]
    drivebench matrix FILE [-o DIR] [--workers N] [--record] [--resume]; drivebench report DIR; drivebench paper
    drivebench run --attach [--router EP]; drivebench view [--run RUN]; drivebench health ROLE
    drivebench recorder info|repair, replay, dataset build|collect, train, export, pack, brains list|check|schema,
    circuits list|show|import, bm import (a Behavior Metrics config as a matrix)
    drivebench board serve --data DIR --port N; drivebench board submit FILE --server URL --name NAME [--wait]

Each module of :data:`COMMANDS` has ``add(commands)``, which adds its subcommand(s) with ``set_defaults(func=...)``;
``main`` calls that function and turns the errors of ``orchestrator.cli.errors`` (and a stack that could not run)
into one line on stderr and the exit code of that table. Modules import what is heavy (torch, the report stack)
inside their commands, so ``drivebench --help`` and a healthcheck stay fast.
"""

from __future__ import annotations

import argparse
import os
import re
import sys

from orchestrator.cli import (
    bm,
    board,
    brains,
    circuits,
    export,
    health,
    matrix,
    paper,
    recording,
    run,
    swap,
    train,
    view,
)
from orchestrator.cli.errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, CommandFailed, UsageError
from orchestrator.stack.failures import StackError, StackFailure
from protocol.bus import BusError
from protocol.deploy.runtime import exit_on_sigterm

# The optional extras (pyproject.toml) by a module each provides: a command that needs one names what to install
# (scripts/demo.sh's lean set has the stack, not torch or Ray).
EXTRA_OF_MODULE = {
    "torch": "ml",
    "onnxruntime": "ml",
    "onnx": "ml",
    "ray": "cluster",
    "moderngl": "gl",
    "pybullet": "sim",
    "scipy": "sim",
    "matplotlib": "report",
    "mcap": "record",
    "zstandard": "record",
    "foxglove": "view",
}

COMMANDS = (run, swap, recording, train, export, matrix, brains, paper, health, view, circuits, bm, board)


EXAMPLES = """examples:
  drivebench run                                    the explicit brain drives one lap of simple
  drivebench run --brain my_module:MyBrain          your own brain (drivebench brains check it first)
  drivebench matrix experiments/smoke.yaml -o runs/smoke      a matrix of episodes, then its report
  drivebench circuits list --json                   every list and inspect command has --json

`drivebench COMMAND --help` for one command; shell completion: drivebench completion bash|zsh.
Documentation: docs/ (bash scripts/docs.sh serve)."""


class SuggestingParser(argparse.ArgumentParser):
    """argparse with "did you mean" for a misspelled command (``drivebench rnu``) or option (``run --circut``).

    Subparsers are made of the same class (argparse's default), and the deepest one to parse is the command the
    user typed: its options are the ones a misspelled option is compared with."""

    parsing: SuggestingParser | None = None  # the deepest parser of the current parse (one parse per process)

    def parse_known_args(self, args=None, namespace=None):
        SuggestingParser.parsing = self
        return super().parse_known_args(args, namespace)

    def error(self, message: str):
        super().error(message + _suggestion(message, SuggestingParser.parsing or self))


def _suggestion(message: str, parser: argparse.ArgumentParser) -> str:
    """The did-you-mean for argparse's message: an invalid choice against its choices, an unrecognized option
    against the options of the command that was parsing."""
    from protocol.suggest import did_you_mean

    choice = re.search(r"invalid choice: '(.*?)' \(choose from (.*)\)$", message)
    if choice:
        return did_you_mean(choice.group(1), re.findall(r"'(.*?)'", choice.group(2)))
    if message.startswith("unrecognized arguments: "):
        options = [option for action in parser._actions for option in action.option_strings]
        for word in message.removeprefix("unrecognized arguments: ").split():
            if word.startswith("-") and (hint := did_you_mean(word.partition("=")[0], options)):
                return hint
    return ""


def build_parser() -> argparse.ArgumentParser:
    parser = SuggestingParser(
        prog="drivebench",
        description="Closed-loop evaluation of end-to-end driving brains: run episodes, record "
        "them, build datasets, train and serve networks.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"drivebench {_version()}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in COMMANDS:
        module.add(commands)
    completion = commands.add_parser(
        "completion", help="print the shell completion script for bash or zsh (generated from this parser)"
    )
    completion.add_argument("shell", choices=("bash", "zsh"))
    completion.set_defaults(func=command_completion)
    return parser


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("drivebench")
    except metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def command_completion(args: argparse.Namespace) -> int:
    """``drivebench completion bash|zsh``: shtab's script for the whole parser, on stdout.

    bash: ``drivebench completion bash > ~/.local/share/bash-completion/completions/drivebench``;
    zsh: ``drivebench completion zsh > "${fpath[1]}/_drivebench"``."""
    import shtab

    parser = build_parser()
    _complete_names(parser)
    print(shtab.complete(parser, shell=args.shell))
    return EXIT_OK


def _complete_names(parser: argparse.ArgumentParser) -> None:
    """Give every option and argument that takes a circuit or a brain the names there are, as shtab completions.

    The names are written into the script when it is generated (a completion that ran drivebench on every Tab would
    wait for Python each time): regenerate it after importing a circuit or installing a brain package. A brain
    also completes to ``.py`` files (a Behavior Metrics brain file) in bash."""
    from brains.registry import brain_names
    from circuits.library import circuit_names

    circuits, brains = " ".join(circuit_names()), " ".join(brain_names())
    # bash: functions that print the candidates for the word ($1); "_file" in a name makes shtab complete file names
    circuit_complete = {
        "bash": "_drivebench_circuits",
        "zsh": f"({circuits})",
        "preamble": {"bash": f'_drivebench_circuits() {{ compgen -W "{circuits}" -- "$1"; }}'},
    }
    brain_complete = {
        "bash": "_drivebench_brains_file",
        "zsh": f"({brains})",
        "preamble": {
            "bash": f'_drivebench_brains_file() {{ compgen -W "{brains}" -- "$1"; compgen -d -- "$1"; '
            f"compgen -f -X '!*.py' -- \"$1\"; }}"
        },
    }
    for command, action in _actions(parser):
        if action.dest == "circuit" or (command.endswith(" circuits show") and action.dest == "name"):
            action.complete = circuit_complete  # type: ignore[attr-defined]
        elif action.dest in ("brain", "shadow"):
            action.complete = brain_complete  # type: ignore[attr-defined]


def _actions(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.Action]]:
    """Every action of the parser and of its subcommands, each with the prog of the (sub)command it belongs to."""
    found = []
    for action in parser._actions:
        found.append((parser.prog, action))
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases map to the same parser
                found += _actions(sub)
    return found


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:  # `drivebench` alone: the help, as git and docker do
        parser.print_help()
        return EXIT_OK
    exit_on_sigterm()  # SIGTERM stops the stack as cleanly as Ctrl-C does
    try:
        return args.func(args)
    except UsageError as error:
        print(f"drivebench: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except CommandFailed as error:
        print(f"drivebench: {error}", file=sys.stderr)
        return EXIT_FAILED
    except (StackError, BusError) as error:
        kind = f" ({error.kind})" if isinstance(error, StackFailure) else ""
        print(f"drivebench: the stack could not run{kind}: {error}", file=sys.stderr)
        return EXIT_FAILED
    except ModuleNotFoundError as error:
        extra = EXTRA_OF_MODULE.get((error.name or "").split(".")[0])
        if extra is None:
            raise
        print(
            f"drivebench: this needs {error.name}, which is not installed: pip install 'drivebench[{extra}]' "
            "(or bash scripts/setup.sh, which installs every extra)",
            file=sys.stderr,
        )
        return EXIT_USAGE  # the user's set-up, fixed by the line above: not a stack that could not run
    except KeyboardInterrupt:
        print("drivebench: interrupted; every process stopped", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # `drivebench ... | head`: the reader has all it wanted
        sys.stdout = open(os.devnull, "w")  # so the interpreter's final flush does not fail
        return EXIT_OK
    except SystemExit as stop:
        if isinstance(stop.code, int) and stop.code > 128:  # our SIGTERM handler: the stack is already stopped
            print("drivebench: terminated; every process stopped", file=sys.stderr)
        raise
