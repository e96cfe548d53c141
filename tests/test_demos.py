"""Every demo runs, and prints the numbers the documentation (README and docs/) quotes from it.

In the manner of DOLFINx's python/demo/test.py: each demo in demos/ runs as a user runs it, as a
subprocess, serially and, where it exercises the distributed model and solver, under
``mpiexec -n 2``. Each writes into a temporary folder named by ``-o`` (through
:func:`lungmech.parallel.destination.output_folder`: staged, so nothing else is written), and
must exit with 0. The numbers the README quotes from it are then read from the README and
compared with the ones the demo printed, so a README that no longer tells what the demo does
fails here.

Tolerances, and where they come from:

* A number quoted as "0.993" must be what the measured value rounds to, give or take half a unit
  of its last digit: the README rounds the demo's output. Every quoted number is the answer of
  a converged computation whose own tolerance lies well below that digit. Newton stops at a
  relative residual of 1e-10 ([solver] rtol). A registration stops when no node moves by more
  than 0.02 voxel, with the det F limit cutting none of its last steps (a descent held by it
  is an error, not a quote). The lock (requirements/lock.txt) fixes the libraries' arithmetic
  too.
* A round-off-sized quantity (a relative error of 1e-12, say) is quoted for its order of
  magnitude only: a factor of 10.
* Times and iteration counts are never compared: they are the machine's and the path's, not
  the answer's.

Which demos run under MPI, and why:

* ``inflate_sphere`` and ``breathing_cycle``: the model and the solver (mixed P2–P1 with a
  follower pressure; poromechanics, the inverse problem, adaptive stepping) on a distributed
  mesh, and the demo's own rank-0 printing and plotting. Each takes seconds.
* ``reduced_lung`` runs serially only: on 2 ranks it takes about 8 minutes on the 2-core CI
  machine, which alone would push the suite past its 15-minute budget; its parallel code
  (distributed POD basis, reduced Newton, a model saved on 2 ranks and loaded on 1) is tested
  on 2 ranks in tests/test_mpi.py.
* ``register_lung`` runs serially only: registration on 2 ranks is tested in tests/test_mpi.py,
  and its node-by-node result depends on the partition (see the README), beyond the precision
  the README quotes its numbers to.

These tests launch mpiexec themselves, so they belong to the serial suite (not marked ``mpi``).
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lungmech.parallel.destination import MARKER

ROOT = Path(__file__).resolve().parents[1]
DEMOS = ROOT / "demos"
PAGES = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts)]
# the README and the documentation's pages as one line: quotes wrap anywhere
README = " ".join(" ".join(page.read_text(encoding="utf-8") for page in PAGES).split())
BIN = Path(sys.executable).parent
MPIEXEC = str(BIN / "mpiexec") if (BIN / "mpiexec").exists() else "mpiexec"
# The demo imports this lungmech (the tree under test), whether or not it is installed.
ENV = {
    **os.environ,
    "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]),
    "PYTHONWARNINGS": "ignore",
    "OMP_NUM_THREADS": "1",
}
NUMBER = r"([-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?)"


def run(demo: str, folder: Path, ranks: int = 1, timeout: float = 900) -> str:
    """Run ``demos/<demo>.py -o folder/out`` from ``folder``; its standard output.

    It must succeed, and write nothing but its output folder, which lungmech marks as its own.
    """
    command = [sys.executable, str(DEMOS / f"{demo}.py"), "-o", str(folder / "out")]
    if ranks > 1:
        command = [MPIEXEC, "-n", str(ranks), *command]
    tic = time.perf_counter()
    done = subprocess.run(command, cwd=folder, env=ENV, capture_output=True, text=True, timeout=timeout)
    print(f"{demo} on {ranks} rank(s): {time.perf_counter() - tic:.0f} s")  # shown by pytest -s or on failure
    assert done.returncode == 0, f"{demo} failed:\n{done.stdout}\n{done.stderr}"
    assert sorted(p.name for p in folder.iterdir()) == ["out"], "the demo wrote outside its output folder"
    assert (folder / "out" / MARKER).is_file(), "the demo did not write through lungmech's output_folder"
    return done.stdout


def quoted(pattern: str) -> tuple[str, ...]:
    """The groups of ``pattern`` in the README (whitespace-insensitive); the sentence must be there."""
    match = re.search(pattern, README)
    assert match, f"the README no longer says {pattern!r}: update the README or this test"
    return match.groups()


def printed(pattern: str, output: str) -> tuple[str, ...]:
    match = re.search(pattern, output)
    assert match, f"the demo no longer prints {pattern!r}; it printed:\n{output}"
    return match.groups()


def rounds_to(text: str, measured: float) -> bool:
    """Whether ``measured`` is ``text`` as written, to half a unit of its last digit.

    "0.993" admits 0.9925 to 0.9935, "3e-4" 2.5e-4 to 3.5e-4, "91" 90.5 to 91.5.
    """
    mantissa, _, exponent = text.lower().partition("e")
    unit = 10.0 ** (int(exponent or 0) - len(mantissa.partition(".")[2]))
    return abs(measured - float(text)) <= unit / 2 * (1 + 1e-9)


def same_order(text: str, measured: float) -> bool:
    """Whether ``measured`` is within a factor of 10 of ``text``: for round-off-sized quantities."""
    return measured > 0 and abs(math.log10(measured / float(text))) <= 1


def within(fraction: float):
    """Whether a measured number is within ``fraction`` of the quoted one: for the answers of a
    long descent, whose last digits follow the CPU's floating point (its BLAS kernels): the
    cohort's leave-one-out errors (0.62 and 0.60 mm on an AMD EPYC, 0.63 and 0.61 on one Intel
    Xeon, 0.61 and 0.59 on another, same versions) and its shape modes."""

    def agree(text: str, measured: float) -> bool:
        return abs(measured - float(text)) <= fraction * abs(float(text))

    return agree


def check(readme: tuple[str, ...], demo: tuple[str, ...], agree=rounds_to) -> None:
    """Each README number against the demo's number in the same place."""
    assert len(readme) == len(demo)
    wrong = [f"README {r}, demo {d}" for r, d in zip(readme, demo) if not agree(r, float(d))]
    assert not wrong, "the README quotes other numbers than the demo prints: " + "; ".join(wrong)


# --- inflate_sphere ------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("ranks", [1, 2])
def test_inflate_sphere(tmp_path, ranks):
    output = run("inflate_sphere", tmp_path, ranks)
    assert (tmp_path / "out" / "sphere_inflation.png").is_file()
    readme = quoted(
        rf"drives this sphere to {NUMBER} % of its limit-point pressure\. It agrees with the closed form to "
        rf"{NUMBER} of P_max"
    )
    check(
        readme,
        printed(rf"to {NUMBER} % of the limit-point pressure; max \|P_FE - P_exact\| / P_max = {NUMBER}", output),
    )


# --- breathing_cycle -----------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("ranks", [1, 2])
def test_breathing_cycle(tmp_path, ranks):
    output = run("breathing_cycle", tmp_path, ranks)
    assert (tmp_path / "out" / "breathing_cycle.png").is_file()
    imaged, unloaded, inspired, difference = quoted(
        rf"\({NUMBER} L imaged, {NUMBER} L unloaded\) and inhale to {NUMBER} L\. .*? the two P–V loops coincide: "
        rf"their end-inspiration volumes differ by less than {NUMBER} relative"
    )
    for mode in ("spontaneous", "ventilator"):
        check((imaged, unloaded), printed(rf"{mode} .*?: imaged {NUMBER} L, unloaded {NUMBER} L", output))
    spontaneous, ventilator, measured = printed(
        rf"spontaneous {NUMBER} L, ventilator {NUMBER} L \(relative difference {NUMBER}\)", output
    )
    check((inspired, inspired), (spontaneous, ventilator))
    assert abs(float(measured)) < float(difference)


# --- reduced_lung --------------------------------------------------------------------------------


@pytest.mark.slow
def test_reduced_lung(tmp_path):
    output = run("reduced_lung", tmp_path)
    assert {"reduced_lung.npz", "reduced_lung.png"} <= {p.name for p in (tmp_path / "out").iterdir()}
    check(
        quoted(
            rf"breaths of depth 0\.5 and 1\.5 \({NUMBER} snapshots\), keeps a POD basis of the {NUMBER} significant"
        ),
        printed(rf"offline: {NUMBER} snapshots, POD basis of {NUMBER} vectors", output),
    )
    rows = re.findall(rf"\| {NUMBER} \((?:between|beyond)\) \| {NUMBER} L \| {NUMBER} L \| {NUMBER} \|", README)
    assert len(rows) == 3, "the README's table of unseen depths has changed: update it or this test"
    for depth, full, reduced, error in rows:
        measured = printed(
            rf"depth {depth}: end-inspiration volume {NUMBER} L full, {NUMBER} L reduced \(relative error {NUMBER}\)",
            output,
        )
        check((full, reduced), measured[:2])
        check((error,), measured[2:], agree=same_order)


# --- register_lung -------------------------------------------------------------------------------


@pytest.mark.slow
def test_register_lung(tmp_path):
    output = run("register_lung", tmp_path)
    files = {p.name for p in (tmp_path / "out").iterdir()}
    assert {"registration.png", "shape_modes.png", "shape_mode_sections.png", "new_lung.vtu"} <= files
    # Registration onto the synthetic patient (the time is the machine's: not compared).
    readme = quoted(
        rf"Registration: {NUMBER} iterations in {NUMBER} s, Dice {NUMBER}, mean surface distance {NUMBER} mm "
        rf"\({NUMBER} voxel\), hd95 {NUMBER} mm, min det F {NUMBER}\."
    )
    demo = printed(
        rf"registered in {NUMBER} iterations, {NUMBER} s: Dice {NUMBER}, mean surface distance {NUMBER} mm "
        rf"\({NUMBER} voxels\), hd95 {NUMBER} mm, min det F {NUMBER}",
        output,
    )
    # Iteration counts are the path of a descent, not its answer: never compared (the same Dice
    # and distances came after 98 iterations with one NumPy and SciPy, 85 with the next).
    check(readme[2:], demo[2:])
    # Shape modes of the cohort.
    (worst,) = quoted(rf"the worst Dice is {NUMBER}\.")
    compactness, ratios = quoted(rf"The first 2 modes capture {NUMBER} % of the variance \(σ/σ₁ = ([\d., ]+), …\)")
    (errors,) = quoted(r"The leave-one-out error falls ([\d.→ ]+) mm with 0 → 3 modes")
    demo_worst, demo_ratios, demo_compactness, demo_errors = printed(
        rf"worst Dice {NUMBER}\); σ/σ1 = \[([\d.\s]+)\]; the first 2 modes capture {NUMBER} % of the variance; "
        r"leave-one-out RMS error ([\d.→ ]+) mm with 0 → 3 modes",
        output,
    )
    ratios, errors = ratios.split(", "), errors.split(" → ")
    demo_ratios, demo_errors = demo_ratios.split()[: len(ratios)], demo_errors.split(" → ")
    check((worst,), (demo_worst,))
    # the variance the two latent parameters explain, and σ₂/σ₁, to 2 %; the modes beyond them
    # are the registrations' noise (a third of a voxel), which moves with the CPU: to 10 %
    check((compactness, *ratios[:2]), (demo_compactness, *demo_ratios[:2]), agree=within(0.02))
    check(tuple(ratios[2:]), tuple(demo_ratios[2:]), agree=within(0.10))
    check(tuple(errors), tuple(demo_errors), agree=within(0.02))


# --- parameter_sweep -----------------------------------------------------------------------------


@pytest.mark.slow
def test_parameter_sweep(tmp_path):
    """The 3 × 3 sweep from Python: no FFCx call after the build, and the README's tidal volumes.
    (The sweep through 'lungmech run --set' is tested on a small scene in test_parameters.py.)"""
    output = run("parameter_sweep", tmp_path)
    assert printed(r"FFCx calls during the 9-point Python sweep: (\d+)", output) == ("0",)
    assert "**0 FFCx calls**" in README
    for pleural in ("300", "500", "700"):
        readme = quoted(rf"\| −{pleural} Pa \| {NUMBER} \| {NUMBER} \| {NUMBER} \|")
        check(readme, printed(rf"\s+-{pleural}\s+{NUMBER}\s+{NUMBER}\s+{NUMBER}", output))
