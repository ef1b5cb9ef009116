"""ucad-cl: OpenCL batch processor turning vehicle CAD libraries into a part-labelled catalogue.

Stages (one module each): ingest -> filter -> cameras -> render -> edges -> segment -> classify
-> features/search -> catalogue. Data classes live in :mod:`ucad_cl.artifacts`.
"""
__version__ = "0.1.0"
