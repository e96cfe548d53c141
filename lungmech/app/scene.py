"""Scene files (TOML): what to model, read and validated into lungmech objects.

A scene declares its geometry, law, formulation, constraints, loads, stepping, solver and
outputs; only what it declares is built. Every unknown key or bad value is a :class:`SceneError`
naming the key, e.g. ``material.nuu: unknown key (expected one of: E, nu)``.
"""

from __future__ import annotations

import copy
import hashlib
import json
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lungmech import checks
from lungmech import mesh as _geometry
from lungmech.app.output import FORMATS as FIELD_FORMATS
from lungmech.app.scene_parameters import ImageLabel, parameters, substituted
from lungmech.app.table_checks import call, check_signature, finite_numbers, no_unknown_keys, section, typed, with_tuple
from lungmech.errors import ParameterError, SceneError
from lungmech.fem.constraints import Displacement, clamp, symmetry
from lungmech.fem.formulations import Formulation, PureDisplacement, TaylorHood
from lungmech.fem.kinematics import PLANES
from lungmech.fem.loads import BodyForce, FollowerPressure, Force, NormalPressure, Traction
from lungmech.fem.materials import LAWS, Material, Sum
from lungmech.fem.parameters import Parameter, Parameters
from lungmech.fem.ramp import Ramp
from lungmech.fem.solver import NewtonOptions, Stepping
from lungmech.lung import AlveolarPressure, Poromechanics, skeleton
from lungmech.lung.gravity import Gravity
from lungmech.lung.inverse import InverseOptions

if TYPE_CHECKING:
    from mpi4py import MPI

SECTIONS = (
    "title",
    "parameters",
    "geometry",
    "material",
    "formulation",
    "constraints",
    "loads",
    "stepping",
    "solver",
    "inverse",
    "output",
)
BUILDERS: dict[str, Callable] = {
    "box": _geometry.box,
    "sphere": _geometry.sphere,
    "ellipsoid": _geometry.ellipsoid,
    "lung_phantom": _geometry.lung_phantom,
    "rectangle": _geometry.rectangle,
    "cook_membrane": _geometry.cook_membrane,
    "quarter_annulus": _geometry.quarter_annulus,
    "plate_with_holes": _geometry.plate_with_holes,
}
LOADS = {
    "body_force": BodyForce,
    "traction": Traction,
    "force": Force,
    "normal_pressure": NormalPressure,
    "follower_pressure": FollowerPressure,
    "alveolar_pressure": AlveolarPressure,
    "gravity": Gravity,
}
FORMULATIONS = {"displacement": PureDisplacement, "mixed": TaylorHood, "poromechanics": Poromechanics}
# Laws made of other laws, by name (their parameters are the builder's arguments).
COMPOSITE_LAWS = {"lung_skeleton": skeleton}
CONSTRAINTS: dict[str, Callable[..., Any]] = {"clamp": clamp, "symmetry": symmetry, "displacement": Displacement}


@dataclass(frozen=True)
class Output:
    """What a run writes besides summary.json and history.csv."""

    fields: bool = True
    probes: tuple[tuple[float, float, float], ...] = ()
    format: str = "vtk"  # of the fields: "vtk" (.pvd/.vtu, read by every viewer) or "vtx" (ADIOS2 .bp)

    def __post_init__(self) -> None:
        checks.boolean("fields", self.fields)
        if self.format not in FIELD_FORMATS:
            raise ParameterError(f"format must be one of {', '.join(FIELD_FORMATS)} (got {self.format!r})")
        if not isinstance(self.probes, Sequence) or isinstance(self.probes, str):
            raise ParameterError(f"probes must be a list of points [x, y, z] (got {self.probes!r})")
        object.__setattr__(
            self, "probes", tuple(checks.vector(f"probes[{i}]", p, (2, 3)) for i, p in enumerate(self.probes))
        )


@dataclass(frozen=True)
class Scene:
    geometry: dict[str, Any]
    material: Material
    degree: int = 1
    plane: str | None = None  # of a 2-D mesh: "strain" or "stress"
    formulation: Formulation = field(default_factory=PureDisplacement)
    constraints: tuple = ()
    loads: tuple = ()
    stepping: Stepping = field(default_factory=Stepping)
    newton: NewtonOptions = field(default_factory=NewtonOptions)
    output: Output = field(default_factory=Output)
    inverse: InverseOptions | None = None  # the geometry is imaged under the loads of stepping.start
    title: str = ""
    folder: Path = Path(".")
    source: Path | None = None  # the scene file, when read from one
    table: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)  # as written (parsed TOML)
    parameters: tuple[Parameter, ...] = ()
    values: dict[str, float] = field(default_factory=dict)  # set with --set (others at their defaults)

    def law(self) -> Callable[[Mapping[str, float]], Material]:
        """The law as a function of the material targets' values by key (``{"c1": 300.0}``): the
        scene's [material] rebuilt with those values, so its own checks and derived constants hold."""
        return lambda keys: material(substituted(self.table["material"], keys, "material"))

    def with_values(self, given: dict[str, float]) -> Scene:
        """This scene with parameter values set (``--set name=value``), each checked against its range."""
        known = Parameters(self.parameters)
        current = known.values(given, start=self.values)
        return replace(self, values={name: current[name] for name in {*self.values, *given}})

    @property
    def inputs(self) -> list[Path]:
        """The files this scene reads: itself, its mesh (with the mesh's companion files) and data."""
        files = [self.source] if self.source is not None else []
        if "file" in self.geometry:
            mesh = Path(self.geometry["file"])
            files += [mesh] + [p for p in _geometry.companions(mesh) if p.exists()]
        if "shape_modes" in self.geometry:
            files.append(Path(self.geometry["shape_modes"]))
        files += list(cell_data(self.formulation).values())
        files += [
            Path(marker.path)
            for p in self.parameters
            if isinstance(marker := getattr(p.region, "marker", None), ImageLabel)
        ]
        return files


def load(path: str | Path) -> Scene:
    """Read and validate a scene file (UTF-8 TOML)."""
    path = Path(path)
    if path.is_dir():
        raise SceneError(f"scene file '{path}' is a folder; name a .toml file")
    if not path.is_file():
        raise SceneError(f"scene file '{path}' not found")
    try:
        data = path.read_bytes()
    except OSError as error:
        raise SceneError(f"cannot read scene file '{path}': {error.strerror or error}") from None
    if b"\0" in data:
        raise SceneError(f"scene file '{path}' is not a text file (it holds binary data); a scene is TOML text")
    try:
        text = data.decode("utf-8-sig")  # a byte-order mark, as some editors write, is not TOML
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise SceneError(
            f"scene file '{path}' is not UTF-8 text (byte 0x{data[error.start]:02x} on line {line}); save it as UTF-8"
        ) from None
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML ({error})") from None
    return parse(table, folder=path.parent, source=path)


def parse(table: dict[str, Any], folder: Path = Path("."), source: Path | None = None) -> Scene:
    """Validate a scene given as a dictionary (the parsed TOML)."""
    no_unknown_keys(table, SECTIONS, "scene")
    finite_numbers(table)
    for required in ("geometry", "material"):
        if required not in table:
            raise SceneError(f"scene: missing section [{required}]")
    formulation = dict(section(table, "formulation"))
    degree = typed(formulation.pop("degree", 1), int, "formulation.degree")
    kind = formulation.pop("type", "displacement")
    plane = formulation.pop("plane", None)
    if plane is not None and plane not in PLANES:
        raise SceneError(f"formulation.plane: 'strain' or 'stress' (got {plane!r}); a 3-D mesh takes none")
    if kind not in FORMULATIONS:
        raise SceneError(f"formulation.type: unknown type {kind!r} (available: {', '.join(FORMULATIONS)})")
    for key in getattr(FORMULATIONS[kind], "cellwise", ()):
        if isinstance(formulation.get(key), str):  # a file of cell values, next to the scene
            path = folder / formulation[key]
            if not path.is_file():
                raise SceneError(f"formulation.{key}: file '{path}' not found")
            formulation[key] = str(path)
    if formulation.get("imaged_porosity") is not None and "inverse" not in table:
        raise SceneError(
            "formulation.imaged_porosity: the porosity of an imaged lung needs [inverse] (the geometry is the "
            "imaged one, and its unloaded reference and solid fraction phi_s0 are found together); give "
            "phi_s0 instead for a reference geometry"
        )
    output = section(table, "output")
    return Scene(
        geometry=_geometry_spec(section(table, "geometry"), folder),
        material=material(section(table, "material")),
        degree=degree,
        plane=plane,
        formulation=call(FORMULATIONS[kind], formulation, "formulation"),
        constraints=tuple(_entries(table, "constraints", CONSTRAINTS)),
        loads=tuple(_entries(table, "loads", LOADS)),
        stepping=call(Stepping, with_tuple(section(table, "stepping"), "times"), "stepping"),
        newton=call(NewtonOptions, section(table, "solver"), "solver"),
        output=call(Output, with_tuple(output, "probes"), "output"),
        inverse=call(InverseOptions, section(table, "inverse"), "inverse") if "inverse" in table else None,
        parameters=parameters(table, folder),
        title=typed(table.get("title", ""), str, "title"),
        folder=folder,
        source=source,
        table=copy.deepcopy(table),
    )


def physics(scene: Scene) -> dict[str, Any]:
    """What a scene models, as plain values: its mesh's boundary names, law, formulation,
    constraints, loads, start time and [inverse]. Two scenes with the same physics may differ
    in title, outputs, stepping (but its start) and solver settings. Numbers are floats, and a
    file (of cell values, or a region's label image) is named by its SHA-256, not its path (a
    mesh is checked by its own fingerprint)."""
    table = copy.deepcopy(scene.table)
    described: dict[str, Any] = {
        key: table[key]
        for key in ("material", "formulation", "constraints", "loads", "inverse", "parameters")
        if key in table
    }
    described["geometry"] = {k: v for k, v in table.get("geometry", {}).items() if k != "file"}
    if "shape_modes" in scene.geometry:  # the library by its content, not its path
        described["geometry"]["shape_modes"] = file_sha256(Path(scene.geometry["shape_modes"]))
    described["stepping.start"] = scene.stepping.start
    if files := cell_data(scene.formulation):
        described["formulation"] = described["formulation"] | {key: file_sha256(path) for key, path in files.items()}
    for p in scene.parameters:
        if isinstance(marker := getattr(p.region, "marker", None), ImageLabel):
            described["parameters"][p.name]["region"]["image"] = file_sha256(Path(marker.path))
    return json.loads(json.dumps(described, default=str), parse_int=float)


def cell_data(formulation: Formulation) -> dict[str, Path]:
    """The formulation's values given by files of cell values (Φs0, κ, …), by key."""
    return {
        key: Path(value)
        for key in getattr(formulation, "cellwise", ())
        if isinstance(value := getattr(formulation, key), str | Path)
    }


def differences(built: dict[str, Any], given: dict[str, Any]) -> list[str]:
    """Where two physics descriptions (:func:`physics`) differ, one line each."""
    left, right = _flatten(built), _flatten(given)
    lines = []
    for key in sorted(set(left) | set(right)):
        if key not in right:
            lines.append(f"{key} = {left[key]!r} only in the model's scene")
        elif key not in left:
            lines.append(f"{key} = {right[key]!r} only in this scene")
        elif left[key] != right[key]:
            lines.append(f"{key}: {left[key]!r} in the model's scene, {right[key]!r} here")
    return lines


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        return {
            k: v for key, item in value.items() for k, v in _flatten(item, f"{prefix}.{key}" if prefix else key).items()
        }
    if isinstance(value, list) and any(isinstance(v, dict | list) for v in value):
        return {k: v for i, item in enumerate(value) for k, v in _flatten(item, f"{prefix}[{i}]").items()}
    return {prefix: value}


def file_sha256(path: str | Path) -> str:
    """A file's SHA-256 (hex): what its content is, wherever it lies."""
    return "sha256:" + hashlib.sha256(Path(path).read_bytes()).hexdigest()


def material(table: dict[str, Any], where: str = "material") -> Material:
    """A law from ``{law = name, <parameters>}``.

    Parameters are the law's own (e.g. mu, lmbda or c0, c1, c2), or E and nu (plus the law's
    optional shares), or ``incompressible = true`` with the shear parameters. ``law = "sum"``
    takes a list ``terms`` of such tables.
    """
    table = dict(table)
    name = table.pop("law", None)
    if name in COMPOSITE_LAWS:
        return call(COMPOSITE_LAWS[name], table, f"{where} (law '{name}')")
    if name == "sum":
        no_unknown_keys(table, ("terms",), where)
        terms = table.get("terms")
        if not isinstance(terms, list) or not terms:
            raise SceneError(f"{where}.terms: a sum needs a non-empty list of laws")
        return Sum(tuple(material(t, f"{where}.terms[{i}]") for i, t in enumerate(terms)))
    if name not in LAWS:
        available = ", ".join([*LAWS, *COMPOSITE_LAWS, "sum"])
        raise SceneError(f"{where}.law: unknown law {name!r} (available: {available})")
    cls = LAWS[name]
    if table.pop("incompressible", False):
        if not hasattr(cls, "incompressible"):
            raise SceneError(f"{where}.incompressible: law '{name}' has no incompressible variant")
        return call(cls.incompressible, table, where)
    if "E" in table or "nu" in table:
        if not hasattr(cls, "from_young"):
            raise SceneError(f"{where}: law '{name}' is not defined by E and nu")
        return call(cls.from_young, table, where)
    return call(cls, table, where)


def build_geometry(spec: dict[str, Any], comm: MPI.Comm) -> _geometry.Geometry:
    """The mesh a scene's [geometry] section describes (with ``shape_modes``: the modes'
    reference mesh, which :mod:`lungmech.app.template` moves to the library's mean shape)."""
    spec = dict(spec)
    spec.pop("shape_modes", None)
    if "file" in spec:
        return _geometry.from_file(spec.pop("file"), comm, spec.pop("boundaries", None))
    builder = BUILDERS[spec.pop("builder")]
    try:
        return builder(comm, **spec)
    except (TypeError, ValueError) as error:  # e.g. a string where a length belongs
        raise SceneError(f"geometry: bad value for the {builder.__name__} builder ({error})") from None


def _geometry_spec(table: dict[str, Any], folder: Path) -> dict[str, Any]:
    if ("file" in table) == ("builder" in table):
        raise SceneError("geometry: give exactly one of 'builder' (a generated mesh) or 'file' (a mesh file)")
    if "shape_modes" in table:  # a library's shape modes (lungmech shape-modes) of this mesh
        modes = Path(typed(table["shape_modes"], str, "geometry.shape_modes"))
        modes = modes if modes.is_absolute() else folder / modes
        if not modes.is_file():
            raise SceneError(f"geometry.shape_modes: shape modes file '{modes}' not found")
        shape = {"shape_modes": str(modes)}
        return _geometry_spec({k: v for k, v in table.items() if k != "shape_modes"}, folder) | shape
    if "file" in table:
        no_unknown_keys(table, ("file", "boundaries"), "geometry")
        typed(table["file"], str, "geometry.file")
        names = table.get("boundaries", {})
        if not isinstance(names, dict) or not all(
            isinstance(v, int) and not isinstance(v, bool) for v in names.values()
        ):
            raise SceneError(
                "geometry.boundaries: expected a table of boundary names and facet tags, e.g. { hilum = 4, pleura = 1 }"
            )
        path = Path(table["file"])
        path = path if path.is_absolute() else folder / path
        if path.is_dir():
            raise SceneError(f"geometry.file: '{path}' is a folder; name a mesh file (.msh, .vtu or .xdmf)")
        if not path.is_file():
            raise SceneError(f"geometry.file: mesh file '{path}' not found")
        return {**table, "file": str(path)}
    name = table["builder"]
    if name not in BUILDERS:
        raise SceneError(f"geometry.builder: unknown builder {name!r} (available: {', '.join(BUILDERS)})")
    parameters = {k: v for k, v in table.items() if k != "builder"}
    check_signature(BUILDERS[name], parameters, "geometry", skip=("comm",))
    return {"builder": name, **{k: tuple(v) if isinstance(v, list) else v for k, v in parameters.items()}}


def _entries(table: dict[str, Any], section: str, kinds: Mapping[str, Callable[..., Any]]) -> list:
    entries = table.get(section, [])
    if not isinstance(entries, list):
        raise SceneError(f"{section}: expected a list of tables ([[{section}]])")
    built = []
    for i, entry in enumerate(entries):
        where = f"{section}[{i}]"
        if not isinstance(entry, dict):
            raise SceneError(f"{where}: expected a table")
        entry = dict(entry)
        kind = entry.pop("type", None)
        if kind not in kinds:
            raise SceneError(f"{where}.type: unknown type {kind!r} (available: {', '.join(kinds)})")
        if "ramp" in entry:
            ramp = entry["ramp"]
            if not isinstance(ramp, dict):
                raise SceneError(f"{where}.ramp: expected a table {{times = [...], values = [...]}}")
            entry["ramp"] = call(Ramp, ramp, f"{where}.ramp")
        if isinstance(entry.get("value"), list):
            entry["value"] = tuple(entry["value"])
        built.append(call(kinds[kind], entry, where))
    return built
