"""Errors meant for people: the CLI prints their message and exits non-zero, no traceback."""


class LungmechError(Exception):
    """Base class of every error lungmech raises on bad input or a failed computation."""


class ParameterError(LungmechError, ValueError):
    """A physical or numerical parameter is out of its admissible range."""


class GeometryError(LungmechError):
    """A mesh file is missing or unreadable, or a boundary name is unknown."""


class SceneError(LungmechError):
    """A scene file has an unknown key or a bad value."""


class SolverError(LungmechError):
    """A nonlinear solve failed even at the smallest allowed load step."""


class ImageError(LungmechError):
    """An image file is missing or unreadable, or its mask is not a usable 3-D segmentation."""


class RegistrationError(LungmechError):
    """A shape registration or a shape-mode library cannot be computed from its input."""


class OutputError(LungmechError):
    """An output folder or file cannot be written without risking what is there, or at all."""


class ModelFileError(LungmechError):
    """A reduced-model file is missing, unreadable, or made for other physics than the scene's."""


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal (SIGINT: Ctrl-C, or SIGTERM); ``signum`` says which.

    A signal that arrives while PETSc calls back into Python (assembling a residual, say) is
    turned by petsc4py into a PETSc error; ``pending`` remembers it, and solvers call
    :meth:`raise_pending` after PETSc returns, so an interrupt is never mistaken for a failed
    Newton solve.

    While ``deferring`` (:func:`lungmech.parallel.collective.deferred`: collective writes, the
    swap of a finished result), a signal is only remembered in ``pending``; the ranks then
    agree at the block's end and raise together, so none is left waiting in a collective call
    and no file is left half-written.
    """

    pending: int | None = None
    deferring: int = 0  # nested deferred blocks

    def __init__(self, signum: int):
        import signal

        self.signum = signum
        self.name = signal.Signals(signum).name
        super().__init__(f"interrupted by {self.name}")

    @classmethod
    def raise_pending(cls) -> None:
        if cls.pending is not None:
            raise cls(cls.pending)
