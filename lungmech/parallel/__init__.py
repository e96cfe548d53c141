"""What makes lungmech MPI-correct: collective errors (``collective``), the one partition-independent
dof and node order (``layout``), the entries a rank owns (``owned``), distributed row-block linear algebra (``linalg``) and output
destinations that never touch a user's files (``destination``)."""

from lungmech.parallel.collective import arrive, deferred, on_root, raise_together, together

__all__ = ["arrive", "deferred", "on_root", "raise_together", "together"]
