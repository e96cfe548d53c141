"""What a person reads on the terminal: progress of a run, its closing line, numbers with units.

lungmech computes in SI units (m, Pa, N, J, kg, s). On the console, volumes are given in litres
and pressures in kPa and cmH2O, the units of respiratory physiology. Progress goes to standard
output on rank 0: a live bar on a terminal, one plain line per step in logs and CI.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path
from typing import TextIO

from mpi4py import MPI

__all__ = ["CMH2O", "Progress", "end_of_run", "litres", "pressure", "volume_text"]

CMH2O = 98.0665  # Pa per cmH2O
log = logging.getLogger("lungmech")


def per_metre_of_thickness(volume: float) -> str:
    """A 2-D body's volume (m³ per m of thickness), for people."""
    return f"{volume:.4g} m³ per m of thickness"


def litres(volume: float) -> str:
    """A volume in m³, written in litres."""
    return f"{1e3 * volume:.4g} L"


def volume_text(value: float, planar: bool = False) -> str:
    """A body's volume for people: litres, or m³ per m of thickness for a plane (2-D) body."""
    return per_metre_of_thickness(value) if planar else litres(value)


def pressure(value: float) -> str:
    """A pressure in Pa, written in kPa and cmH2O."""
    return f"{value / 1e3:.4g} kPa ({value / CMH2O:.3g} cmH2O)"


class Progress:
    """The progress of one phase of a run (e.g. "breathing", "unloading the imaged lung").

    On a terminal the last line is redrawn in place, with a bar; elsewhere (a log file, CI)
    every update is a line of its own. Prints on rank 0 only, and only when the ``lungmech``
    logger shows INFO messages (``-q`` silences it).
    """

    def __init__(self, phase: str, comm: MPI.Comm = MPI.COMM_WORLD, stream: TextIO | None = None) -> None:
        self.phase = phase
        self.stream = stream or sys.stdout
        self.enabled = comm.rank == 0 and log.isEnabledFor(logging.INFO)
        self.live = self.enabled and _terminal(self.stream)
        self._drawn = False
        self._started = time.perf_counter()

    def update(self, fraction: float, text: str) -> None:
        """``fraction`` of the phase is done; ``text`` says where it stands."""
        if not self.enabled:
            return
        if self.live:
            width = 24
            filled = int(round(width * min(max(fraction, 0.0), 1.0)))
            bar = "#" * filled + "." * (width - filled)
            self.stream.write(f"\r\033[K{self.phase} [{bar}] {100 * fraction:3.0f}%  {text}")
            self._drawn = True
        else:
            self.stream.write(f"{self.phase}: {text}\n")
        self.stream.flush()

    def note(self, text: str) -> None:
        """A line of its own (e.g. a step cut back), kept above a live bar."""
        if not self.enabled:
            return
        if self._drawn:
            self.stream.write("\r\033[K")
        self.stream.write(f"{self.phase}: {text}\n")
        self.stream.flush()
        self._drawn = False

    def close(self, text: str | None = None) -> None:
        if not self.enabled:
            return
        if self._drawn:
            self.stream.write("\n")
        seconds = time.perf_counter() - self._started
        if text is not None:
            self.stream.write(f"{self.phase}: {text} ({seconds:.1f} s)\n")
        self.stream.flush()
        self._drawn = False


def _terminal(stream: TextIO) -> bool:
    if os.environ.get("CI") or os.environ.get("TERM") == "dumb":
        return False
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def end_of_run(summary: dict, folder: Path) -> str:
    """The closing line of a run: the work done and the volumes a physiologist reads."""
    largest = summary["largest_volume"]
    imaged = summary["start"]["kind"] == "imaged"
    start = "imaged (start)" if imaged else "start"

    def show(value: float) -> str:
        return volume_text(value, bool(summary.get("plane")))

    text = (
        f"lungmech: done in {summary['steps']} steps ({summary['cut_steps']} cut back), "
        f"{summary['newton_iterations']} Newton iterations, {summary['timings_seconds']['solve']:.1f} s "
        f"({summary['solver']}); volume: {start} {show(summary['start_volume'])}, largest "
        f"{show(largest['volume'])} at t = {largest['time']:.3g} s, final {show(summary['deformed_volume'])}"
    )
    if imaged:
        text += f"; unloaded reference {show(summary['reference_volume'])}"
    if summary.get("error_indicator") is not None:
        text += f"; estimated error {summary['error_indicator']:.1e} (relative, energy norm)"
    text += f"; outputs in {folder}"
    if summary.get("full_fields") is False:
        text += " (summary.json and history.csv: --fields adds the fields and the pictures)"
    return text
