"""The learning curves of every training run: ``curve.csv`` (one row per iteration or round) and
``curve.png`` (its score columns against the first), written into the checkpoint, and the live
curves (:class:`LiveCurves`), TensorBoard event files written as the run goes.

The event files go beside the checkpoint, not into it (a checkpoint directory is replaced whole
at every save): by default ``<parent>/tensorboard/<name>`` for a checkpoint ``<parent>/<name>``
(:func:`tensorboard_dir`), so that ``tensorboard --logdir <parent>/tensorboard`` shows every run
of a folder side by side. They are written with TensorBoard's own event-file writer, which needs
protobuf and numpy only (no torch, no TensorFlow), and only imported when a run writes them.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "CURVE_CSV",
    "CURVE_PNG",
    "FLUSH_SECONDS",
    "TENSORBOARD",
    "LiveCurves",
    "read_curve",
    "tensorboard_dir",
    "write_curve",
]

CURVE_CSV = "curve.csv"
CURVE_PNG = "curve.png"
#: The folder, beside a checkpoint, that holds the live curves of its folder's runs.
TENSORBOARD = "tensorboard"
#: Seconds between two flushes of the event files (and so at most between a value and the time
#: TensorBoard can show it).
FLUSH_SECONDS = 5.0
#: The names TensorBoard's event files begin with.
_EVENTS = "events.out.tfevents."


def write_curve(
    directory: str | Path,
    columns: Sequence[str],
    rows: Iterable[Sequence[Any] | Mapping[str, Any]],
    *,
    lines: Mapping[str, str],
    xlabel: str,
    ylabel: str,
    title: str,
    marker: str | None = None,
) -> None:
    """Writes ``rows`` (sequences in ``columns``' order, or mappings by column) to ``curve.csv``
    and, if there is any row, plots each column of ``lines`` (column -> legend label) against
    ``columns[0]`` to ``curve.png`` (a legend only with more than one line)."""
    directory = Path(directory)
    rows = [[row[c] for c in columns] if isinstance(row, Mapping) else list(row) for row in rows]
    with open(directory / CURVE_CSV, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        w.writerows(rows)
    if not rows:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [row[0] for row in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    for column, label in lines.items():
        k = list(columns).index(column)
        ax.plot(x, [row[k] for row in rows], marker=marker, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if len(lines) > 1:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(directory / CURVE_PNG)
    plt.close(fig)


def read_curve(directory: str | Path) -> list[dict[str, str]]:
    """The rows of a checkpoint's ``curve.csv``, by column."""
    with open(Path(directory) / CURVE_CSV, newline="") as f:
        return list(csv.DictReader(f))


def tensorboard_dir(out: str | Path, given: str | Path | None = None) -> Path:
    """Where the live curves of the run checkpointed to ``out`` go: ``given`` (``--tensorboard
    DIR``), else ``<out's parent>/tensorboard/<out's name>``."""
    if given is not None:
        return Path(given)
    out = Path(out)
    return out.parent / TENSORBOARD / out.name


class LiveCurves:
    """A run's TensorBoard event files: scalars by tag (``rollout/score``, ``train/entropy``,
    ...), one :meth:`add` per iteration, epoch or round, flushed every :data:`FLUSH_SECONDS` and
    at :meth:`close`. ``directory`` ``None``: nothing is written.

    A new run (``resumed`` false) removes the event files an earlier run left in ``directory``
    (as its checkpoint replaces the earlier one); a resumed run, continuing from its checkpoint's
    ``step``, adds its own file beside them, starting with TensorBoard's restart marker, so that
    the values the earlier process wrote after that step (after its last checkpoint) are dropped
    from the view, not drawn twice."""

    def __init__(
        self, directory: str | Path | None, *, resumed: bool = False, step: int = 0
    ) -> None:
        self.directory = None if directory is None else Path(directory)
        self._writer: Any = None
        if self.directory is None:
            return
        from tensorboard.compat.proto.event_pb2 import Event, SessionLog
        from tensorboard.compat.proto.summary_pb2 import Summary
        from tensorboard.summary.writer.event_file_writer import EventFileWriter

        self._event, self._summary = Event, Summary
        self.directory.mkdir(parents=True, exist_ok=True)
        if not resumed:
            for old in self.directory.glob(_EVENTS + "*"):
                old.unlink()
        self._writer = EventFileWriter(str(self.directory), flush_secs=FLUSH_SECONDS)
        if resumed:
            # A reader drops the values at and after the marker's step that came before it.
            start = SessionLog(status=SessionLog.START)
            marker = Event(wall_time=time.time(), step=step + 1, session_log=start)
            self._writer.add_event(marker)

    def add(self, step: int, scalars: Mapping[str, float | int | None]) -> None:
        """Writes ``scalars`` (tag -> value) at ``step``; ``None`` and non-finite values (a score
        before any episode ended) are left out."""
        if self._writer is None:
            return
        values = [
            self._summary.Value(tag=tag, simple_value=float(value))
            for tag, value in scalars.items()
            if value is not None and math.isfinite(float(value))
        ]
        if values:
            summary = self._summary(value=values)
            self._writer.add_event(self._event(wall_time=time.time(), step=step, summary=summary))

    def close(self) -> None:
        """Flushes and closes the event file (again: nothing)."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> LiveCurves:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
