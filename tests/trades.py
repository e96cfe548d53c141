"""A small scene to trade on: a thick sphere octant inflated from inside and let out again,
its stiffness a parameter (tests/test_trade.py, tests/test_trade_cli.py)."""

from pathlib import Path

from mpi4py import MPI

SCENE = """
title = "a thick sphere octant inflated from inside"
[geometry]
builder = "sphere"
inner_radius = 0.5
outer_radius = 1.0
mesh_size = 0.4
[material]
law = "neo_hookean"
E = 10.0
nu = 0.3
[[constraints]]
type = "symmetry"
boundary = "x0"
component = 0
[[constraints]]
type = "symmetry"
boundary = "y0"
component = 1
[[constraints]]
type = "symmetry"
boundary = "z0"
component = 2
[[loads]]
type = "follower_pressure"
name = "inner"
boundary = "inner"
value = {pressure}
ramp = {{ times = [0.0, 1.0, 2.0], values = [0.0, 1.0, 0.5] }}
[stepping]
end = 2.0
max_step = 0.5
min_step = {min_step}
[parameters.stiffness]
target = "material.E"
range = [{low}, 20.0]
[output]
probes = [[0.5, 0.0, 0.0]]
"""


def written(
    folder: Path, low: float = 5.0, min_step: float = 1e-3, pressure: float = 0.5, name: str = "sphere.toml"
) -> Path:
    """The scene file ``name`` in ``folder``: stiffness E in [``low``, 20] Pa, ``pressure`` Pa
    inside; written by rank 0 (under MPI the ranks share ``folder``: one writer, then all read)."""
    path = folder / name
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(SCENE.format(low=low, min_step=min_step, pressure=pressure))
    MPI.COMM_WORLD.Barrier()
    return path
