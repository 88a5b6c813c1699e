"""A challenge's conditions: a matrix-style file with a public part (shown) and a hidden part (drawn from a secret
seed kept in the data folder, never shown).

A conditions file is a matrix file without ``brains`` (the submission is the brain) and with two parts::

    name: my-challenge
    limits: {laps: 1, max_sim_seconds: 15}
    camera: 160x120
    parts:
      public: {circuits: [simple], variations: {line: [red, white]}}
      hidden: {draw: {count: 6, circuits: [random, twisty, grandprix], variations: {line: [red, white]}}}

The hidden part's ``draw`` takes no ``seed``: it comes from ``DIR/secret_seed`` (written once, mode 0600). Each
evaluation is that file with the submission as its only brain and the secret seed in the draw: the matrix runner
runs it like any other matrix (``orchestrator.matrix.draw`` draws the held-out conditions).
"""

from __future__ import annotations

import hashlib
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from orchestrator.matrix.load import parse_matrix
from orchestrator.matrix.plan import Matrix, MatrixError

PUBLIC, HIDDEN = "public", "hidden"
SECRET_FILE = "secret_seed"
SUBMISSION_LABEL = "submission"  # the brain's label in every evaluation (its bus name; episode keys start with it)
_SEED_BITS = 62  # fits the matrix schema's int64 seed; far too many to guess from a score or a digest

# The default challenge: a few conditions, short episodes (an evaluation takes well under a minute on 2 cores).
DEFAULT_CONDITIONS = """\
name: drivebench-challenge
limits: {laps: 1, max_sim_seconds: 12}
camera: 160x120
parts:
  public: {circuits: [simple], variations: {line: [red, white]}}
  hidden: {draw: {count: 6, circuits: [random, twisty, grandprix], variations: {line: [red, white]}}}
"""


@dataclass(frozen=True)
class Challenge:
    """The conditions file's text (``source`` names it in errors) and the secret seed of its hidden draw."""

    text: str
    source: str
    secret_seed: int

    def matrix_text(self, *, brain: dict[str, Any]) -> str:
        """The matrix an evaluation runs: the file, ``brain`` (a matrix brains entry) its only brain, the seed set.
        Secret: it names the seed; kept in the data folder only."""
        data = yaml.safe_load(self.text)
        data["brains"] = [{**brain, "label": SUBMISSION_LABEL}]
        data["parts"][HIDDEN]["draw"]["seed"] = self.secret_seed
        return yaml.safe_dump(data, sort_keys=False)

    def matrix(self, *, brain: dict[str, Any]) -> Matrix:
        return parse_matrix(self.matrix_text(brain=brain), source=f"{self.source} (with the submission)")

    def hidden_names(self) -> list[str]:
        """What must never leave the server: the seed, and the circuit and world labels the hidden draw gave."""
        matrix = self.matrix(brain={"name": "explicit"})
        hidden = [episode for episode in matrix.episodes if episode.part == HIDDEN]
        public = {episode.circuit for episode in matrix.episodes if episode.part == PUBLIC}
        circuits = {episode.circuit for episode in hidden} - public  # a circuit also public is no secret
        return [str(self.secret_seed), *sorted(circuits)]

    def public_text(self) -> str:
        """The conditions as the page shows them: the public part and the top level; of the hidden part, only how
        many conditions it draws."""
        data = yaml.safe_load(self.text)
        count = data["parts"][HIDDEN]["draw"]["count"]
        data["parts"][HIDDEN] = f"{count} conditions drawn from a secret seed (not shown)"
        return yaml.safe_dump(data, sort_keys=False)


def load_challenge(*, data_dir: Path, conditions: Path | None) -> Challenge:
    """The challenge of ``data_dir`` (its secret seed made on first use) with ``conditions`` (default: the built-in
    challenge). Raises :class:`MatrixError` (one line, at the line of the mistake) for a bad conditions file."""
    source = str(conditions) if conditions else "<default challenge>"
    if conditions is None:
        text = DEFAULT_CONDITIONS
    else:
        try:
            text = Path(conditions).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as error:
            raise MatrixError(f"cannot read the conditions file ({error})", source=source, line=None) from None
    _check_conditions(text, source=source)
    return Challenge(text=text, source=source, secret_seed=secret_seed(data_dir))


def _check_conditions(text: str, *, source: str) -> None:
    """Every mistake of the file at its own line: the file as a matrix with a brain appended (which keeps its line
    numbers), then the shape a challenge needs."""
    if "\nbrains:" in f"\n{text}":
        raise MatrixError("a conditions file names no brains (each submission is the brain)", source=source, line=1)
    parse_matrix(f"{text.rstrip()}\nbrains: [explicit]\n", source=source)
    parts = (yaml.safe_load(text) or {}).get("parts") or {}
    if set(parts) != {PUBLIC, HIDDEN}:
        raise MatrixError(f"a conditions file has exactly two parts, {PUBLIC} and {HIDDEN}", source=source, line=1)
    draw = parts[HIDDEN].get("draw")
    if not isinstance(draw, dict):
        what = "the hidden part draws its conditions (draw: {count: ..., circuits: ...})"
        raise MatrixError(what, source=source, line=None)
    if "seed" in draw:
        what = "the hidden draw takes no seed: it comes from the data folder's secret"
        raise MatrixError(what, source=source, line=None)


def secret_seed(data_dir: Path) -> int:
    """The challenge's secret seed: read from ``DIR/secret_seed``, or made there once (readable by its owner only)."""
    path = Path(data_dir) / SECRET_FILE
    try:
        descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return int(path.read_text().strip())
    with os.fdopen(descriptor, "w") as file:
        file.write(f"{secrets.randbits(_SEED_BITS)}\n")
    return int(path.read_text().strip())


def digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


class Redactor:
    """Replaces every secret (the seed, the hidden circuits' names) in text that leaves the server: a last guard
    under the rule that nothing hidden is put in an answer in the first place."""

    def __init__(self, secrets_: list[str]):
        self._secrets = sorted((s for s in secrets_ if s), key=len, reverse=True)

    def __call__(self, text: str) -> str:
        for secret in self._secrets:
            text = text.replace(secret, "<hidden>")
        return text
