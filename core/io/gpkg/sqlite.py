"""SQLite for the GeoPackages written here: quoted identifiers, the page size, rows inserted many per statement."""
from __future__ import annotations

import sqlite3
from typing import List

#: Bound values per INSERT statement: SQLite's smallest default limit (SQLITE_MAX_VARIABLE_NUMBER before 3.32).
MAX_VARIABLES = 999
#: Page size of the files written here: a 3D model's ~75 kB blob spans 5 pages, not 19 (at 4096), for
#: ~4% more bytes (the half-filled last page of each blob).
PAGE_SIZE = 16384


def quote(name: str) -> str:
    """``name`` as an SQL identifier (double quotes, inner quotes doubled)."""
    return '"' + str(name).replace('"', '""') + '"'


def insert_rows(con: sqlite3.Connection, name: str, names: List[str], values: List[list], n: int) -> None:
    """INSERT ``n`` rows given as one list per column, many rows per statement.

    One ``INSERT ... VALUES (...), (...), ...`` of up to :data:`MAX_VARIABLES`
    values steps SQLite once for hundreds of rows: a tile's ~10^5 points
    cost a few thousand statement steps, not one each.  Rows keep their
    order, so their fids are 1..n in order.  Sylva, not in the paper.
    """
    if not names:
        con.executemany(f"INSERT INTO {quote(name)} DEFAULT VALUES", [()] * n)
        return
    width = len(names)
    flat = [None] * (n * width)
    for j, column in enumerate(values):
        flat[j::width] = column
    head = f"INSERT INTO {quote(name)} ({','.join(quote(c) for c in names)}) VALUES "
    row = "(" + ",".join("?" * width) + ")"
    per = max(1, MAX_VARIABLES // width)            # rows per statement
    whole = n - n % per                             # rows in statements of ``per`` rows; one more for the rest
    step = per * width
    if whole:
        con.executemany(head + ",".join([row] * per), (flat[i:i + step] for i in range(0, whole * width, step)))
    if whole < n:
        con.execute(head + ",".join([row] * (n - whole)), flat[whole * width:])
