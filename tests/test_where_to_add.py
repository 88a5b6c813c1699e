"""ARCHITECTURE.md's "where to add" rows are the whole list: a sample noise model, metric and network, added to a copy
of the packages through exactly the places their rows name, work end to end (issue 41 item 10).

Each addition is a set of text insertions into the files of its row; the test first checks that the row names every
file it edits, then runs real code in the copy: the noise stage parses from ``--noise``, decodes from the wire and
perturbs a frame; the scorer fills the metric and every report shows it; the network builds, runs a frame and is a
brain.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("circuits", "protocol", "services", "brains", "orchestrator", "recorder", "drivebench")

# (file, the text the addition goes after (its first occurrence), the text added)
NOISE = [
    (
        "protocol/episode_spec.py",
        "\nNoiseStage = (\n",
        None,  # the struct goes before the union: see _noise_struct
    ),
    ("protocol/episode_spec.py", "NoiseStage = (\n    SaltPepper\n", "    | Invert\n"),
    ("protocol/episode_spec.py", "NOISE_MODELS: tuple[type[_Noise], ...] = (\n    SaltPepper,\n", "    Invert,\n"),
    ("services/noise/models.py", "from protocol.episode_spec import (\n", "    Invert,\n"),
    ("services/noise/models.py", "\n_MODELS: dict[type, type[NoiseModel]] = {\n", None),  # see _noise_model
    ("services/noise/models.py", "    SaltPepper: SaltPepperModel,\n", "    Invert: InvertModel,\n"),
    ("protocol/variations.py", "_PRIMARY = {\n", '    "invert": "strength",\n'),
    ("orchestrator/cli/run.py", 'help="camera perturbation, applied in order (repeatable): ', "invert=0.5, "),
]
METRIC = [
    ("protocol/messages.py", "    bm_suddenness_distance: float | None = None\n", "    half_distance_m: float = 0.0\n"),
    ("services/scorer/metrics.py", "\n\nclass EpisodeScorer:", None),  # the pure function: see _metric_function
    (
        "services/scorer/metrics.py",
        "        return EpisodeMetrics(\n",
        "            half_distance_m=half_distance_m(float(distance)),\n",
    ),
    (
        "orchestrator/report/columns.py",
        '    MetricColumn(field="steps", label=None),\n',
        '    MetricColumn(field="half_distance_m", label="half the distance", unit=" m", digits=1),\n',
    ),
]
NETWORK = [
    ("brains/nets/__init__.py", "from brains.nets import ", "sample_net, "),
    ("brains/nets/__init__.py", "NETWORKS: tuple[ModelInfo, ...] = (\n", "    sample_net.INFO,\n"),
]

_NOISE_STRUCT = '''
class Invert(_Noise, tag="invert", frozen=True):
    """The image's negative, blended in with ``strength`` (0: unchanged, 1: the negative)."""

    strength: float = 1.0

'''
_NOISE_MODEL = '''
class InvertModel(NoiseModel):
    """``(1 - strength) * in + strength * (255 - in)``, rounded."""

    stage: Invert

    def apply(self, image_rgb: np.ndarray) -> np.ndarray:
        image = _check_image(image_rgb).astype(np.float32)
        s = self.stage.strength
        return np.rint((1 - s) * image + s * (255 - image)).astype(np.uint8)

'''
_METRIC_FUNCTION = '''

def half_distance_m(distance_m: float) -> float:
    """Half the completed distance (m): a sample metric."""
    return distance_m / 2
'''
EXTRA = {  # inserted before their anchor, in the same files as above
    ("protocol/episode_spec.py", "\nNoiseStage = (\n"): _NOISE_STRUCT,
    ("services/noise/models.py", "\n_MODELS: dict[type, type[NoiseModel]] = {\n"): _NOISE_MODEL,
    ("services/scorer/metrics.py", "\n\nclass EpisodeScorer:"): _METRIC_FUNCTION,
}

CHECK = textwrap.dedent(
    """
    import json, math, subprocess, sys
    import msgspec, numpy as np

    from protocol import codec
    from protocol.episode_spec import EpisodeSpec, Invert
    from protocol.variations import noise_stage
    from services.noise.models import make_model

    stage = noise_stage("invert=0.5")
    assert stage == Invert(strength=0.5), stage
    spec = EpisodeSpec(noise=[stage])
    assert codec.decode(codec.encode(spec), EpisodeSpec).noise == [stage]
    frame = np.full((4, 6, 3), 100, np.uint8)
    assert (make_model(stage).apply(frame) == 128).all()
    help_text = subprocess.run([sys.executable, "-P", "-m", "orchestrator.cli", "run", "--help"],
                               capture_output=True, text=True, check=True).stdout
    assert "invert=0.5" in " ".join(help_text.split()), help_text

    from circuits import load_circuit
    from orchestrator.report.columns import CSV_COLUMNS, METRIC_COLUMNS, metric_rows
    from protocol.messages import EpisodeMetrics
    from services.scorer.metrics import EpisodeScorer

    circuit = load_circuit("simple")
    scorer = EpisodeScorer(circuit=circuit, laps_target=1, step_s=0.05)
    for i in range(200):
        x, y, heading = circuit.centreline.pose_at(i * 0.5)
        scorer.add_pose(seq=i, stamp_ns=round(i * 0.05e9), x_m=x, y_m=y, yaw_rad=heading)
    metrics = scorer.finish(wall_time_s=1.0)
    assert metrics.completed_distance_m > 50 and metrics.half_distance_m == metrics.completed_distance_m / 2
    assert sorted(c.field for c in METRIC_COLUMNS) == sorted(EpisodeMetrics.__struct_fields__)
    assert dict(metric_rows(metrics))["half the distance"] == f"{metrics.half_distance_m:.1f} m"
    assert "half_distance_m" in [c.field for c in CSV_COLUMNS]

    import torch
    from brains.nets import MODELS, make_model as make_network
    from brains.registry import brain_names

    info = MODELS["sample_net"]
    net = make_network("sample_net").eval()
    with torch.no_grad():
        out = net(torch.zeros(1, 3, info.input_height_px, info.input_width_px))
    assert out.shape == (1, 2), out.shape
    assert "sample_net" in brain_names()
    print("ok")
    """
)


def _apply(copy: Path, edits: list[tuple[str, str, str | None]]) -> None:
    for relative, anchor, added in edits:
        path = copy / relative
        text = path.read_text()
        assert anchor in text, f"{relative}: the anchor {anchor!r} is gone: update this test's sample addition"
        if added is None:
            text = text.replace(anchor, EXTRA[(relative, anchor)] + anchor, 1)
        else:
            text = text.replace(anchor, anchor + added, 1)
        path.write_text(text)


def _row(kind: str) -> str:
    for line in (ROOT / "ARCHITECTURE.md").read_text().splitlines():
        if line.startswith(f"| {kind} |"):
            return line
    raise AssertionError(f"ARCHITECTURE.md has no 'where to add' row for {kind}")


@pytest.mark.parametrize(
    ("kind", "edits", "folders"),
    [("a noise model", NOISE, []), ("a metric", METRIC, []), ("a network", NETWORK, ["brains/nets/<name>/"])],
)
def test_the_row_names_every_place_its_sample_edits(kind, edits, folders):
    row = _row(kind)
    for place in {relative for relative, _, _ in edits} | set(folders):
        assert f"`{place}`" in row, f"ARCHITECTURE.md's row for {kind} does not name {place}: {row}"


def test_a_sample_noise_model_metric_and_network_work_through_exactly_those_places(tmp_path):
    pytest.importorskip("torch")
    copy = tmp_path / "tree"
    for package in PACKAGES:
        shutil.copytree(ROOT / package, copy / package, ignore=shutil.ignore_patterns("__pycache__", "weights"))
    _apply(copy, NOISE + METRIC + NETWORK)
    # A network is a folder: pilotnet's, renamed (its INFO names the new network and module).
    shutil.copytree(
        ROOT / "brains/nets/pilotnet", copy / "brains/nets/sample_net", ignore=shutil.ignore_patterns("__pycache__")
    )
    init = copy / "brains/nets/sample_net/__init__.py"
    init.write_text(
        init.read_text()
        .replace('name="pilotnet"', 'name="sample_net"')
        .replace("brains.nets.pilotnet.model", "brains.nets.sample_net.model")
    )
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(copy), "HOME": str(tmp_path)}
    result = subprocess.run(
        [sys.executable, "-c", CHECK], cwd=copy, env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stdout + result.stderr
