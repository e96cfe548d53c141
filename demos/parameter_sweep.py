# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # A parameter sweep of the breathing lung, compiled once
#
# The bundled breathing scene (`lungmech/scenes/lung_breathing.toml`), without the tissue's
# weight, gets two parameters μ: `stiffness`, the skeleton's $c_1$ (Pa), and `pleural`, the
# pleural pressure at end-expiration (Pa; the breath doubles it). One `FullOrderModel` solves
# the 3 × 3 grid of them: its forms hold every parameter in a `Constant`, so they are compiled
# once, and the sweep counts the FFCx calls it makes after the build.
#
# At every point the mesh is the lung *imaged* at end-expiration: each solve finds the unloaded
# reference for its own stiffness and pressure (the scene's `[inverse]`), as
# `lungmech run --set` does, one problem ([parameters](../guide/parameters.md)).
#
# Run it as `python demos/parameter_sweep.py [-o FOLDER] [--cli]`; with `--cli` it also runs
# the grid through `lungmech run SCENE --set ...` in fresh processes sharing a new FFCx cache,
# and prints the compiled forms in that cache after each run: only the first run adds any.

# %%
import copy
import os
import subprocess
import sys
import tempfile
import tomllib
from importlib import resources
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
from mpi4py import MPI

import matplotlib.pyplot as plt
import numpy as np

from lungmech.app import scene as scenes
from lungmech.app.demo import Demo
from lungmech.app.run import full_order_model

demo = Demo("parameter_sweep", flags={"cli": "also sweep through 'lungmech run --set' in fresh processes"})
comm = MPI.COMM_WORLD
STIFFNESS = (100.0, 200.0, 400.0)  # Pa, c1 of the skeleton
PLEURAL = (-300.0, -500.0, -700.0)  # Pa at end-expiration

# %% [markdown]
# ## The scene and its parameters
#
# A parameter names the scene key it sets (`target`) and its range; the sweep gives its
# values by name.

# %%
with resources.as_file(resources.files("lungmech.scenes") / "lung_breathing.toml") as path:
    table = copy.deepcopy(tomllib.loads(Path(path).read_text()))
table["loads"][0]["name"] = "pleural"
# Without the tissue's weight: balancing it costs a fixed point of Newton solves per step (until
# the coefficients join the Newton solve), and the sweep is about stiffness and pressure.
table["loads"] = [load for load in table["loads"] if load["type"] != "gravity"]
table["parameters"] = {
    "stiffness": {"target": "material.c1", "range": [50.0, 800.0], "scale": "log"},
    "pleural": {"target": "loads.pleural.value", "range": [-1000.0, -200.0]},
}
table["output"] = {"fields": False}

# %% [markdown]
# ## The sweep
#
# `full.solve(μ)` answers one point: the unloaded reference, then the breath. The tidal volume
# is the end-inspiration volume ($t = 1$) minus the end-expiration one ($t = 2$).

# %%
import dolfinx.jit  # noqa: E402  (after lungmech, which orders MPI before DOLFINx's bindings)

full = full_order_model(scenes.parse(table), comm)
calls = []
compile_forms = dolfinx.jit.ffcx_jit
dolfinx.jit.ffcx_jit = lambda *args, **kwargs: calls.append(1) or compile_forms(*args, **kwargs)
try:
    tidal = np.zeros((len(PLEURAL), len(STIFFNESS)))
    for i, pleural in enumerate(PLEURAL):
        for j, stiffness in enumerate(STIFFNESS):
            solution = full.solve({"stiffness": stiffness, "pleural": pleural})
            volume = dict(zip(solution.times, solution.outputs["volume"]))
            tidal[i, j] = (volume[1.0] - volume[2.0]) * 1e3
            demo.report(f"tidal_{i}_{j}", tidal[i, j])
finally:
    dolfinx.jit.ffcx_jit = compile_forms
if comm.rank == 0:
    print("tidal volume [L] (rows: pleural pressure at end-expiration [Pa]; columns: c1 [Pa])")
    print("          " + "".join(f"{s:>10g}" for s in STIFFNESS))
    for pleural, row in zip(PLEURAL, tidal):
        print(f"{pleural:>10g}" + "".join(f"{v:>10.4f}" for v in row))
demo.report("calls", len(calls), f"FFCx calls during the 9-point Python sweep: {len(calls)}")
assert not calls, f"the sweep compiled {len(calls)} forms after the model was built"
# A softer skeleton and a deeper breath both inhale more.
assert np.all(np.diff(tidal, axis=1) < 0) and np.all(np.diff(tidal, axis=0) > 0)

# %% [markdown]
# The sweep made {glue:text}`calls:.0f` FFCx calls after the model was built. Tidal volume (L),
# the pleural pressure doubling in the breath:
#
# | pleural pressure at end-expiration | $c_1$ = 100 Pa | 200 Pa | 400 Pa |
# |---|---|---|---|
# | −300 Pa | {glue:text}`tidal_0_0:.4f` | {glue:text}`tidal_0_1:.4f` | {glue:text}`tidal_0_2:.4f` |
# | −500 Pa | {glue:text}`tidal_1_0:.4f` | {glue:text}`tidal_1_1:.4f` | {glue:text}`tidal_1_2:.4f` |
# | −700 Pa | {glue:text}`tidal_2_0:.4f` | {glue:text}`tidal_2_1:.4f` | {glue:text}`tidal_2_2:.4f` |
#
# Doubling $c_1$ takes only a few per cent off the breath: $c_1$ is one of several terms of the
# skeleton's energy (the others stay). The breath grows nearly in proportion to the pleural
# pressure.

# %%
figure, axes = plt.subplots(figsize=(5.5, 4))
for pleural, row in zip(PLEURAL, tidal):
    axes.plot(STIFFNESS, row, "o-", label=f"{pleural:g} Pa → {2 * pleural:g} Pa")
axes.set_xscale("log")
axes.set_xticks(STIFFNESS, [f"{s:g}" for s in STIFFNESS])
axes.minorticks_off()
axes.set_ylim(0.0, 1.05 * tidal.max())
axes.set_xlabel("skeleton stiffness c1 [Pa]")
axes.set_ylabel("tidal volume [L]")
axes.set_title("Right lung phantom, imaged at end-expiration: tidal volume of one breath", fontsize=10)
axes.legend(title="pleural pressure, expiration → inspiration", fontsize=8, title_fontsize=8, loc="lower left")
figure.tight_layout()
demo.figure(figure, "parameter_sweep.png")


# %% [markdown]
# ## The same grid from the command line (`--cli`)
#
# Nine `lungmech run --set` processes share a fresh FFCx cache; the count of compiled forms
# in it after each run shows that only the first compiles.


# %%
def toml(table: dict) -> str:
    """A small TOML writer for the scene (tomllib reads only)."""

    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + "}"
        return repr(v)

    lines = [f"title = {value(table.get('title', ''))}"]
    for key, section in table.items():
        if isinstance(section, dict) and key != "parameters":
            lines += [f"[{key}]", *(f"{k} = {value(v)}" for k, v in section.items())]
        elif isinstance(section, list):
            for entry in section:
                lines += [f"[[{key}]]", *(f"{k} = {value(v)}" for k, v in entry.items())]
    for name, entry in table.get("parameters", {}).items():
        lines += [f"[parameters.{name}]", *(f"{k} = {value(v)}" for k, v in entry.items())]
    return "\n".join(lines) + "\n"


if demo.flags["cli"] and comm.rank == 0:
    scene = demo.folder / "lung_sweep.toml"
    scene.write_text(toml(table))
    cache = Path(tempfile.mkdtemp(prefix="lungmech-ffcx-"))
    environment = os.environ | {"XDG_CACHE_HOME": str(cache)}
    counts = []
    for pleural in PLEURAL:
        for stiffness in STIFFNESS:
            run = [sys.executable, "-m", "lungmech.app.cli", "run", str(scene), "-q"]
            run += ["-o", str(demo.folder / f"run_{stiffness:g}_{pleural:g}")]
            run += ["--set", f"stiffness={stiffness}", "--set", f"pleural={pleural}"]
            subprocess.run(run, check=True, env=environment, stdout=subprocess.DEVNULL)
            counts.append(sum(1 for _ in cache.rglob("*.so")))
    print(f"compiled forms in the fresh FFCx cache after each of the 9 CLI runs: {counts}")
demo.close()
