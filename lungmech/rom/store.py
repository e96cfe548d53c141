"""Reduced models on disk: plain arrays and JSON metadata in one ``.npz`` (nothing pickled).

A model file is data: it is read with ``allow_pickle=False``, and its SHA-256 digest covers every
array (names, dtypes, shapes, bytes) and every metadata field, so that a file changed after
lungmech wrote it — damaged, or edited — is refused on reading. The digest is a check against
accidents and edits, not a signature: whoever edits a file can also recompute it, so a model
file is trusted no further than its source, and what it holds is checked as data (its embedded
file names, :func:`lungmech.app.model_file.embedded_scene`; its basis, on loading).

Vectors are written in the canonical dof order of :mod:`lungmech.parallel.layout`, so a basis built on
any number of ranks loads on any other; the mesh fingerprint is checked on loading. Rank 0 alone
holds a whole vector: it gathers the rows to write them, and reads the file and sends every rank
its rows on loading.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from collections.abc import Callable, Sequence
from os import PathLike
from pathlib import Path

from mpi4py import MPI

import numpy as np

from lungmech.errors import ModelFileError, ParameterError
from lungmech.fem.model import Model
from lungmech.fem.quantities import Probe
from lungmech.fem.solver import NewtonOptions, Stepping
from lungmech.fem.start import StartReport
from lungmech.mesh import nodes
from lungmech.mesh.geometry import Geometry
from lungmech.parallel import on_root, together
from lungmech.parallel.destination import output_file
from lungmech.parallel.layout import layout
from lungmech.parallel.linalg import apply, gram
from lungmech.parallel.owned import owned_size
from lungmech.rom import body, imaged
from lungmech.rom.basis import Basis, inner_product
from lungmech.rom.ecsw import Sample
from lungmech.rom.hyper_reduced import HyperReducedSolver
from lungmech.rom.reduced import ReducedModel
from lungmech.rom.whole import OnMesh, Stored

# 2: canonical order, the scene and its files inside; 3: the digest covers the metadata; 4: the reduced
# model's own record (its start, how it was built) and its arrays written by rom.store itself; 5: a
# hyper-reduced model's body (its sampled cells) and what it needs of the whole body; 6: the indicator's
# Gram matrix of the basis and its enrichment together
FORMAT = "lungmech-rom/6"
_DIGESTED = ("lungmech-rom/3", "lungmech-rom/4", "lungmech-rom/5")  # older formats whose digest covers the metadata


def save(
    path: str | Path,
    model: Model,
    basis: Basis,
    extra: dict | None = None,
    arrays: dict | None = None,
    inputs: Sequence[str | PathLike] = (),
) -> Path:
    """Write ``basis`` (and any ``extra`` metadata / named canonical ``arrays``) to ``path``.

    Collective. The file is written to a staging name and moved into place; an existing file is
    replaced only if it is a lungmech reduced model (see :mod:`lungmech.parallel.destination`).
    """
    path = suffixed(path)
    with output_file(path, model.geometry.mesh.comm, inputs=inputs, ours=is_model) as staging:
        write(staging, model, basis, extra, arrays)
    return path


def write(path: str | Path, model: Model, basis: Basis, extra: dict | None = None, arrays: dict | None = None) -> None:
    """Collective: write the model file at ``path`` as it is (no checks; :func:`save` checks).

    ``arrays`` are canonical arrays, read on rank 0 only (the other ranks may pass None values).
    """
    where = layout(model.space)
    if where.fingerprint != basis.fingerprint:
        raise ParameterError("save: the basis does not belong to this model's mesh and space")
    vectors = where.gather(basis.vectors)

    def written() -> None:
        content = {"vectors": vectors, "values": basis.values, **(arrays or {})}
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
        metadata["sha256"] = digest(metadata, content)
        np.savez(path, metadata=json.dumps(metadata), **content)

    on_root(where.comm, written)


def is_model(path: str | Path) -> bool:
    """Whether ``path`` is a lungmech reduced-model file (any mesh, this format or an older one
    with a digest), unchanged since it was written."""
    try:
        read(path, any_version=True)
    except ModelFileError:
        return False
    return True


def digest(metadata: dict, arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 of a model file's content: its metadata but the digest itself (as canonical JSON),
    then its named arrays (names, dtypes, shapes and bytes, in name order)."""
    sha = hashlib.sha256()
    fields = {key: value for key, value in metadata.items() if key != "sha256"}
    sha.update(json.dumps(fields, sort_keys=True, separators=(",", ":")).encode())
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        sha.update(f"{name}:{array.dtype.str}:{array.shape};".encode())
        sha.update(array.data)  # the bytes in place: no copy of a large basis
    return sha.hexdigest()


def suffixed(path: str | Path) -> Path:
    """``path`` as a model file's name (.npz), or refused in one line."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ParameterError(f"model files are saved as .npz (got {path.name or path})")
    return path


class _Older(Exception):
    """A reduced-model file of another format version."""


class _Changed(Exception):
    """A reduced-model file whose content is not what lungmech wrote (its digest differs)."""


def read(path: str | Path, arrays: bool = True, any_version: bool = False) -> tuple[dict, dict[str, np.ndarray | None]]:
    """The metadata and arrays of a reduced-model file, checked to be one (any mesh) and unchanged
    since lungmech wrote it (its digest). With ``arrays=False`` the arrays are read for the
    digest only, and their names map to None. ``any_version``: a file of an older format (3 on,
    whose digest covers its metadata) is one too (to be replaced, not read)."""
    wanted = arrays
    path = Path(path)
    if path.is_dir():
        raise ModelFileError(f"reduced model '{path}' is a folder; name the .npz file 'lungmech rom build' wrote")
    if not path.is_file():
        raise ModelFileError(f"reduced model file not found: {path}")
    if not zipfile.is_zipfile(path):
        raise ModelFileError(f"'{path}' is not a lungmech reduced model (not an .npz archive, or a truncated one)")
    try:
        with np.load(path, allow_pickle=False) as data:
            metadata = json.loads(str(data["metadata"]))
            if isinstance(metadata, dict) and str(metadata.get("format", "")).startswith("lungmech-rom/"):
                if metadata["format"] != FORMAT and not (any_version and metadata["format"] in _DIGESTED):
                    raise _Older(metadata["format"])
            if not isinstance(metadata, dict) or metadata.get("format") not in (FORMAT, *_DIGESTED):
                raise ValueError(
                    f"format {metadata.get('format') if isinstance(metadata, dict) else None!r}, expected {FORMAT!r}"
                )
            content = {name: data[name] for name in data.files if name != "metadata"}
        if metadata.get("sha256") != digest(metadata, content):
            raise _Changed()
        found: dict[str, np.ndarray | None] = dict(content) if wanted else dict.fromkeys(content)
        for key in ("vectors", "values"):
            if key not in found:
                raise KeyError(f"no array '{key}'")
        for key in ("kind", "inner_product", "fingerprint", "dofs", "extra"):
            if key not in metadata:
                raise KeyError(f"no '{key}' in its metadata")
    except _Older as older:
        raise ModelFileError(
            f"'{path}' was written by another lungmech version (format {older}, this one reads {FORMAT}); "
            "rebuild it with 'lungmech rom build'"
        ) from None
    except _Changed:
        raise ModelFileError(
            f"'{path}' was changed after lungmech wrote it (its SHA-256 digest does not match its content): "
            "rebuild it with 'lungmech rom build', or use an unchanged copy"
        ) from None
    except Exception as error:  # zipfile, zlib, json and numpy raise many kinds on a damaged file
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise ModelFileError(f"'{path}' is not a lungmech reduced model, or is damaged ({reason})") from None
    return metadata, found


def read_on_root(path: str | Path, comm: MPI.Comm, arrays: bool = True) -> tuple[dict, dict[str, np.ndarray | None]]:
    """Collective: :func:`read` on rank 0 only. The metadata on every rank; the arrays on rank 0,
    and the same names with None on the others. An error reading is raised on every rank."""
    found = on_root(comm, lambda: read(path, arrays))
    metadata, names = comm.bcast((found[0], sorted(found[1])) if found is not None else None)
    return metadata, found[1] if found is not None else dict.fromkeys(names)


def load(
    path: str | Path, model: Model, content: tuple[dict, dict] | None = None
) -> tuple[Basis, dict, dict[str, np.ndarray | None]]:
    """Collective: read a reduced model for ``model``: (basis, extra metadata, other arrays).

    Rank 0 reads the file and sends every rank its rows of the basis; the other arrays (canonical,
    for :meth:`~lungmech.parallel.layout.Layout.scatter`) are returned on rank 0, with the same
    names but None on the other ranks. Refused with a :class:`ModelFileError` when the file is not
    a lungmech reduced model, is damaged, or was built on another mesh or space. ``content``: what
    :func:`read_on_root` gave, when the caller has read the file already.
    """
    where = layout(model.space)
    metadata, arrays = content if content is not None else read_on_root(path, where.comm)
    arrays = dict(arrays)
    if metadata["fingerprint"] != where.fingerprint or metadata["dofs"] != where.size:
        raise ModelFileError(
            f"{path} was built on another mesh or discretisation ({metadata['dofs']} dofs, fingerprint "
            f"{metadata['fingerprint']}); this model has {where.size} dofs, fingerprint {where.fingerprint}"
        )
    vectors, values = arrays.pop("vectors"), arrays.pop("values")
    with together(where.comm):  # only rank 0 holds the arrays to check
        if vectors is not None:
            assert values is not None  # (rank 0 holds both)
            _check_basis(path, vectors, values, where.size)
    basis = Basis(
        where.scatter(vectors),
        where.comm.bcast(values),
        metadata["kind"],
        metadata["inner_product"],
        where.fingerprint,
        metadata["source"],
    )
    return basis, metadata["extra"], arrays


def _check_basis(path: str | Path, vectors: np.ndarray, values: np.ndarray, dofs: int) -> None:
    if vectors.ndim != 2 or vectors.shape[0] != dofs or values.shape != (vectors.shape[1],):
        raise ModelFileError(
            f"'{path}' is damaged: its basis has shape {vectors.shape} and {values.size} values, for {dofs} dofs"
        )
    if not (np.isfinite(vectors).all() and np.isfinite(values).all()):
        raise ModelFileError(f"'{path}' is damaged: its basis holds values that are not finite numbers")


ORTHONORMAL = 1e-8  # |VᵀWV − I| a loaded basis may have: Gram–Schmidt twice leaves ~1e-14


def hyper_record(reduced: ReducedModel) -> dict | None:
    """How a reduced model is hyper-reduced, for its record and its build's summary (None if it
    is not): the method, τ, the sampled cells per name and in words, the mesh's cells, the judge."""
    if reduced.sample is None:
        return None
    comm = reduced.model.geometry.mesh.comm
    mesh = reduced.model.geometry.mesh
    return {
        "method": "ecsw",
        "tolerance": reduced.sample.tolerance,
        "samples": reduced.sample.count(comm),
        "described": reduced.sample.described(comm),
        "cells": mesh.topology.index_map(mesh.topology.dim).size_global,
        "judge": (reduced.built.get("hyper") or {}).get("judge"),
    }


def write_reduced(
    path: str | Path, reduced: ReducedModel, extra: dict | None = None, arrays: dict | None = None
) -> None:
    """Collective: the reduced model ``reduced`` as a model file at ``path`` (no checks: the caller
    stages the file, :mod:`lungmech.parallel.destination`). It holds the basis, the start state,
    the enrichment, an ECSW sample (partition-independent), the training points, what the start
    is (:class:`~lungmech.fem.start.StartReport`) and how the reductor built it (``built``); the
    caller's ``extra`` metadata and canonical ``arrays`` beside them. The mesh's current nodes are
    kept as ``reference_nodes`` (a reference moved from the mesh as built, say). A hyper-reduced
    model also keeps its body, the sampled cells with its rows there (:mod:`lungmech.rom.body`),
    and what it needs of the whole body (:mod:`lungmech.rom.whole`): :func:`load_body` loads it
    with no full mesh."""
    model = reduced.model
    where = layout(model.space)
    owned = reduced.basis.vectors.shape[0]
    enrichment = reduced.enrichment if reduced.enrichment is not None else np.zeros((owned, 0))
    content = {"start": where.gather(reduced.start[:owned]), "enrichment": where.gather(enrichment)}
    content["reference_nodes"] = nodes.positions(*nodes.displacement_space(model.geometry.mesh))
    if reduced.sample is not None:
        mesh = model.geometry.mesh
        content |= {f"ecsw/{name}": data for name, data in reduced.sample.export(mesh).items()}
        content |= _body(reduced)
    hyper = hyper_record(reduced)
    start = reduced.described
    record = {
        "start": {"kind": start.kind, "description": start.description, "details": start.details},
        "training": reduced.training,
        "hyper": hyper,
        "built": reduced.built,
        "body": None if reduced.sample is None else _whole_body(model),
    }
    if reduced.image is not None:  # an imaged body's reduced inverse motion, its start at every μ
        record["image"], held = imaged.exported(reduced.image)
        content |= held
    write(path, model, reduced.basis, extra=(extra or {}) | {"reduced": record}, arrays=content | (arrays or {}))


def load_reduced(
    path: str | Path,
    model: Model,
    stepping: Stepping,
    newton: NewtonOptions | None = None,
    probes: Sequence[Sequence[float]] | Probe = (),
    content: tuple[dict, dict] | None = None,
) -> ReducedModel:
    """Collective: the reduced model of the file at ``path`` on ``model`` (built on the mesh the
    file was made for, whose nodes it puts where the build had them), with the load path
    ``stepping``, Newton ``newton`` options and ``probes`` (points, or a located
    :class:`~lungmech.fem.quantities.Probe`). Refused in one line when the file is not one
    (:func:`load`), or its basis is not orthonormal in its inner product (the projection's
    premise). ``content``: what :func:`read_on_root` gave, when the caller has read the file."""
    comm = model.geometry.mesh.comm
    metadata, arrays = content if content is not None else read_on_root(path, comm)
    record = metadata["extra"].get("reduced")
    if not isinstance(record, dict) or "start" not in record:
        raise ModelFileError(f"'{path}' is damaged: it holds no record of its reduced model; rebuild it")
    nodes.place_canonical(*nodes.displacement_space(model.geometry.mesh), arrays["reference_nodes"])
    basis, _, arrays = load(path, model, content=(metadata, arrays))  # checked on the mesh as placed
    check_orthonormal(path, model, basis)
    where = layout(model.space)
    owned = basis.vectors.shape[0]
    model.reset()
    model.state.x.array[:owned] = where.scatter(arrays["start"])
    model.state.x.scatter_forward()
    start = model.state.x.array.copy()
    model.set_time(stepping.start)
    sample = None
    if record.get("hyper") is not None:
        data = comm.bcast({name[len("ecsw/") :]: a for name, a in arrays.items() if name.startswith("ecsw/")})
        if "internal_cells" not in data or not all(f"{n}_weights" in data for n in ("internal", "strain_energy")):
            raise ModelFileError(f"'{path}' is damaged: its ECSW sample is incomplete; rebuild it")
        sample = Sample.place(model.geometry.mesh, data, record["hyper"]["tolerance"])
    enrichment = where.scatter(arrays["enrichment"])
    described = StartReport(**record["start"])
    image = None
    if record.get("image") is not None:
        image = imaged.placed(model, record["image"], arrays, newton, str(path))
        check_orthonormal(path, image.inverse, image.basis)
    reduced = ReducedModel(
        model,
        basis,
        stepping,
        newton,
        start,
        probes,
        record.get("training", []),
        sample,
        enrichment,
        described,
        image=image,
    )
    reduced.built = dict(record.get("built", {}))
    return reduced


def _body(reduced: ReducedModel) -> dict[str, np.ndarray]:
    """A hyper-reduced model's body and whole-body operators, as arrays (rank 0's; collective)."""
    assert reduced.sample is not None and isinstance(reduced.solver, HyperReducedSolver)  # (a hyper-reduced model)
    whole, owned = reduced.solver.whole, reduced.basis.vectors.shape[0]
    if not isinstance(whole, OnMesh):
        raise ParameterError("a hyper-reduced model is saved from the full model it was built on")
    reference, imposed, _ = whole.imposed()
    columns = {"basis": reduced.basis.vectors, "start": reduced.start[:owned], "reference": reference[:owned]}
    columns |= {"imposed": imposed[:owned]}
    if reduced.enrichment is not None:
        columns["enrichment"] = reduced.enrichment
    sampled = body.cells_of(reduced.sample)
    if reduced.image is not None:  # and the inverse motion's sampled cells, with its columns
        theirs, more = imaged.body_columns(reduced.image)
        sampled, columns = np.union1d(sampled, theirs).astype(np.int32), columns | more
    cells = body.export(reduced.model, sampled, columns)
    return (cells or {}) | {f"whole/{name}": array for name, array in whole.arrays().items()}


def _whole_body(model: Model) -> dict:
    """What a body's geometry needs of the whole one: its boundaries' names and measures, and its size."""
    geometry, mesh = model.geometry, model.geometry.mesh
    tdim = mesh.topology.dim
    return {
        "boundaries": dict(geometry.boundaries),
        "whole": {"size": geometry.size, "volume": geometry.volume()},
        "cells": mesh.topology.index_map(tdim).size_global,
        "dofs": layout(model.space).size,
    }


def load_body(
    path: str | Path,
    build: Callable[[Geometry], Model],
    stepping: Stepping,
    newton: NewtonOptions | None = None,
    content: tuple[dict, dict] | None = None,
    comm: MPI.Comm = MPI.COMM_WORLD,
) -> ReducedModel:
    """Collective: the hyper-reduced model of the file at ``path`` on its body alone: its sampled
    cells as a mesh of their own, the model on it made by ``build(geometry)`` (the scene's, on that
    geometry), its values there and its whole-body operators from the file, with no full mesh
    (O(sample) work). Its outputs are the model's at the build's probes; it gives no full fields.
    Refused in one line when the file is not one, or holds no body (not hyper-reduced).
    ``content``: what :func:`read_on_root` gave, when the caller has read the file."""
    metadata, arrays = content if content is not None else read_on_root(path, comm)
    record = metadata["extra"].get("reduced")
    if not isinstance(record, dict) or "start" not in record:
        raise ModelFileError(f"'{path}' is damaged: it holds no record of its reduced model; rebuild it")
    if record.get("body") is None:
        raise ModelFileError(
            f"'{path}' is not hyper-reduced: it is solved on its full mesh, not on a body of sampled cells"
        )
    kept = record["body"]
    geometry = body.geometry(arrays, comm, kept["boundaries"], kept["whole"], f"the sampled cells of '{path}'")
    model = build(geometry)
    body.place_functions(model, arrays)
    space = model.space
    local = {name: body.place(space, arrays, name) for name in ("basis", "start", "reference", "imposed")}
    owned = owned_size(space)
    basis = Basis(
        np.ascontiguousarray(local["basis"][:owned]),
        comm.bcast(arrays["values"]),
        metadata["kind"],
        metadata["inner_product"],
        layout(space).fingerprint,
        metadata["source"],
    )
    has_enrichment = comm.bcast(arrays.get("body/enrichment") is not None)
    enrichment = body.place(space, arrays, "enrichment")[:owned] if has_enrichment else None
    data = comm.bcast(_sample_on_body(arrays) if comm.rank == 0 else None)
    sample = Sample.place(geometry.mesh, data, record["hyper"]["tolerance"])
    operators = comm.bcast({n[len("whole/") :]: a for n, a in arrays.items() if n.startswith("whole/")})
    whole = Stored(operators, local["reference"][:, 0], local["imposed"], str(path))
    model.reset()
    model.state.x.array[:] = local["start"][:, 0]
    model.state.x.scatter_forward()
    model.set_time(stepping.start)
    image = None
    if record.get("image") is not None:
        image = imaged.placed(model, record["image"], arrays, newton, str(path), on_body=True)
    reduced = ReducedModel(
        model,
        basis,
        stepping,
        newton,
        model.state.x.array.copy(),
        (),
        record.get("training", []),
        sample,
        enrichment,
        StartReport(**record["start"]),
        whole,
        image,
    )
    reduced.built = dict(record.get("built", {}))
    reduced.full_size = {"dofs": kept["dofs"], "cells": kept["cells"]}
    return reduced


def _sample_on_body(arrays: dict) -> dict[str, np.ndarray]:
    """The ECSW sample's cells as positions in the body (whose cells are the sampled ones, sorted)."""
    cells = arrays["body/cells"]
    data = {name[len("ecsw/") :]: a for name, a in arrays.items() if name.startswith("ecsw/")}
    return {name: np.searchsorted(cells, a) if name.endswith("_cells") else a for name, a in data.items()}


def check_orthonormal(path: str | Path, model: Model, basis: Basis) -> None:
    """Refuse a basis that is not orthonormal in its inner product: |VᵀWV − I| > ORTHONORMAL."""
    comm = model.geometry.mesh.comm
    W = inner_product(model, basis.inner_product)
    try:
        G = gram(basis.vectors, apply(W, np.ascontiguousarray(basis.vectors), comm), comm)
    finally:
        if W is not None:
            W.destroy()
    off = float(np.abs(G - np.eye(basis.size)).max(initial=0.0))
    if not off <= ORTHONORMAL:
        raise ModelFileError(
            f"'{path}' is damaged: its basis is not orthonormal in its {basis.inner_product} inner product "
            f"(|VᵀWV − I| = {off:.1e}, at most {ORTHONORMAL:g}); rebuild it"
        )
