"""A demo is three things at once: a script a user runs, a page of the documentation, and a test.

The demos in ``demos/`` are literate scripts (jupytext's percent format: ``# %%`` code cells,
``# %% [markdown]`` prose). :class:`Demo` owns a demo's output folder and the numbers it
reports, and behaves as each use needs:

* run as a script (``python demos/<name>.py [-o FOLDER]``, also under ``mpiexec``): the folder
  is ``-o`` (default ``demos/output/<name>``), staged by
  :func:`~lungmech.parallel.destination.output_folder` so that nothing of the user's is ever
  overwritten, and moved into place by :meth:`Demo.close`; a number is a line printed on rank 0,
  and all of them are written to ``numbers.json``;
* executed as a notebook (the documentation's build, myst-nb, or the tests through the same
  jupyter-cache): the folder is a fresh temporary one; a number is also *glued* (myst-nb's
  ``glue``), so that the page's prose shows the value of this very run (``{glue:text}`key```),
  and a picture is shown on the page.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from mpi4py import MPI

from lungmech.errors import LungmechError
from lungmech.parallel.destination import output_folder

__all__ = ["Demo", "in_notebook"]

NUMBERS = "numbers.json"


def in_notebook() -> bool:
    """Whether this code runs in a Jupyter kernel (a notebook's execution), not as a script."""
    shell = sys.modules.get("IPython") and sys.modules["IPython"].get_ipython()
    return bool(shell) and "IPKernelApp" in getattr(shell, "config", {})


class Demo:
    """The output folder of the demo ``name`` and the numbers it reports (see the module).

    Args:
        name: the demo's file name without ``.py``.
        inputs: the files it reads (the output folder may not hold them).
        flags: the script's switches beyond ``-o``, ``{"cli": "help text"}`` for ``--cli``; all
            off in a notebook. :attr:`flags` says which are on.
        comm: the ranks that run it.
    """

    def __init__(
        self,
        name: str,
        inputs: Sequence[str | Path] = (),
        flags: Mapping[str, str] | None = None,
        comm: MPI.Comm = MPI.COMM_WORLD,
    ) -> None:
        self.name, self.comm = name, comm
        self.notebook = in_notebook()
        self.flags = dict.fromkeys(flags or {}, False)
        if self.notebook:
            self.target = Path(tempfile.mkdtemp(prefix=f"lungmech-{name}-")) / "output"
        else:
            parser = argparse.ArgumentParser(description=f"lungmech's demo {name} (a page of its documentation)")
            default = Path(sys.argv[0]).resolve().parent / "output" / name
            parser.add_argument("-o", "--output", type=Path, default=default, help="output folder (%(default)s)")
            for flag, text in (flags or {}).items():
                parser.add_argument(f"--{flag}", action="store_true", help=text)
            arguments = vars(parser.parse_args())
            self.target = arguments.pop("output")
            self.flags = {flag: bool(arguments[flag.replace("-", "_")]) for flag in self.flags}
        self._open = contextlib.ExitStack()
        try:
            self.folder: Path = self._open.enter_context(
                output_folder(self.target, comm, inputs=inputs, command=f"python demos/{name}.py")
            )
        except LungmechError as error:  # a folder of the user's, say: one line, as the command line says it
            if self.notebook:
                raise
            if comm.rank == 0:
                print(f"{name}: error: {error}", file=sys.stderr)
            raise SystemExit(2) from None
        self.numbers: dict[str, float] = {}

    def report(self, key: str, value: float, line: str = "") -> float:
        """Keep ``value`` as ``key`` and print ``line`` on rank 0; in a notebook, glue it too."""
        value = float(value)
        self.numbers[key] = value
        if line and self.comm.rank == 0:
            print(line, flush=True)
        if self.notebook:
            with contextlib.suppress(ImportError):  # a notebook opened outside the docs' build
                from myst_nb import glue

                glue(key, value, display=False)
        return value

    def figure(self, figure: Any, filename: str) -> Path:
        """Save the matplotlib ``figure`` as ``filename`` in the folder (rank 0) and show it."""
        if self.comm.rank == 0:
            figure.savefig(self.folder / filename, dpi=120)
        import matplotlib.pyplot as plt

        plt.close(figure)
        return self.show(filename)

    def show(self, filename: str) -> Path:
        """Show the picture ``filename`` of the folder on the page (in a notebook; else nothing)."""
        if self.notebook and self.comm.rank == 0:
            from IPython.display import Image, display

            display(Image(filename=str(self.folder / filename)))
        return self.folder / filename

    def close(self) -> None:
        """Write the numbers to ``numbers.json`` and move the folder into place."""
        if self.comm.rank == 0:
            (self.folder / NUMBERS).write_text(json.dumps(self.numbers, indent=2) + "\n")
        self._open.close()
        if self.comm.rank == 0 and not self.notebook:
            print(f"wrote {self.target}")
