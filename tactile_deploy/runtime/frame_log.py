"""``frames.csv``: one row per processed frame, written while the run goes on.

Columns: ``frame_index``, ``t_capture_ns`` (capture, wall clock, ns since the UNIX epoch),
``latency_ms`` (capture -> mesh), ``ood_score``, ``in_distribution`` (1/0),
``total_normal_force_n`` (empty with ``--no-forces``), ``source_label`` (an image folder's file
name), ``t_source_ns`` (the frame's time within its recording, ns from its first frame; empty
for a live camera), ``mesh_files`` (the files written for this frame, ``;``-separated, empty when
none), ``mesh_status`` (``written``, ``not requested`` (``--every``), ``no mesh files`` (no
``--out`` formats), or ``dropped: <reason>``).

Meshes are written by a background thread, so a row whose mesh is queued waits until the writer
says whether it was written; rows stay in frame order. The file is written under a temporary
name and renamed when the run ends.
"""

from __future__ import annotations

import os
from collections import deque
from pathlib import Path

HEADER = ("frame_index,t_capture_ns,latency_ms,ood_score,in_distribution,total_normal_force_n,"
          "source_label,t_source_ns,mesh_files,mesh_status")
#: ``mesh_status`` of a frame whose mesh waits for the writer.
PENDING = None


def csv_field(text: str) -> str:
    """``text`` as one CSV field (quoted when it holds a comma, quote or line break)."""
    if any(c in text for c in ',"\n\r'):
        return '"' + text.replace('"', '""') + '"'
    return text


class FrameLog:
    """frames.csv of a run in ``folder`` (module docstring). ``writer``: the run's
    :class:`~tactile_deploy.runtime.writers.MeshWriter`, whose ``results`` resolve pending rows."""

    def __init__(self, folder: Path, writer=None):
        self.path = Path(folder) / "frames.csv"
        self._tmp = Path(folder) / ".frames.csv.partial"
        self._f = open(self._tmp, "w", encoding="utf-8")
        self._f.write(HEADER + "\n")
        self.writer = writer
        self._rows: deque = deque()       # [index, text before the mesh columns, status]
        self._done: dict[int, str | None] = {}

    def add(self, frame, pred, force, latency_ms: float, mesh_status: str | None) -> None:
        """One processed frame; ``mesh_status`` PENDING when its mesh was queued."""
        f_txt = "" if force is None else f"{force.total_normal_force_n:.6g}"
        label = "" if frame.label is None else csv_field(frame.label)
        t_src = "" if frame.t_source_ns is None else str(int(frame.t_source_ns))
        text = (f"{frame.index},{frame.t_wall_ns},{latency_ms:.4f},{pred.ood_score:.6g},"
                f"{int(pred.in_distribution)},{f_txt},{label},{t_src}")
        self._rows.append([frame.index, text, mesh_status])
        self.flush()

    def flush(self, final: bool = False) -> None:
        """Write the rows whose mesh status is known (all of them when ``final``)."""
        w = self.writer
        while w is not None and w.results:
            index, reason = w.results.popleft()
            self._done[index] = reason
        while self._rows:
            index, text, status = self._rows[0]
            if status is PENDING:
                if index in self._done:
                    reason = self._done.pop(index)
                    status = "written" if reason is None else f"dropped: {reason}"
                elif final:
                    status = "dropped: the writer did not finish"
                else:
                    return
            files = ";".join(w.files_for(index)) if status == "written" else ""
            self._f.write(f"{text},{files},{csv_field(status)}\n")
            self._rows.popleft()

    def close(self) -> None:
        self.flush(final=True)
        self._f.close()
        os.replace(self._tmp, self.path)
