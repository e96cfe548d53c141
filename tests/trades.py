"""The bundled small scene to trade on (a thick sphere octant inflated from inside and let out
again, its stiffness a parameter), varied for tests/test_trade.py and tests/test_trade_cli.py."""

from importlib import resources
from pathlib import Path

from mpi4py import MPI

BUNDLED = resources.files("lungmech.scenes") / "sphere_inflation_parameters.toml"


def written(
    folder: Path,
    low: float = 5.0,
    min_step: float = 1e-3,
    pressure: float = 0.5,
    name: str = "sphere.toml",
    mesh_size: float = 0.4,
) -> Path:
    """The scene file ``name`` in ``folder``: stiffness E in [``low``, 20] Pa, ``pressure`` Pa
    inside, cells of ``mesh_size`` m; written by rank 0 (under MPI the ranks share ``folder``: one
    writer, then all read)."""
    path = folder / name
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(_varied(BUNDLED.read_text(), low, min_step, pressure, mesh_size))
    MPI.COMM_WORLD.Barrier()
    return path


def _varied(text: str, low: float, min_step: float, pressure: float, mesh_size: float) -> str:
    """The bundled scene's text with its stiffness range, smallest step, pressure and mesh size
    replaced."""
    for old, new in (
        ("range = [5.0, 20.0]", f"range = [{low}, 20.0]"),
        ("mesh_size = 0.4", f"mesh_size = {mesh_size}"),
        ("min_step = 1e-3", f"min_step = {min_step}"),
        ("value = 0.5 ", f"value = {pressure} "),
    ):
        if old not in text:
            raise AssertionError(f"the bundled sphere scene no longer holds {old!r}")
        text = text.replace(old, new, 1)
    return text
