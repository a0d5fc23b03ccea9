"""A GeoPackage read without GDAL: Python's sqlite3 and the geometry blob decoded by hand
(OGC 12-128r18, 2.1.3: "GP", version, flags, srs_id, envelope, then ISO WKB), to check
what pyogrio wrote against the standard rather than against the library that wrote it."""

from __future__ import annotations

import sqlite3
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import shapely

ENVELOPE_DOUBLES = {0: 0, 1: 4, 2: 6, 3: 6, 4: 8}
"""Flags bits 1-3 (envelope contents indicator) to the envelope's number of doubles."""


@dataclass
class Layer:
    name: str
    data_type: str  # "features" or "attributes"
    description: str
    srs_id: int | None
    geometry_column: str | None
    geometry_type: str | None
    rows: list[dict[str, Any]]
    geometries: list[shapely.Geometry]


def decode_geometry(blob: bytes, srs_id: int) -> shapely.Geometry:
    """A GeoPackage geometry blob as a shapely geometry; asserts its header: the magic,
    version 0, a standard (not extended) geometry of ``srs_id`` whose envelope holds it."""
    assert blob[:2] == b"GP" and blob[2] == 0
    flags = blob[3]
    assert not flags & 0b100000  # standard GeoPackage binary, not an extension
    order = "<" if flags & 1 else ">"
    envelope_kind = (flags >> 1) & 0b111
    (blob_srs,) = struct.unpack(order + "i", blob[4:8])
    assert blob_srs == srs_id
    n = ENVELOPE_DOUBLES[envelope_kind]
    envelope = struct.unpack(order + "d" * n, blob[8 : 8 + 8 * n])
    geometry = shapely.from_wkb(blob[8 + 8 * n :])
    assert bool(flags & 0b10000) == geometry.is_empty
    if n and not geometry.is_empty:
        minx, maxx, miny, maxy = envelope[:4]
        assert (minx, miny, maxx, maxy) == tuple(geometry.bounds)
    return geometry


def read_gpkg(path: Path) -> tuple[dict[str, Layer], dict[int, tuple[str, int, str]]]:
    """The layers of a GeoPackage by name, and its spatial reference systems (srs_id to
    organization, its id, the definition)."""
    connection = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        (application_id,) = connection.execute("PRAGMA application_id").fetchone()
        assert application_id == int.from_bytes(b"GPKG", "big")
        systems = {
            int(srs): (str(org), int(org_id), str(definition))
            for srs, org, org_id, definition in connection.execute(
                "SELECT srs_id, organization, organization_coordsys_id, definition "
                "FROM gpkg_spatial_ref_sys"
            )
        }
        columns = {
            table: (column, kind, srs)
            for table, column, kind, srs in connection.execute(
                "SELECT table_name, column_name, geometry_type_name, srs_id "
                "FROM gpkg_geometry_columns"
            )
        }
        layers: dict[str, Layer] = {}
        contents = connection.execute(
            "SELECT table_name, data_type, description, srs_id FROM gpkg_contents"
        ).fetchall()
        for table, data_type, description, srs_id in contents:
            column, kind, column_srs = columns.get(table, (None, None, None))
            if column is not None:
                assert column_srs == srs_id
            cursor = connection.execute(f'SELECT * FROM "{table}" ORDER BY rowid')
            names = [d[0] for d in cursor.description]
            rows, geometries = [], []
            for values in cursor:
                row = dict(zip(names, values, strict=True))
                if column is not None:
                    geometries.append(decode_geometry(row.pop(column), srs_id))
                rows.append(row)
            layers[table] = Layer(
                table, data_type, description or "", srs_id, column, kind, rows, geometries
            )
        return layers, systems
    finally:
        connection.close()
