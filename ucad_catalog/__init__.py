"""ucad_catalog: the part-labelled catalogue (SQLite index + content-addressed artifacts).

Writer: :class:`Catalog` (``store.py``), used by the build driver. Reader: :class:`CatalogReader`
(``reader.py``), for consumers on any machine. Nothing in this package imports OpenCL.
Layout and schema: ``ucad_catalog/SCHEMA.md``.
"""
from ._db import SCHEMA_VERSION, CatalogError, options_hash
from .entry import CatalogEntry, MaterialRow, ViewRow
from .reader import CatalogReader, MeshInfo, PartRow, ViewRecord
from .store import Catalog

__all__ = ["SCHEMA_VERSION", "Catalog", "CatalogEntry", "CatalogError", "CatalogReader",
           "MaterialRow", "MeshInfo", "PartRow", "ViewRecord", "ViewRow", "options_hash"]
