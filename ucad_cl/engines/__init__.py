"""Build engines: where the per-mesh pipeline (``ucad_cl.pipeline``) runs. ``run_local`` (the
default, worker processes on this machine) and ``run_ray`` (Ray tasks on a cluster) both take
``todo`` = ``(MeshRef, force)`` pairs and call ``commit(entry)`` / ``skip(ref, sha)`` in the driver,
the catalogue's single writer; the policies are written once in ``ucad_cl.build``'s docstring.
"""
from .local import run_local
from .ray import run_ray

__all__ = ["run_local", "run_ray"]
