"""A fake Behavior Metrics checkout: BM's folder layout with the test brains, for the BM adapter and importer tests."""

from __future__ import annotations

import shutil
from pathlib import Path

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "behavior_metrics"


def fake_bm_checkout(folder: Path) -> Path:
    """Copy the fake checkout into ``folder``/BehaviorMetrics, with the test brains in its brains/gazebo/f1."""
    root = folder / "BehaviorMetrics"
    shutil.copytree(FIXTURES / "fake_checkout", root)
    for brain in FIXTURES.glob("brain_f1_*.py"):
        shutil.copy(brain, root / "behavior_metrics" / "brains" / "gazebo" / "f1")
    return root
