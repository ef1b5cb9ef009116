"""ucad_catalog: the part-labelled catalogue (SQLite index + content-addressed artifacts).

Reader: ``ucad_catalog.open(path)`` -> :class:`CatalogReader` (``reader.py``), for consumers on
any machine: meshes by id (the content sha256, or a prefix of at least 8 hex digits), part
tables, cameras, one view at a time by index or angle, part masks, edges, features, exports.
Writer: :class:`Catalog` (``store.py``), used by the build driver. Nothing in this package
imports OpenCL; it needs NumPy and OpenEXR (pyarrow for Parquet exports). It installs on its own
(``pip install ./ucad_catalog``) or with the whole project. Layout and schema:
``ucad_catalog/SCHEMA.md``.
"""
__version__ = "0.1.0"

from ._db import SCHEMA_VERSION, CatalogError, options_hash  # noqa: E402
from .entry import CatalogEntry, MaterialRow, ViewRow  # noqa: E402
from .reader import (MIN_ID_PREFIX, CatalogReader, FeatureTable, MeshEntry,  # noqa: E402
                     MeshInfo, PartRow, ViewAngles, ViewInfo, ViewRecord)
from .store import Catalog  # noqa: E402


def open(path) -> CatalogReader:  # noqa: A001 - ucad_catalog.open(path), like gzip.open
    """Open the catalogue directory ``path`` for reading (see :class:`CatalogReader`)."""
    return CatalogReader(path)


__all__ = ["MIN_ID_PREFIX", "SCHEMA_VERSION", "Catalog", "CatalogEntry", "CatalogError",
           "CatalogReader", "FeatureTable", "MaterialRow", "MeshEntry", "MeshInfo", "PartRow",
           "ViewAngles", "ViewInfo", "ViewRecord", "ViewRow", "open", "options_hash"]
