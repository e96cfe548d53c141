"""Every demo runs as a page of the documentation and as a script, and its numbers hold.

The demos (``demos/*.py``) are literate scripts in jupytext's percent format. The documentation's
build executes each as a notebook (myst-nb, ``docs/conf.py``) through jupyter-cache, and its
prose shows the numbers of that run (``{glue:text}`key```). These tests execute the demos into
the same cache (``docs/_build/.jupyter_cache``), or read them from it, so a CI run executes each
demo once: the docs build finds them there. The cache keys a notebook by its code cells.

* A demo asserts its own results against its reference value at its algorithm's tolerance (the
  sphere against the closed form, the two breaths against each other, the reduced breaths
  against the full ones, ...): a failed assertion fails its execution, and so this test.
* Every number its prose glues was glued by the run, and its pictures are on the page.
* The README's quotes of a demo's numbers are the run's, to the quote's last digit.
* ``inflate_sphere`` and ``breathing_cycle`` also run as scripts under ``mpiexec -n 2`` (the
  model and the solver on a distributed mesh, the demo's rank-0 printing and plotting), each in
  seconds, and give the numbers of the one-rank run (their ``numbers.json``). ``reduced_lung``
  would take minutes on 2 ranks (its parallel code is tested in tests/test_mpi.py), and
  ``register_lung``'s node-by-node result depends on the partition.

Times are never compared: they are the machine's, not the answer's.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from lungmech.app.demo import NUMBERS
from lungmech.parallel.destination import MARKER

pytestmark = pytest.mark.serial  # executes notebooks and starts mpiexec itself

ROOT = Path(__file__).resolve().parents[1]
DEMOS = ROOT / "demos"
CACHE = ROOT / "docs" / "_build" / ".jupyter_cache"  # docs/conf.py: nb_execution_cache_path
README = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())  # quotes wrap anywhere
BIN = Path(sys.executable).parent
MPIEXEC = str(BIN / "mpiexec") if (BIN / "mpiexec").exists() else "mpiexec"
# The demo imports this lungmech (the tree under test), whether or not it is installed.
ENV = {"PYTHONPATH": str(ROOT), "PYTHONWARNINGS": "ignore", "OMP_NUM_THREADS": "1"}
NUMBER = r"([-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?)"
GLUE = "application/papermill.record/text/plain"  # how myst-nb's glue stores a value


def executed(demo: str, monkeypatch: pytest.MonkeyPatch) -> dict:
    """The demo as the documentation shows it: its notebook, executed (from the cache, or now
    and into it)."""
    import jupytext
    from jupyter_cache import get_cache
    from jupyter_cache.base import CacheBundleIn
    from jupyter_cache.executors.utils import single_nb_execution

    path = DEMOS / f"{demo}.py"
    notebook = jupytext.reads(path.read_text(encoding="utf-8"), fmt="py:percent")  # as docs/conf.py reads it
    with _locked():
        cache = get_cache(str(CACHE))
        with contextlib.suppress(KeyError):
            return cache.merge_match_into_notebook(notebook)[1]
    for name, value in ENV.items():
        monkeypatch.setenv(name, value)  # the kernel inherits the environment
    tic = time.perf_counter()
    with tempfile.TemporaryDirectory() as cwd:  # as the docs build does (nb_execution_in_temp)
        result = single_nb_execution(notebook, cwd=cwd, allow_errors=False, timeout=1800, meta_override=True)
    print(f"{demo} as a notebook: {time.perf_counter() - tic:.0f} s")  # shown by pytest -s or on failure
    assert result.err is None, f"demos/{demo}.py failed as a notebook:\n{result.exc_string}"
    bundle = CacheBundleIn(notebook, str(path), data={"execution_seconds": result.time})
    with _locked():
        cache.cache_notebook_bundle(bundle, check_validity=False, overwrite=True)
    return notebook


@contextlib.contextmanager
def _locked():
    """One pytest worker at a time in the cache's database (made by the first)."""
    import fcntl

    CACHE.mkdir(parents=True, exist_ok=True)
    with open(CACHE.parent / ".jupyter_cache.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def glued(notebook: dict) -> dict[str, float]:
    """The numbers the run glued, by key; every key the prose shows must be among them."""
    values = {
        output["metadata"]["scrapbook"]["name"]: float(output["data"][GLUE])
        for cell in notebook["cells"]
        for output in cell.get("outputs", [])
        if "scrapbook" in output.get("metadata", {})
    }
    prose = " ".join(cell["source"] for cell in notebook["cells"] if cell["cell_type"] == "markdown")
    shown = set(re.findall(r"\{glue:text\}`([^`:]+)", prose))
    assert shown, "the demo's prose shows no number of its run"
    assert shown <= set(values), f"the prose shows numbers the run did not glue: {sorted(shown - set(values))}"
    return values


def pictures(notebook: dict) -> int:
    """How many pictures the page shows."""
    return sum("image/png" in o.get("data", {}) for c in notebook["cells"] for o in c.get("outputs", []))


def run(demo: str, folder: Path, ranks: int) -> dict[str, float]:
    """Run ``demos/<demo>.py -o folder/out`` as a script from ``folder``; the numbers it wrote.

    It must succeed, and write nothing but its output folder, which lungmech marks as its own.
    """
    command = [MPIEXEC, "-n", str(ranks), sys.executable, str(DEMOS / f"{demo}.py"), "-o", str(folder / "out")]
    done = subprocess.run(command, cwd=folder, env=os.environ | ENV, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, f"{demo} failed:\n{done.stdout}\n{done.stderr}"
    assert sorted(p.name for p in folder.iterdir()) == ["out"], "the demo wrote outside its output folder"
    assert (folder / "out" / MARKER).is_file(), "the demo did not write through lungmech's output_folder"
    return json.loads((folder / "out" / NUMBERS).read_text())


def quoted(pattern: str) -> tuple[str, ...]:
    """The groups of ``pattern`` in the README (whitespace-insensitive); the sentence must be there."""
    match = re.search(pattern, README)
    assert match, f"the README no longer says {pattern!r}: update the README or this test"
    return match.groups()


def rounds_to(text: str, measured: float) -> bool:
    """Whether ``measured`` is ``text`` as written, to half a unit of its last digit.

    "0.993" admits 0.9925 to 0.9935, "3e-4" 2.5e-4 to 3.5e-4, "91" 90.5 to 91.5.
    """
    mantissa, _, exponent = text.lower().partition("e")
    unit = 10.0 ** (int(exponent or 0) - len(mantissa.partition(".")[2]))
    return abs(measured - float(text)) <= unit / 2 * (1 + 1e-9)


def test_rounds_to():
    assert rounds_to("3e-4", 2.89e-4) and not rounds_to("3e-4", 3.6e-4)
    assert rounds_to("0.993", 0.9934) and not rounds_to("0.993", 0.9936) and rounds_to("91", 90.6)


def same_as_one_rank(distributed: dict[str, float], serial: dict[str, float], round_off: set[str] = frozenset()):
    """The 2-rank script's numbers against the 1-rank notebook's: the same answer to Newton's
    tolerance (1e-10 relative residual, so 1e-7 in the values), round-off quantities to 1e-12."""
    assert set(distributed) == set(serial)
    for key, value in serial.items():
        tolerance = {"abs": 1e-12} if key in round_off else {"rel": 1e-7, "abs": 1e-12}
        assert distributed[key] == pytest.approx(value, **tolerance), key


@pytest.mark.slow
def test_inflate_sphere(tmp_path, monkeypatch):
    page = executed("inflate_sphere", monkeypatch)
    numbers = glued(page)
    assert pictures(page) == 1
    percent, error = quoted(
        rf"drives this sphere to {NUMBER} % of its limit-point pressure\. It agrees with the closed form to "
        rf"{NUMBER} of P_max"
    )
    assert rounds_to(percent, numbers["percent"]) and rounds_to(error, numbers["error"])
    same_as_one_rank(run("inflate_sphere", tmp_path, 2), numbers)


@pytest.mark.slow
def test_breathing_cycle(tmp_path, monkeypatch):
    page = executed("breathing_cycle", monkeypatch)
    numbers = glued(page)
    assert pictures(page) == 2
    assert numbers["spontaneous_unloaded"] == pytest.approx(numbers["ventilated_unloaded"], rel=1e-12)
    same_as_one_rank(run("breathing_cycle", tmp_path, 2), numbers, round_off={"difference"})


@pytest.mark.slow
def test_reduced_lung(monkeypatch):
    page = executed("reduced_lung", monkeypatch)
    numbers = glued(page)
    assert pictures(page) == 1
    assert numbers["basis"] < numbers["snapshots"]


@pytest.mark.slow
def test_parameter_sweep(monkeypatch):
    page = executed("parameter_sweep", monkeypatch)
    assert glued(page)["calls"] == 0
    assert pictures(page) == 1


@pytest.mark.slow
def test_register_lung(monkeypatch):
    page = executed("register_lung", monkeypatch)
    numbers = glued(page)
    assert pictures(page) == 3
    assert numbers["worst_dice"] > 0.98 and 0 < numbers["new_volume"] < 5


@pytest.mark.slow
def test_pgd_lung(monkeypatch):
    page = executed("pgd_lung", monkeypatch)
    numbers = glued(page)
    assert pictures(page) == 3
    assert numbers["worst"] < 1e-4 and numbers["modes"] <= 5  # the target: ≤ 1e-4 with ≤ 5 modes
    for k in (1, 2):
        assert sum(numbers[f"mode{k}_{axis}"] for axis in "xyz") == pytest.approx(1.0)


def test_a_demo_leaves_a_users_folder_alone(tmp_path):
    """-o naming a folder of the user's: one line, exit code 2, and the folder as it was."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("theirs")
    command = [sys.executable, str(DEMOS / "inflate_sphere.py"), "-o", str(tmp_path / "mine")]
    done = subprocess.run(command, env=os.environ | ENV, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("inflate_sphere: error:") and "mine" in done.stderr
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]
    assert (tmp_path / "mine" / "notes.txt").read_text() == "theirs"
