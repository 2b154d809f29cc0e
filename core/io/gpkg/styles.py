"""Styles: QGIS's ``layer_styles`` table filled from Sylva's .qml files."""
from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Dict, Iterable

from ...errors import SylvaError

#: The .qml files that ``styles`` and Param.style name.
STYLES = Path(__file__).resolve().parents[3] / "resources" / "styles"


def _style_text(style) -> str:
    path = Path(style)
    if not path.is_absolute() and not path.exists():
        path = STYLES / style
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SylvaError(f"style {style}: cannot be read ({exc.strerror})") from None


def write_styles(con: sqlite3.Connection, styles: Dict[str, str]) -> None:
    """QGIS's ``layer_styles`` rows (one default style per layer) from .qml files; replaces earlier ones.

    The table has QGIS's schema (QgsOgrProvider's saveStyle) and is registered
    as an attributes table, as QGIS registers it.
    """
    if not styles:
        return
    exists = con.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'layer_styles'").fetchone()
    if not exists:
        con.execute(
            "CREATE TABLE layer_styles (id INTEGER PRIMARY KEY AUTOINCREMENT, f_table_catalog TEXT(256), "
            "f_table_schema TEXT(256), f_table_name TEXT(256), f_geometry_column TEXT(256), styleName TEXT(30), "
            "styleQML TEXT, styleSLD TEXT, useAsDefault BOOLEAN, description TEXT, owner TEXT(30), ui TEXT(30), "
            "update_time DATETIME DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')))")
        con.execute("INSERT OR REPLACE INTO gpkg_contents (table_name, data_type, identifier, description, srs_id) "
                    "VALUES ('layer_styles', 'attributes', 'layer_styles', '', 0)")
        con.execute("INSERT OR REPLACE INTO gpkg_ogr_contents (table_name, feature_count) "
                    "VALUES ('layer_styles', NULL)")
    geometry = dict(con.execute("SELECT table_name, column_name FROM gpkg_geometry_columns").fetchall())
    for layer, style in styles.items():
        qml = _style_text(style)
        con.execute("DELETE FROM layer_styles WHERE f_table_name = ?", (layer,))
        con.execute("INSERT INTO layer_styles (f_table_catalog, f_table_schema, f_table_name, f_geometry_column, "
                    "styleName, styleQML, styleSLD, useAsDefault, description, owner, ui) "
                    "VALUES ('', '', ?, ?, ?, ?, '', 1, ?, '', '')",
                    (layer, geometry.get(layer, ""), layer, qml, f"Sylva style {Path(style).name}"))
    con.execute("UPDATE gpkg_ogr_contents SET feature_count = (SELECT count(*) FROM layer_styles) "
                "WHERE table_name = 'layer_styles'")


def default_styles(layers: Iterable[str]) -> Dict[str, str]:
    """{layer: "<layer>.qml"} for the layers with a style of that name in :data:`STYLES`."""
    return {name: f"{name}.qml" for name in layers if (STYLES / f"{name}.qml").is_file()}
