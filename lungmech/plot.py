"""Pictures of results (matplotlib, off-screen)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def pressure_volume(pressure: np.ndarray, volume: np.ndarray, path: Path, pressure_label: str) -> None:
    """The P–V curve, inspiration (volume rising) and expiration (falling) drawn apart."""
    pressure, volume = np.asarray(pressure, dtype=float), np.asarray(volume, dtype=float)
    rising = np.diff(volume) >= 0
    fig, ax = plt.subplots(figsize=(5.5, 4))
    branches = ((rising, "tab:blue", "-o", "inspiration"), (~rising, "tab:orange", "--s", "expiration"))
    for branch, colour, style, label in branches:
        for k, i in enumerate(np.flatnonzero(branch)):
            ax.plot(pressure[i : i + 2], volume[i : i + 2], style, color=colour, ms=3, label=label if k == 0 else None)
    ax.set_xlabel(pressure_label)
    ax.set_ylabel("volume")
    ax.set_title("Pressure–volume curve")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
