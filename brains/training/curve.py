"""The training curve as a PNG, drawn with matplotlib (Agg): losses and validation MAE per epoch, log axes with
real ticks, each panel's legend below it, outside the lines."""

from __future__ import annotations

from pathlib import Path
from typing import Any

_LABELS = {
    "train_loss": "training loss (while training)",
    "train_eval_loss": "training loss (evaluated)",
    "val_loss": "validation loss",
    "val_mae_speed_mps": "validation MAE, speed (m/s)",
    "val_mae_yaw_rate_radps": "validation MAE, yaw rate (rad/s)",
}
_COLOURS = {
    "train_loss": "#d97706",
    "train_eval_loss": "#15803d",
    "val_loss": "#1d4ed8",
    "val_mae_speed_mps": "#9333ea",
    "val_mae_yaw_rate_radps": "#0891b2",
}
PANELS = (
    (("train_loss", "train_eval_loss", "val_loss"), "loss", "no loss recorded"),
    (("val_mae_speed_mps", "val_mae_yaw_rate_radps"), "validation MAE", "no validation split"),
)


def plot_curve(curve: list[dict[str, Any]], path: Path) -> bool:
    """PNG of ``curve`` (one dict per epoch) at ``path``: losses (left) and validation MAE (right), each on a log
    axis; False when the file could not be written."""
    import matplotlib

    matplotlib.use("Agg")  # no display: training runs headless
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.4), layout="constrained")
    for ax, (keys, title, empty) in zip(axes, PANELS):
        _panel(ax, curve, keys, title=title, empty=empty)
    try:
        fig.savefig(path, dpi=110)
    except OSError:
        return False
    finally:
        plt.close(fig)
    return True


def _panel(ax, curve: list[dict[str, Any]], keys: tuple[str, ...], *, title: str, empty: str) -> None:
    series = {key: [(e["epoch"], e[key]) for e in curve if e.get(key) is not None and e[key] > 0] for key in keys}
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("epoch", fontsize=9)
    drawn = [key for key in keys if series[key]]
    if not drawn:
        ax.text(0.5, 0.5, empty, ha="center", va="center", transform=ax.transAxes, color="0.4")
        ax.set_xticks([])
        ax.set_yticks([])
        return
    for key in drawn:
        epochs, values = zip(*series[key])
        ax.plot(epochs, values, color=_COLOURS[key], lw=1.8, marker="o" if len(epochs) < 12 else None, ms=4)
        ax.lines[-1].set_label(_LABELS[key])
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))  # labelled ticks, not only decades
    ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.grid(True, which="both", color="0.92")
    ax.tick_params(labelsize=8)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncols=1, fontsize=8, frameon=False)
