"""Benchmarks that cannot rot: each one's --quick case runs here, in a fresh process, writing its
markdown, CSV and plot into a temporary folder (LUNGMECH_BENCHMARK_RESULTS) — never over the
measured results in benchmarks/results, which the docs quote."""

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
HELPERS = {"case", "handwritten", "machine", "resumable"}  # run by the benchmarks, not benchmarks themselves
# --quick cases: the command's arguments and the stem of the files it writes
QUICK = {
    "run": (["--quick"], "discretisation"),
    "cook": (["--quick"], "cook_quick"),
    "rom_process": (["--quick"], "rom_process_quick"),
    "ecsw_block": (["--quick"], "ecsw_block_quick"),
    "paired": (["--quick"], "overhead_paired_quick"),
    "layout": (["--quick"], "layout/layout_quick"),
    "large_lung": (["--quick"], "large_lung_quick"),
    "rom_real_time": (["--quick"], "rom_real_time_quick"),
    "rom_imaged": (["--quick"], "rom_imaged_quick"),
    "rom_parameters": (["--quick"], "rom_parameters_quick"),
    "ecsw_lung": (["--quick"], "ecsw_lung_quick"),
    "registration": (["--quick"], "registration_quick"),
    "rom": (["--quick"], "rom_quick"),
    "ensemble": (["--quick"], "ensemble_quick"),
    "trade": (["--quick"], "trade_quick"),
    "threads": (["--quick"], "threads_quick"),
    "greedy_batch": (["--quick"], "greedy_batch_quick"),
    "twin": (["--quick"], "twin_quick"),
    "population": (["--quick"], "population_quick"),
    "twin_population": (["--quick"], "twin_population_quick"),
    "pgd": (["--quick"], "pgd_quick"),
    "pgd_tangent": (["--quick"], "pgd_tangent_quick"),
}


def _scripts() -> list[str]:
    return sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem not in HELPERS)


def test_every_benchmark_has_a_quick_case_in_the_suite():
    assert sorted(QUICK) == _scripts()  # each ≤ 60 s (in all about 7 min of the one-rank run)
    for name in QUICK:
        tree = ast.parse((BENCHMARKS / f"{name}.py").read_text())
        options = {
            a.value for n in ast.walk(tree) if isinstance(n, ast.Call) for a in n.args if isinstance(a, ast.Constant)
        }
        assert "--quick" in options, name


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(QUICK))
def test_a_quick_benchmark_runs_and_writes_its_results_elsewhere(name, tmp_path):
    arguments, stem = QUICK[name]
    measured = {p: p.stat().st_mtime_ns for p in (BENCHMARKS / "results").rglob("*") if p.is_file()}
    environment = os.environ | {"LUNGMECH_BENCHMARK_RESULTS": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / f"{name}.py"), *arguments],
        env=environment,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    for suffix in (".md", ".csv"):
        assert (tmp_path / f"{stem}{suffix}").stat().st_size > 0, suffix
    assert (tmp_path / f"{stem}.png").stat().st_size > 0, "no plot"
    after = {p: p.stat().st_mtime_ns for p in (BENCHMARKS / "results").rglob("*") if p.is_file()}
    assert after == measured, "a --quick run changed benchmarks/results"
