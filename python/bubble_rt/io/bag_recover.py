"""What is readable of a ROS 2 bag cut short (a recorder killed, a disk full), for ``rosbags``.

rosbags opens neither storage when the file is cut: an MCAP file needs its summary at the end
("File end magic is invalid") and sqlite refuses a file shorter than its header says
("database disk image is malformed"). :func:`readable_copy` rewrites the readable part of each
storage file into a folder (a temporary one, which the caller removes):

* MCAP: :func:`bubble_rt.io.mcap.recover` (every complete chunk; the ros2 profile is kept);
* sqlite3: the file is copied and padded with empty pages to the size its header states, so
  sqlite opens it; the small tables (topics, schema, metadata, definitions) are copied whole
  and the messages in id order up to the first damaged page (the rest is lost).

It needs as much free space as the readable part. The report says what was lost, counted
against the bag's metadata.yaml when it lists message counts.
"""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

SQLITE_MAGIC = b"SQLite format 3\x00"


def readable_copy(files: list[Path], out: Path) -> tuple[list[Path], str]:
    """(the rewritten storage files in ``out``, a report of what was lost) for a bag's
    storage ``files`` (.mcap and .db3). Raises ValueError when nothing is readable."""
    paths: list[Path] = []
    reports: list[str] = []
    for f in files:
        dst = out / f.name
        if f.suffix == ".mcap":
            from bubble_rt.io.mcap import recover

            reports.append(recover(f, dst).summary())
        elif f.suffix == ".db3":
            reports.append(_recover_db3(f, dst, out / f"{f.stem}.padded"))
        else:
            continue
        paths.append(dst)
    if not paths:
        raise ValueError("no .mcap or .db3 storage file to read")
    return paths, "; ".join(reports)


def _recover_db3(src: Path, dst: Path, scratch: Path) -> str:
    """Copy the readable rows of a cut sqlite3 bag file into ``dst``; the report."""
    with open(src, "rb") as fh:
        head = fh.read(100)
    if len(head) < 100 or not head.startswith(SQLITE_MAGIC):
        raise ValueError(f"{src.name}: not an sqlite3 file (or cut inside its header)")
    page = int.from_bytes(head[16:18], "big")
    page = 65536 if page == 1 else page
    pages = int.from_bytes(head[28:32], "big")
    size = src.stat().st_size
    shutil.copyfile(src, scratch)
    if pages * page > size:
        with open(scratch, "r+b") as fh:
            fh.truncate(pages * page)  # empty pages where the cut file ends
    old = sqlite3.connect(f"file:{scratch}?immutable=1", uri=True)
    new = sqlite3.connect(dst)
    try:
        objects = old.execute(
            "SELECT type, name, sql FROM sqlite_master WHERE sql IS NOT NULL ORDER BY type DESC"
        ).fetchall()  # tables before indexes
        tables = [n for t, n, _ in objects if t == "table"]
        for t, _, sql in objects:
            if t == "table":
                new.execute(sql)
        copied = 0
        for name in tables:
            cols = len(old.execute(f'SELECT * FROM "{name}" LIMIT 0').description)
            insert = f'INSERT INTO "{name}" VALUES ({", ".join("?" * cols)})'
            try:
                for row in old.execute(f'SELECT * FROM "{name}" ORDER BY rowid'):
                    new.execute(insert, row)
                    copied += name == "messages"
            except sqlite3.DatabaseError:
                pass  # the first damaged page: what follows it is lost
        for t, _, sql in objects:
            if t == "index":
                new.execute(sql)
        new.commit()
    finally:
        old.close()
        new.close()
        scratch.unlink(missing_ok=True)
    lost = f"{size} of {pages * page} bytes" if pages * page > size else "damaged"
    return f"{src.name}: cut ({lost}); read {copied} messages up to the first damaged page"
