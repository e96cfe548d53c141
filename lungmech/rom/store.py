"""Reduced models on disk: plain arrays and JSON metadata in one ``.npz`` (nothing pickled).

Vectors are written in the canonical dof order of :mod:`lungmech.rom.layout`, so a basis built on
any number of ranks loads on any other; the mesh fingerprint is checked on loading.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from lungmech.errors import ParameterError
from lungmech.rom.basis import Basis
from lungmech.rom.layout import layout

FORMAT = "lungmech-rom/1"


def save(path: str | Path, model, basis: Basis, extra: dict | None = None, arrays: dict | None = None) -> Path:
    """Write ``basis`` (and any ``extra`` metadata / named canonical ``arrays``) to ``path``.

    Collective; rank 0 writes, atomically (a temporary file renamed into place).
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise ParameterError(f"reduced models are saved as .npz (got {path.name})")
    where = layout(model.space)
    if where.fingerprint != basis.fingerprint:
        raise ParameterError("save: the basis does not belong to this model's mesh and space")
    vectors = where.gather(basis.vectors)
    metadata = {
        "format": FORMAT,
        "kind": basis.kind,
        "size": basis.size,
        "inner_product": basis.inner_product,
        "fingerprint": basis.fingerprint,
        "dofs": where.size,
        "source": basis.source,
        "extra": extra or {},
    }
    if where.comm.rank == 0:
        path.parent.mkdir(parents=True, exist_ok=True)
        staging = path.with_name(f".{path.stem}.partial.npz")
        np.savez(staging, vectors=vectors, values=basis.values, metadata=json.dumps(metadata), **(arrays or {}))
        os.replace(staging, path)
    where.comm.Barrier()
    return path


def read(path: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The metadata and arrays of a reduced-model file, checked to be one (any mesh)."""
    path = Path(path)
    if not path.is_file():
        raise ParameterError(f"reduced model file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            metadata = json.loads(str(data["metadata"]))
            arrays = {name: data[name] for name in data.files if name != "metadata"}
    except (OSError, ValueError, KeyError) as error:
        raise ParameterError(f"{path} is not a lungmech reduced model ({error})") from None
    if metadata.get("format") != FORMAT:
        raise ParameterError(f"{path} is not a lungmech reduced model (format {metadata.get('format')!r})")
    return metadata, arrays


def load(path: str | Path, model) -> tuple[Basis, dict, dict[str, np.ndarray]]:
    """Read a reduced model for ``model``: (basis, extra metadata, other arrays).

    Refused with a :class:`ParameterError` when the file is not a lungmech reduced model or was
    built on another mesh or space.
    """
    metadata, arrays = read(path)
    where = layout(model.space)
    if metadata["fingerprint"] != where.fingerprint or metadata["dofs"] != where.size:
        raise ParameterError(
            f"{path} was built on another mesh or discretisation ({metadata['dofs']} dofs, fingerprint "
            f"{metadata['fingerprint']}); this model has {where.size} dofs, fingerprint {where.fingerprint}"
        )
    vectors, values = arrays.pop("vectors"), arrays.pop("values")
    basis = Basis(
        where.scatter(vectors), values, metadata["kind"], metadata["inner_product"], where.fingerprint,
        metadata["source"],
    )
    return basis, metadata["extra"], arrays
