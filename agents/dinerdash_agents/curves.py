"""The learning curves every training run writes beside its checkpoint: ``curve.csv`` (one row
per iteration or round) and ``curve.png`` (its score columns against the first)."""

from __future__ import annotations

import csv
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["CURVE_CSV", "CURVE_PNG", "read_curve", "write_curve"]

CURVE_CSV = "curve.csv"
CURVE_PNG = "curve.png"


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
